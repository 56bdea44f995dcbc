"""A sweep's specification: recordings x field settings x run settings x seeds, from YAML.

``SWEEP.yaml``::

    recordings:                 # each one a recording split in time, or a map/query pair
      - data: data/room_a       # field on frames 0:split, correction on split:1
        split: 0.5              # (default 0.5)
      - name: yesterday_today   # default: the folder's name
        map: data/room_map      # field from one recording ...
        query: data/room_walk   # ... corrections on another
        map_frames: "0:0.5"     # optional, as --frames
        query_frames: null
    field:                      # train-field options; a list is a dimension of the grid
      model: [splat, grid]
      steps: 300
    run:                        # run options; a list is a dimension of the grid
      matcher: [sift, xfeat]
      odom: vo
    seeds: [0, 1]               # run --seed (the odometry noise); default [0]

Option names are the command's long options without the dashes (``keyframe_every`` or
``keyframe-every``); ``true`` gives a flag, ``false`` its ``--no-`` form or nothing. The
options a sweep sets itself (data, frames, field, out, seed) are refused; every cell's options
are checked with the command's own parser when the file is loaded, so a typo costs no run.
``model: none`` runs without a field (odometry only, a baseline), ``model: oracle`` with a
simulated room's exact field. A field is trained once per (recording, field settings) and
shared by every run that needs it.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

from nap3d_graph.datasets import source_of

__all__ = ["SweepError", "SweepSpec", "FieldTask", "Cell", "Recording"]

#: Options the sweep sets for each cell itself.
_RESERVED_RUN = {"data", "traj", "frames", "field", "out", "seed", "config", "write_bag", "viz", "max_frames_per_cell"}
_RESERVED_FIELD = {"data", "frames", "out", "force", "quiet"}
#: Field "models" that are not trained: no field at all, or a simulated room's exact one.
UNTRAINED = ("none", "oracle")


class SweepError(ValueError):
    """A sweep file that cannot be used; the message names the file and the key."""


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.=+-]+", "-", str(text)).strip("-")[:60] or "x"


def option_argv(options: dict) -> list[str]:
    """``{"keyframe_every": 5, "overlap": True}`` -> ``["--keyframe-every", "5", "--overlap"]``."""
    argv: list[str] = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if value is None:
            continue
        if value is True:
            argv.append(flag)
        elif value is False:
            argv.append("--no-" + key.replace("_", "-"))
        else:
            argv += [flag, str(value)]
    return argv


@dataclass(frozen=True)
class Recording:
    """Where a study's field comes from (``map``) and what it corrects (``query``)."""

    name: str
    map_data: str
    query_data: str
    map_frames: str | None
    query_frames: str | None
    topics: str | None = None


@dataclass(frozen=True)
class FieldTask:
    """One field to build: a recording's map part with one set of train-field options."""

    recording: Recording
    options: tuple  # ((key, value), ...) sorted

    @property
    def id(self) -> str:
        digest = hashlib.sha1(json.dumps([self.recording.name, self.recording.map_data, self.recording.map_frames,
                                          list(self.options)], default=str).encode()).hexdigest()[:8]
        parts = "_".join(f"{k}={_slug(v)}" for k, v in self.options) or "default"
        return f"{_slug(self.recording.name)}__{parts}__{digest}"

    @property
    def untrained(self) -> bool:
        """``model: none`` (no field: odometry only) or ``model: oracle`` (a simulated room's
        exact field): nothing to train."""
        return dict(self.options).get("model") in UNTRAINED

    @property
    def run_field(self) -> str | None:
        """What ``run --field`` takes for an untrained field ('none', 'oracle'), else None."""
        return dict(self.options).get("model") if self.untrained else None

    def argv(self, out_pt: Path) -> list[str]:
        argv = ["train-field", self.recording.map_data, "--out", str(out_pt), "--quiet"]
        if self.recording.map_frames:
            argv += ["--frames", self.recording.map_frames]
        if self.recording.topics:
            argv += ["--topics", self.recording.topics]
        return argv + option_argv(dict(self.options))


