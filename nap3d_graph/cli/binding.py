"""Command-line options bound to settings by :class:`Option` rows: each names its flag, the
``section.setting`` it sets and how argparse reads it, never its default (that is the
setting's, unless the command line's differs). The rows are generated from the settings'
fields, which declare their flags (:func:`~nap3d_graph.arguments.setting`;
:func:`flag_options`), for a settings tree
(:class:`~nap3d_graph.run.settings.SettingsTree`) or for plain sections. :func:`add_options`
adds rows to a parser; :func:`settings_from_args` reads a tree back from the parsed options
over a base tree (a ``--config`` file's, for the settings with no flag), and
:func:`section_values` the sections' values; :func:`apply_settings` sets the options a config
file gives where the command line gave none.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from nap3d_graph.arguments import flagged
from nap3d_graph.run.settings import RunSettings, SettingsTree

__all__ = ["Option", "add_options", "apply_settings", "settings_from_args", "flag_options", "SectionDefaults",
           "section_values"]

_UNSET = object()


class Option:
    """One flag (or positional argument) bound to the setting at ``path``
    (``'section.setting'``); ``kwargs`` are argparse's (type, choices, action, help...).
    ``dest``: the parsed option's name when it is not the flag's; ``setting`` / ``option``:
    how a value goes from the parsed option to the tree and back when it is more than a path
    (text) or a vector (a list); ``default``: the command line's default where it is not the
    setting's (the map's matcher: chosen by the data)."""

    def __init__(self, flag: str, path: str, *, dest: str | None = None, setting: Callable | None = None,
                 option: Callable | None = None, default: Any = _UNSET, **kwargs: Any) -> None:
        self.flag, self.path, self.kwargs = flag, path, kwargs
        self.dest_name, self.setting, self.option, self.command_default = dest, setting, option, default

    def __repr__(self) -> str:
        return f"Option({self.flag!r}, {self.path!r})"

    @property
    def dest(self) -> str:
        return self.dest_name or self.flag.lstrip("-").replace("-", "_")

    def to_setting(self, value):
        """The option's value as the tree holds it (paths as text, vectors as lists)."""
        if self.setting is not None:
            return self.setting(value)
        if isinstance(value, Path):
            return str(value)
        return list(value) if isinstance(value, tuple) else value

    def to_option(self, value):
        """The setting's value as the parsed option holds it."""
        if self.option is not None:
            return self.option(value)
        return Path(value) if self.kwargs.get("type") is Path and value is not None else value

    def default_in(self, tree):
        """The option's default: the command line's own, else the setting's in ``tree`` (the
        defaults' tree)."""
        return self.command_default if self.command_default is not _UNSET else self.to_option(tree.get(self.path))


def flag_options(sections: type[SettingsTree] | dict[str, type], only_run: bool | None = None) -> tuple[Option, ...]:
    """The options of the fields that declare a flag (:func:`~nap3d_graph.arguments.setting`)
    in a settings tree's sections, or in ``sections`` (name -> dataclass), in section and field
    order (see :func:`~nap3d_graph.arguments.flagged` for ``only_run``)."""
    sections = sections if isinstance(sections, dict) else sections.SECTIONS
    return tuple(Option(flag["flag"], path, **({"default": flag["default"]} if "default" in flag else {}),
                        **flag["argparse"]) for path, flag in flagged(sections, only_run))


class SectionDefaults:
    """The defaults of settings ``sections`` (name -> dataclass) as :func:`add_options` asks
    them (``get('section.setting')``), for settings that are not a tree."""

    def __init__(self, sections: dict[str, type]):
        self.defaults = {name: kind() for name, kind in sections.items()}

    def get(self, path: str) -> Any:
        section, name = path.split(".")
        return getattr(self.defaults[section], name)


def section_values(args, options: tuple[Option, ...]) -> dict[str, dict[str, Any]]:
    """``{section: {setting: value}}`` of the parsed ``options`` (as the settings hold them)."""
    values: dict[str, dict[str, Any]] = {}
    for option in options:
        section, name = option.path.split(".")
        values.setdefault(section, {})[name] = option.to_setting(getattr(args, option.dest))
    return values


def add_options(parser, options: tuple[Option, ...], defaults=None) -> None:
    """Add ``options`` to ``parser``, each with its setting's default in ``defaults`` (a
    settings tree; default: the run's); the parser remembers them (``args.bound_options``)
    for :func:`settings_from_args`."""
    defaults = defaults if defaults is not None else RunSettings()
    for option in options:
        named = {"dest": option.dest_name} if option.dest_name and option.flag.startswith("-") else {}
        parser.add_argument(option.flag, default=option.default_in(defaults), **named, **option.kwargs)
    parser.set_defaults(bound_options=(parser.get_default("bound_options") or ()) + tuple(options))


def settings_from_args(args, base=None):
    """The settings tree of the parsed options: ``base`` (default: a ``--config`` file's tree,
    ``args.config_settings``, else the run's defaults) with every bound option's value."""
    base = base or getattr(args, "config_settings", None) or RunSettings()
    return base.replace({o.path: o.to_setting(getattr(args, o.dest)) for o in args.bound_options})


def apply_settings(args, settings, given: set[str]) -> None:
    """Set each bound option the command line did not give (``given``: argparse dests) from
    ``settings``, and keep the tree for the settings with no flag (``args.config_settings``)."""
    for option in args.bound_options:
        if option.dest not in given:
            setattr(args, option.dest, option.to_option(settings.get(option.path)))
    args.config_settings = settings
