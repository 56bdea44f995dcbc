"""A map's field in parts: submaps, each its own field over its part of the floor.

One field for a whole floor gets less training time per room and more memory per metre as
the floor grows. So a survey longer than ``max_frames`` is cut into submaps by space: the
survey frames' camera positions are ordered along their principal direction and cut
into ``ceil(frames / max_frames)`` slabs of equal count (a survey walked room by room gives
about one submap a room). Each submap's *core* is its slab; it trains on the frames whose
camera stands in its core or within ``overlap_m`` of it, so neighbours share the views across
their boundary. Every submap's field is trained at the map's poses, which one pose graph and
one bundle adjustment solved over all keyframes: the submaps share one frame, and a run that
moves from one to the next renders from another field in the same frame (no jump in its
estimate, only in which field answers).

:class:`SubmapField` is the map's field: it renders from the submap whose core holds the point
``look_ahead_m`` along the camera's optical axis (what it mostly sees; the nearest core when
none does), and satisfies the field protocol, so a run, the relocaliser and the benchmarks take it
as any field. ``submaps.json`` in the map folder is its index; ``submaps/NN.pt`` its fields.
A survey of ``max_frames`` or fewer makes one submap, stored as the map's one ``field.pt``,
as before submaps. How a survey is cut: :func:`~nap3d_graph.mapping.submaps.plan_submaps`.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics, RenderedView
from nap3d_graph.textfiles import write_json_atomic

__all__ = ["SubmapSettings", "Submap", "SubmapField", "SUBMAPS_INDEX", "load_submap_field", "write_submaps_index"]

log = logging.getLogger(__name__)

#: The index of a map's submaps, in the map folder.
SUBMAPS_INDEX = "submaps.json"


@dataclass(frozen=True)
class SubmapSettings:
    """max_frames: survey frames per submap at most before the survey is cut (300: a room's
    survey, fr1/desk's 277 frames and the simulated room's 270 stay one submap); overlap_m: how
    far beyond its core a submap takes training frames; look_ahead_m: the point in front of the
    camera whose submap renders."""

    max_frames: int = 300
    overlap_m: float = 0.75
    look_ahead_m: float = 1.0

    def __post_init__(self):
        if self.max_frames < 2 or self.overlap_m < 0 or self.look_ahead_m < 0:
            raise ValueError(f"submaps need max_frames >= 2, overlap_m >= 0, look_ahead_m >= 0; got {self}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Submap:
    """``core`` (2,): its slab of the floor, ``[from, to]`` metres along ``axis`` (3,), the
    survey's principal direction in the map's frame (unbounded ends at -+inf); ``frames``: the
    survey frames it trains on. A map grown by another day's survey (:mod:`~nap3d_graph.mapping.extend`)
    holds submaps of several surveys, whose slabs lie along different axes: each submap then has
    ``look_points`` (M, 3), the points its training cameras looked at (``look_ahead_m`` along
    their optical axes, map frame), and ``survey``, the survey its frames index (0: the first)."""

    index: int
    axis: np.ndarray
    core: np.ndarray
    frames: np.ndarray
    survey: int = 0
    look_points: np.ndarray | None = None

    @property
    def file(self) -> str:
        return f"submaps/{self.index:02d}.pt"

    def distance_m(self, p_map: np.ndarray) -> float:
        """Metres along the axis from ``p_map`` (3,) to the core (0 inside)."""
        x = float(np.asarray(p_map, dtype=float) @ self.axis)
        return max(self.core[0] - x, x - self.core[1], 0.0)

    def to_dict(self) -> dict:
        out = {"index": self.index, "axis": [round(float(v), 6) for v in self.axis],
               "core": [_finite(v) for v in self.core], "frames": [int(i) for i in self.frames], "file": self.file}
        if self.look_points is not None:
            out.update(survey=self.survey, look_points=np.round(self.look_points, 3).tolist())
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "Submap":
        lo, hi = d["core"]
        core = np.array([-np.inf if lo is None else float(lo), np.inf if hi is None else float(hi)])
        look = d.get("look_points")
        return cls(int(d["index"]), np.asarray(d["axis"], dtype=float), core, np.asarray(d["frames"], dtype=int),
                   int(d.get("survey", 0)), None if look is None else np.asarray(look, dtype=float).reshape(-1, 3))


def _finite(v: float):
    return None if not np.isfinite(v) else round(float(v), 4)


class SubmapField:
    """The map's field over its submaps (see the module's text): ``fields`` and ``submaps`` in
    the same order; ``meta``: the map-wide record (capture timing, the field error a run widens
    its corrections by: the largest of the submaps', training frames and stamps of all)."""

    name = "submaps"

    def __init__(self, fields: list, submaps: list[Submap], settings: SubmapSettings | None = None):
        if not fields or len(fields) != len(submaps):
            raise ValueError(f"need one field per submap, got {len(fields)} fields for {len(submaps)} submaps")
        self.fields, self.submaps = list(fields), list(submaps)
        self.settings = settings or SubmapSettings()
        self.meta = _merged_meta(self.fields)
        self.last_submap: int | None = None

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) the union of the submaps' fields' bounds (metres)."""
        b = np.stack([np.asarray(f.bounds, dtype=float) for f in self.fields])
        return np.stack([b[:, 0].min(axis=0), b[:, 1].max(axis=0)])

    def submap_at(self, T_world_cam: np.ndarray) -> int:
        """The submap that renders a camera at ``T_world_cam`` (4, 4): the one whose core holds
        the point ``look_ahead_m`` along its optical axis, else the nearest core; in a map of
        several surveys (every submap with ``look_points``) the one whose training cameras looked
        nearest to that point."""
        T = np.asarray(T_world_cam, dtype=float)
        point = T[:3, 3] + T[:3, 2] * self.settings.look_ahead_m
        if all(s.look_points is not None and len(s.look_points) for s in self.submaps):
            return int(np.argmin([np.min(np.linalg.norm(s.look_points - point, axis=1)) for s in self.submaps]))
        return int(np.argmin([s.distance_m(point) for s in self.submaps]))

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        k = self.submap_at(T_world_cam)
        if k != self.last_submap and self.last_submap is not None:
            log.debug("rendering from submap %d (was %d)", k, self.last_submap)
        self.last_submap = k
        return self.fields[k].render(T_world_cam, intrinsics)

    def __repr__(self) -> str:
        return f"SubmapField({len(self.fields)} submaps of {type(self.fields[0]).__name__})"


def _merged_meta(fields: list) -> dict:
    """One record for a run from the submaps' records: the first one's (model, timing, source),
    the largest field error (a run widens its corrections by it: the worst submap sets the
    caution), and every submap's training frames and stamps."""
    metas = [dict(getattr(f, "meta", {}) or {}) for f in fields]
    meta = dict(metas[0])
    errors = [m.get("field_error") for m in metas if m.get("field_error")]
    if errors:
        worst = max(errors, key=lambda e: float(e.get("sigma_m", 0.0) or 0.0))
        meta["field_error"] = {k: v for k, v in worst.items() if k != "by_view"}
    for key in ("train_frames", "train_timestamps"):
        values = sorted({v for m in metas for v in m.get(key, [])})
        if values:
            meta[key] = values
    meta.pop("pose_corrections", None)
    meta["submaps"] = len(fields)
    return meta


def write_submaps_index(folder: Path, submaps: list[Submap], settings: SubmapSettings, extra: dict) -> None:
    """``submaps.json``: the settings, each submap (core, frames, field file) and ``extra``."""
    write_json_atomic(Path(folder) / SUBMAPS_INDEX, {"settings": settings.to_dict(),
                                                     "submaps": [s.to_dict() for s in submaps], **extra})


def load_submap_field(folder, load_field) -> SubmapField:
    """The :class:`SubmapField` of a map folder with ``submaps.json``, each submap's checkpoint
    opened by ``load_field`` (:func:`nap3d_graph.fields.load_field`); ``FileNotFoundError``
    naming what is missing."""
    folder = Path(folder)
    index = json.loads((folder / SUBMAPS_INDEX).read_text())
    submaps = [Submap.from_dict(d) for d in index["submaps"]]
    missing = [s.file for s in submaps if not (folder / s.file).is_file()]
    if missing:
        raise FileNotFoundError(f"{folder}: the map's submap fields {', '.join(missing)} are missing (its 'nap3d-graph "
                                "map' stopped in the field stage); run the same map command again to finish them")
    fields = [load_field(folder / s.file) for s in submaps]
    return SubmapField(fields, submaps, SubmapSettings(**index["settings"]))