@dataclass(frozen=True)
class Cell:
    """One run: a recording's query part, a field, run options and a seed."""

    recording: Recording
    field: FieldTask
    options: tuple  # ((key, value), ...) sorted
    seed: int
    settings: tuple = field(default=())  # the swept values, for the tables: ((key, value), ...)

    @property
    def id(self) -> str:
        digest = hashlib.sha1(json.dumps([self.field.id, list(self.options), self.seed], default=str).encode()
                              ).hexdigest()[:8]
        swept = "_".join(f"{k}={_slug(v)}" for k, v in self.settings) or "run"
        return f"{_slug(self.recording.name)}__{swept}__seed{self.seed}__{digest}"

    def argv(self, field_path: Path | None, out_dir: Path) -> list[str]:
        data = self.recording.query_data

        argv = ["run", "--traj", source_of(data), "--data", data, "--field",
                self.field.run_field or str(field_path), "--seed", str(self.seed), "--out", str(out_dir)]
        if self.recording.query_frames:
            argv += ["--frames", self.recording.query_frames]
        if self.recording.topics:
            argv += ["--topics", self.recording.topics]
        return argv + option_argv(dict(self.options))

    def command(self, field_path: Path | None, out_dir: Path) -> str:
        """The shell command that reproduces the cell (its field built as the sweep built it)."""
        return " ".join(shlex.quote(a) for a in ["nap3d-graph", *self.argv(field_path, out_dir)])


def _grid(section: dict, where: str) -> list[dict]:
    """Every combination of a section's list values (scalars are fixed)."""
    if not isinstance(section, dict):
        raise SweepError(f"{where}: expected a mapping of options, got {type(section).__name__}")
    keys = [k.replace("-", "_") for k in section]
    values = [v if isinstance(v, list) else [v] for v in section.values()]
    if any(len(v) == 0 for v in values):
        raise SweepError(f"{where}: an empty list gives no cell")
    return [dict(zip(keys, combo)) for combo in itertools.product(*values)]


def _check_options(command: str, options: dict, reserved: set[str], where: str, check_argv) -> None:
    """Parse the options as the command's own parser would (``check_argv``, raising ValueError
    on a bad command line): unknown options and bad values now, not in a worker later."""
    taken = sorted(reserved & set(options))
    if taken:
        raise SweepError(f"{where}: {', '.join(taken)} are set by the sweep for each cell (use recordings: and seeds:)")
    if check_argv is None:
        return
    if dict(options).get("model") in UNTRAINED:
        options = {k: v for k, v in options.items() if k != "model"}
    base = ["train-field", "x", "--out", "x.pt"] if command == "train-field" else \
        ["run", "--traj", "sim", "--data", "x", "--field", "none"]
    try:
        check_argv(base + option_argv(options))
    except ValueError as exc:
        raise SweepError(f"{where}: {exc}") from None


