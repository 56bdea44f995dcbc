"""``run --config config.yaml``: a run reproduced from the configuration another run wrote.

Every run writes ``config.yaml`` (:mod:`nap3d_graph.run.output`): its settings tree
(:class:`~nap3d_graph.run.settings.RunSettings`, under ``settings``) as the run resolved it,
and what it found beside it (under ``resolved``: the frames read, the field's error, the
pipeline's configuration as used...). Reading it back sets every option the command line did
not give from the tree (a flag given wins over the file, even when it gives the option's
default) and keeps the tree for the settings with no flag; the options and the tree are bound
by the fields of the tree, which declare their flags (:mod:`nap3d_graph.cli.run_options`).
"""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.run.settings import RunSettings, SettingsError

from .binding import apply_settings
from .common import UsageError

__all__ = ["apply_config", "apply_run_config", "load_config_file"]


def load_config_file(path: Path, section: str, command: str, older_section: str | None = None) -> dict:
    """The mapping a ``command``'s ``config.yaml`` holds, which must have a ``section``
    mapping (one-line errors for a bad file; ``older_section``: the section a config.yaml of
    an older version held instead, said as such)."""
    import yaml

    try:
        config = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise UsageError(f"--config {path}: file not found") from None
    except (OSError, yaml.YAMLError) as exc:
        raise UsageError(f"--config {path}: not a readable YAML file ({str(exc).splitlines()[0]})") from None
    if isinstance(config, dict) and isinstance(config.get(section), dict):
        return config
    if older_section is not None and isinstance(config, dict) and isinstance(config.get(older_section), dict):
        raise UsageError(f"--config {path}: written by an older nap3d-graph (a '{older_section}' section, no "
                         f"{section} tree); run it again with the flags it lists, once, to write a config.yaml "
                         "this version reads")
    raise UsageError(f"--config {path}: not a {command}'s config.yaml (no '{section}' section)")


def _given(args, parser) -> set[str]:
    """The options the command line gave (``args.given``, set by the CLI's ``main``); without
    it, those whose value differs from the default."""
    given = getattr(args, "given", None)
    if given is not None:
        return set(given)
    return {dest for dest, value in vars(args).items() if value != parser.get_default(dest)}


def apply_config(args, path: Path, tree: type, command: str, older_section: str | None = None) -> None:
    """Set ``args`` from the settings tree (of class ``tree``) in ``command``'s config.yaml at
    ``path`` where the command line did not give an option; the whole tree goes to
    ``args.config_settings`` (the settings with no flag come from it)."""
    config = load_config_file(path, "settings", command, older_section)
    try:
        settings = tree.from_dict(config["settings"])  # type: ignore[attr-defined]
    except (SettingsError, ValueError) as exc:  # ValueError: a section's own check (StudyConfig's split)
        raise UsageError(f"--config {path}: {exc}") from None
    apply_settings(args, settings, _given(args, args.parser))


def apply_run_config(args, path: Path) -> None:
    """``run --config``: the run's settings tree from ``path`` (a config.yaml from before the
    tree held a 'pipeline' section)."""
    apply_config(args, path, RunSettings, "run", older_section="pipeline")
