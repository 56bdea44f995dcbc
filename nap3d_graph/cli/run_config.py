"""``run --config config.yaml``: a run reproduced from the configuration another run wrote.

Every run writes ``config.yaml`` (:mod:`nap3d_graph.run.output`): its settings tree
(:class:`~nap3d_graph.run.settings.RunSettings`, under ``settings``) as the run resolved it,
and what it found beside it (under ``resolved``: the frames read, the field's error, the
pipeline's configuration as used...). Reading it back sets every option the command line did
not give from the tree (a flag given wins over the file, even when it gives the option's
default) and keeps the tree for the settings with no flag; the options and the tree are bound
by one table (:mod:`nap3d_graph.cli.run_options`).
"""

from __future__ import annotations

from pathlib import Path

from .common import UsageError

__all__ = ["apply_run_config", "load_config_file", "set_unless_given"]


def load_config_file(path: Path, section: str, command: str) -> dict:
    """The mapping a ``command``'s ``config.yaml`` holds, which must have a ``section``
    mapping (one-line errors for a bad file)."""
    import yaml

    try:
        config = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise UsageError(f"--config {path}: file not found") from None
    except (OSError, yaml.YAMLError) as exc:
        raise UsageError(f"--config {path}: not a readable YAML file ({str(exc).splitlines()[0]})") from None
    if not isinstance(config, dict) or not isinstance(config.get(section), dict):
        raise UsageError(f"--config {path}: not a {command}'s config.yaml (no '{section}' section)")
    return config


def _given(args, parser) -> set[str]:
    """The options the command line gave (``args.given``, set by the CLI's ``main``); without
    it, those whose value differs from the default."""
    given = getattr(args, "given", None)
    if given is not None:
        return set(given)
    return {dest for dest, value in vars(args).items() if value != parser.get_default(dest)}


def set_unless_given(args, parser, values: dict) -> None:
    """Set each option of ``values`` the command line did not give (flags win)."""
    given = _given(args, parser)
    for dest, value in values.items():
        if hasattr(args, dest) and dest not in given:
            setattr(args, dest, value)


def apply_run_config(args, path: Path) -> None:
    """Set ``args`` from the run configuration at ``path`` where the command line did not give
    an option; the file's whole tree goes to ``args.config_settings`` (the settings with no
    flag come from it)."""
    from nap3d_graph.run.settings import RunSettings, SettingsError

    from .binding import apply_settings

    try:
        config = load_config_file(path, "settings", "run")
    except UsageError as exc:
        if "'settings'" in str(exc) and _has_old_layout(path):
            raise UsageError(f"--config {path}: written by an older nap3d-graph (a 'pipeline' section, no settings "
                             "tree); run it again with the flags it lists, once, to write a config.yaml this "
                             "version reads") from None
        raise
    try:
        settings = RunSettings.from_dict(config["settings"])
    except SettingsError as exc:
        raise UsageError(f"--config {path}: {exc}") from None
    apply_settings(args, settings, _given(args, args.parser))


def _has_old_layout(path: Path) -> bool:
    """Whether ``path`` is a run's config.yaml from before the settings tree."""
    import yaml

    config = yaml.safe_load(Path(path).read_text())
    return isinstance(config, dict) and isinstance(config.get("pipeline"), dict)