@dataclass
class SweepSpec:
    recordings: list[Recording]
    field_grid: list[dict]
    run_grid: list[dict]
    seeds: list[int]
    path: Path | None = None

    @classmethod
    def load(cls, path, check_argv=None) -> "SweepSpec":
        """The sweep file at ``path``; ``check_argv(argv)`` (raising ValueError) checks each
        grid's options against the commands' parsers (the CLI passes its own)."""
        import yaml

        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except FileNotFoundError:
            raise SweepError(f"{path}: no such sweep file") from None
        except (OSError, yaml.YAMLError) as exc:
            raise SweepError(f"{path}: not a readable YAML file ({str(exc).splitlines()[0]})") from None
        return cls.from_dict(data, path, check_argv)

    @classmethod
    def from_dict(cls, data, path: Path | None = None, check_argv=None) -> "SweepSpec":
        where = str(path or "sweep")
        if not isinstance(data, dict):
            raise SweepError(f"{where}: expected a mapping with recordings, field, run and seeds")
        unknown = set(data) - {"recordings", "field", "run", "seeds"}
        if unknown:
            raise SweepError(f"{where}: unknown keys {sorted(unknown)} (known: recordings, field, run, seeds)")
        base = path.parent if path is not None else Path(".")
        recordings = [_recording(r, base, f"{where}: recordings[{i}]") for i, r in enumerate(data.get("recordings") or [])]
        if not recordings:
            raise SweepError(f"{where}: no recordings")
        names = [r.name for r in recordings]
        if len(set(names)) != len(names):
            raise SweepError(f"{where}: two recordings share a name ({names}); give each a name:")
        field_grid = _grid(data.get("field") or {}, f"{where}: field")
        run_grid = _grid(data.get("run") or {}, f"{where}: run")
        for options in field_grid:
            _check_options("train-field", options, _RESERVED_FIELD, f"{where}: field", check_argv)
        for options in run_grid:
            _check_options("run", options, _RESERVED_RUN, f"{where}: run", check_argv)
        seeds = data.get("seeds", [0])
        seeds = seeds if isinstance(seeds, list) else [seeds]
        if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
            raise SweepError(f"{where}: seeds must be a list of integers, got {seeds!r}")
        return cls(recordings, field_grid, run_grid, seeds, path)

    def swept_keys(self) -> list[str]:
        """The settings that take more than one value (the tables' columns)."""
        keys = []
        for grid, prefix in ((self.field_grid, "field."), (self.run_grid, "")):
            for key in (grid[0] if grid else {}):
                if len({json.dumps(g[key], default=str) for g in grid}) > 1:
                    keys.append(prefix + key)
        return keys

    def fields(self) -> list[FieldTask]:
        return [FieldTask(r, tuple(sorted(f.items()))) for r in self.recordings for f in self.field_grid]

    def cells(self) -> list[Cell]:
        swept = self.swept_keys()
        cells = []
        for task in self.fields():
            for options in self.run_grid:
                settings = tuple((k, dict(task.options)[k[6:]]) if k.startswith("field.") else (k, options[k])
                                 for k in swept)
                for seed in self.seeds:
                    cells.append(Cell(task.recording, task, tuple(sorted(options.items())), int(seed), settings))
        ids = [c.id for c in cells]
        assert len(set(ids)) == len(ids), "two cells with one folder"
        return cells


def _recording(entry, base: Path, where: str) -> Recording:
    if not isinstance(entry, dict):
        raise SweepError(f"{where}: expected a mapping (data: PATH, or map: PATH and query: PATH)")
    unknown = set(entry) - {"name", "data", "split", "map", "query", "map_frames", "query_frames", "topics"}
    if unknown:
        raise SweepError(f"{where}: unknown keys {sorted(unknown)}")

    def resolve(key):
        value = Path(str(entry[key])).expanduser()
        value = value if value.is_absolute() else (base / value)
        if not value.exists():
            raise SweepError(f"{where}: {key}: {value} does not exist")
        return str(value.resolve())

    if "data" in entry:
        if "map" in entry or "query" in entry:
            raise SweepError(f"{where}: give data: (split in time) or map: and query:, not both")
        split = float(entry.get("split", 0.5))
        if not 0.05 <= split <= 0.95:
            raise SweepError(f"{where}: split must be in [0.05, 0.95], got {split}")
        data = resolve("data")
        return Recording(str(entry.get("name") or Path(data).name), data, data, f"0:{split}", f"{split}:1",
                         entry.get("topics"))
    if "map" not in entry or "query" not in entry:
        raise SweepError(f"{where}: needs data: PATH, or both map: PATH and query: PATH")
    map_data, query_data = resolve("map"), resolve("query")
    name = entry.get("name") or f"{Path(map_data).name}-to-{Path(query_data).name}"
    return Recording(str(name), map_data, query_data, entry.get("map_frames"), entry.get("query_frames"),
                     entry.get("topics"))
