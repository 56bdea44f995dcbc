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
from collections import OrderedDict
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from nap3d_graph.arguments import positive_float, positive_int, setting
from nap3d_graph.camera import Intrinsics, RenderedView, backproject
from nap3d_graph.textfiles import write_json_atomic

__all__ = ["SubmapSettings", "Submap", "SubmapField", "FramedField", "SUBMAPS_INDEX", "load_submap_field", "write_submaps_index"]

log = logging.getLogger(__name__)

#: The index of a map's submaps, in the map folder.
SUBMAPS_INDEX = "submaps.json"
#: A render that leaves more than this share of its pixels empty is filled from the submap
#: further along the camera's view (a view down a row of rooms sees past its submap's field).
EMPTY_SHARE_TO_FILL = 0.02
#: How far along the empty pixels' mean ray the submaps that fill them are looked for (metres:
#: a room's far wall, the next room's, the one after; each submap rendered once).
FILL_FROM_M = (4.0, 8.0, 12.0)


@dataclass(frozen=True)
class SubmapSettings:
    """max_frames: survey frames per submap at most before the survey is cut (300: a room's
    survey, fr1/desk's 277 frames and the simulated room's 270 stay one submap); overlap_m: how
    far beyond its core a submap takes training frames; look_ahead_m: the point in front of the
    camera whose submap renders; resident: submap fields a run keeps loaded at once (the rest
    are read again when rendered); reach_m: how far beyond its core a submap's field reaches
    (what a camera up to ``look_ahead_m`` outside the core sees in front of it): its grid covers
    its part of the floor, not the next rooms its cameras saw through the doors, which would
    stretch it down the floor (a middle room's grid of the 6-room floor ran 22 m, 620 MB);
    max_length_m: a cut survey's submap cores no longer than this along the floor (a one-room
    field's span: the simulated room's grid is 5.7 m along it): where the survey crossed rooms
    quickly, as many frames lay along 10 m and that submap's grid, twice a room's, was the map's
    and the run's peak memory.
    viewing_frames: survey frames whose camera stood outside a submap but whose depth saw into its
    core (at least ``viewing_share`` of their sampled depth points there) that it trains on too,
    this many at most, those that saw most of it first (their depth outside its slab masked as
    every frame's is; 0: its own cameras' frames alone). A camera looks down a row of rooms at
    the far walls and the ceiling, which its own submap's grid does not hold, while the cameras
    that stood under that ceiling looked at the floor and walls around them: trained by its own
    cameras alone, no field of the 6-room floor held what the upper fifth of a view along the
    floor saw, and such views rendered 15-18 dB where a room's own views render 27."""

    max_frames: int = setting(300, "--submap-frames", type=positive_int, metavar="N",
        help="a survey of more than N frames is cut by space into submaps of about N frames, each its own field "
             "over its own part of the floor and its own training budget, under the one pose graph (default "
             "%(default)s: a room's survey stays one field)")
    overlap_m: float = 0.75
    look_ahead_m: float = 1.0
    resident: int = 2
    reach_m: float = 1.5
    max_length_m: float = setting(6.0, "--submap-length", type=positive_float, metavar="M",
        help="a cut survey's submaps are at most M metres along the floor, however few frames lie there (default "
             "%(default)s: a room; a field's memory grows with the space it covers)")
    viewing_frames: int = 150
    viewing_share: float = 0.1

    def __post_init__(self):
        if (self.max_frames < 2 or self.overlap_m < 0 or self.look_ahead_m < 0 or self.resident < 1
                or self.reach_m < 0 or not self.max_length_m > 0 or self.viewing_frames < 0
                or not 0 < self.viewing_share <= 1):
            raise ValueError(f"submaps need max_frames >= 2, overlap_m >= 0, look_ahead_m >= 0, resident >= 1, "
                             f"reach_m >= 0, max_length_m > 0, viewing_frames >= 0 and 0 < viewing_share <= 1; "
                             f"got {self}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SubmapSettings":
        """The settings an index holds (a key another version wrote and this one lacks ignored)."""
        return cls(**{f.name: d[f.name] for f in fields(cls) if f.name in d})


@dataclass
class Submap:
    """``core`` (2,): its slab of the floor, ``[from, to]`` metres along ``axis`` (3,), the
    survey's principal direction in the map's frame (unbounded ends at -+inf); ``frames``: the
    survey frames it trains on. A map grown by another day's survey (:mod:`~nap3d_graph.mapping.extend`)
    holds submaps of several surveys, whose slabs lie along different axes: each submap then has
    ``look_points`` (M, 3), the points its training cameras looked at (``look_ahead_m`` along
    their optical axes, map frame), and ``survey``, the survey its frames index (0: the first).
    ``R_grid_map`` (3, 3): the rotation into the frame its field's grid is trained in (rows: the
    grid's axes in the map's frame; level and along the floor, so the grid's box holds its part of
    the floor and not the tilt of the first camera's frame: in that frame one submap of the
    3-room floor was a 7 x 9 x 15 m grid, 1.6 GB, its worker 9.7 GB); None: the map's own frame."""

    index: int
    axis: np.ndarray
    core: np.ndarray
    frames: np.ndarray
    survey: int = 0
    look_points: np.ndarray | None = None
    R_grid_map: np.ndarray | None = None

    @property
    def file(self) -> str:
        return f"submaps/{self.index:02d}.pt"

    def distance_m(self, p_map: np.ndarray) -> float:
        """Metres along the axis from ``p_map`` (3,) to the core (0 inside)."""
        x = float(np.asarray(p_map, dtype=float) @ self.axis)
        return max(self.core[0] - x, x - self.core[1], 0.0)

    def slab_m(self, reach_m: float) -> tuple | None:
        """The slab its field trains in (:class:`~nap3d_graph.fields.train_config.TrainConfig`'s
        ``slab_m``, in its grid's frame): its core and ``reach_m`` beyond, along its axis; None for
        a core unbounded both ways (a map of one submap)."""
        if not np.isfinite(self.core).any():
            return None
        a = self.axis if self.R_grid_map is None else self.R_grid_map @ self.axis
        lo, hi = self.core[0] - reach_m, self.core[1] + reach_m
        return (*(float(v) for v in a), float(lo) if np.isfinite(lo) else None, float(hi) if np.isfinite(hi) else None)

    def to_dict(self) -> dict:
        out = {"index": self.index, "axis": [round(float(v), 6) for v in self.axis],
               "core": [_finite(v) for v in self.core], "frames": [int(i) for i in self.frames], "file": self.file}
        if self.look_points is not None:
            out.update(survey=self.survey, look_points=np.round(self.look_points, 3).tolist())
        if self.R_grid_map is not None:
            out["R_grid_map"] = np.round(self.R_grid_map, 9).tolist()
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "Submap":
        lo, hi = d["core"]
        core = np.array([-np.inf if lo is None else float(lo), np.inf if hi is None else float(hi)])
        look, R = d.get("look_points"), d.get("R_grid_map")
        return cls(int(d["index"]), np.asarray(d["axis"], dtype=float), core, np.asarray(d["frames"], dtype=int),
                   int(d.get("survey", 0)), None if look is None else np.asarray(look, dtype=float).reshape(-1, 3),
                   None if R is None else np.asarray(R, dtype=float).reshape(3, 3))


def _finite(v: float):
    return None if not np.isfinite(v) else round(float(v), 4)


class FramedField:
    """A field trained in another frame (a submap's grid frame, ``R_grid_map`` (3, 3)) answering
    in the map's: it renders the camera at ``R_grid_map @ T_map_cam``; depth and colour are the
    camera's own, so the render is the same in either frame. ``bounds``: the box of its grid's
    bounds in the map's frame (metres)."""

    def __init__(self, field, R_grid_map: np.ndarray):
        self.field = field
        self.T_grid_map = np.eye(4)
        self.T_grid_map[:3, :3] = np.asarray(R_grid_map, dtype=float)
        self.meta = getattr(field, "meta", {})
        self.name = getattr(field, "name", type(field).__name__)

    @property
    def bounds(self) -> np.ndarray:
        lo, hi = np.asarray(self.field.bounds, dtype=float)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        in_map = corners @ self.T_grid_map[:3, :3]  # R^T applied to each corner: grid -> map
        return np.stack([in_map.min(axis=0), in_map.max(axis=0)])

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        return self.field.render(self.T_grid_map @ np.asarray(T_world_cam, dtype=float), intrinsics)

    def __repr__(self) -> str:
        return f"FramedField({self.field!r})"


class SubmapField:
    """The map's field over its submaps (see the module's text), ``submaps`` in order, each
    field given loaded (``fields``) or read when first rendered (:meth:`lazy`): a run across a
    floor keeps ``settings.resident`` of them in memory, the ones it rendered from last, so its
    memory does not grow with the floor. ``meta``: the map-wide record (capture timing, the
    field error a run widens its corrections by: the largest of the submaps', training frames
    and stamps of all)."""

    name = "submaps"

    def __init__(self, fields: list, submaps: list[Submap], settings: SubmapSettings | None = None):
        self._set_up([(lambda f=f: f) for f in fields], [getattr(f, "meta", {}) for f in fields],
                     [f.bounds for f in fields], submaps, settings)

    @classmethod
    def lazy(cls, loaders: list, submaps: list[Submap], settings: SubmapSettings | None = None) -> "SubmapField":
        """The map's field with each submap's field read by ``loaders[k]()`` when it is needed:
        each is read once here for its record and bounds (one at a time), then again when a
        render needs it and it is not among the ``resident`` kept."""
        metas, bounds = [], []
        for load in loaders:
            field = load()
            metas.append(getattr(field, "meta", {}))
            bounds.append(field.bounds)
            del field
        self = cls.__new__(cls)
        self._set_up(loaders, metas, bounds, submaps, settings)
        return self

    def _set_up(self, loaders: list, metas: list, bounds: list, submaps: list[Submap],
                settings: SubmapSettings | None) -> None:
        if not loaders or len(loaders) != len(submaps):
            raise ValueError(f"need one field per submap, got {len(loaders)} fields for {len(submaps)} submaps")
        self.submaps, self.settings = list(submaps), settings or SubmapSettings()
        self._loaders, self._loaded = list(loaders), OrderedDict()
        self._bounds = [np.asarray(b, dtype=float) for b in bounds]
        self.meta, self.last_submap = _merged_meta(metas, len(loaders)), None

    def field_of(self, k: int):
        """Submap ``k``'s field, read if it is not loaded; the least recently used one is let go
        when more than ``settings.resident`` would be loaded."""
        if k in self._loaded:
            self._loaded.move_to_end(k)
            return self._loaded[k]
        # Let go first: a field read while ``resident`` others are held would peak at one more.
        while len(self._loaded) >= self.settings.resident:
            self._loaded.popitem(last=False)
        field = self._loaders[k]()
        self._loaded[k] = field
        return field

    @property
    def fields(self) -> list:
        """Every submap's field (reads each that is not loaded, keeping none of them resident)."""
        return [self._loaded[k] if k in self._loaded else self._loaders[k]() for k in range(len(self.submaps))]

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) the union of the submaps' fields' bounds (metres, map frame)."""
        b = np.stack(self._bounds)
        return np.stack([b[:, 0].min(axis=0), b[:, 1].max(axis=0)])

    def submap_at(self, T_world_cam: np.ndarray) -> int:
        """The submap that renders a camera at ``T_world_cam`` (4, 4): the one that holds the
        point ``look_ahead_m`` along its optical axis (:meth:`submap_holding`)."""
        T = np.asarray(T_world_cam, dtype=float)
        return self.submap_holding(T[:3, 3] + T[:3, 2] * self.settings.look_ahead_m)

    def submap_holding(self, point_map: np.ndarray) -> int:
        """The submap whose core holds ``point_map`` (3,), else the nearest core; in a map of
        several surveys (every submap with ``look_points``) the one whose training cameras looked
        nearest to it."""
        point = np.asarray(point_map, dtype=float)
        if all(s.look_points is not None and len(s.look_points) for s in self.submaps):
            return int(np.argmin([np.min(np.linalg.norm(s.look_points - point, axis=1)) for s in self.submaps]))
        return int(np.argmin([s.distance_m(point) for s in self.submaps]))

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        """The view from the submap the camera looks into; where that submap's field ends and the
        camera sees further (through a doorway, down the floor), the pixels it left empty come
        from the submaps that hold the points ``FILL_FROM_M`` along their mean ray."""
        k = self.submap_at(T_world_cam)
        if k != self.last_submap and self.last_submap is not None:
            log.debug("rendering from submap %d (was %d)", k, self.last_submap)
        self.last_submap = k
        view = self.field_of(k).render(T_world_cam, intrinsics)
        if len(self.submaps) < 2:
            return view
        T = np.asarray(T_world_cam, dtype=float)
        tried = {k}
        for far_m in FILL_FROM_M:
            empty = view.opacity < 0.5
            if empty.mean() <= EMPTY_SHARE_TO_FILL:
                break
            v, u = np.nonzero(empty)
            ray = backproject(np.stack([u, v], 1), np.ones(len(u)), intrinsics)
            ray = (ray / np.linalg.norm(ray, axis=1, keepdims=True)).mean(axis=0)
            other = self.submap_holding(T[:3, 3] + T[:3, :3] @ ray * (far_m / np.linalg.norm(ray)))
            if other in tried:
                continue
            tried.add(other)
            beyond = self.field_of(other).render(T_world_cam, intrinsics)
            fill = empty & (beyond.opacity >= 0.5)
            view = RenderedView(np.where(fill[..., None], beyond.rgb, view.rgb), np.where(fill, beyond.depth_m, view.depth_m),
                                np.where(fill, beyond.opacity, view.opacity), view.intrinsics)
        return view

    def __repr__(self) -> str:
        return f"SubmapField({len(self.submaps)} submaps)"


def _merged_meta(metas: list[dict], submaps: int) -> dict:
    """One record for a run from the submaps' records: the first one's (model, timing, source),
    the largest field error (a run widens its corrections by it: the worst submap sets the
    caution), and every submap's training frames and stamps."""
    metas = [dict(m or {}) for m in metas]
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
    meta["submaps"] = submaps
    return meta


def write_submaps_index(folder: Path, submaps: list[Submap], settings: SubmapSettings, extra: dict) -> None:
    """``submaps.json``: the settings, each submap (core, frames, field file) and ``extra``."""
    write_json_atomic(Path(folder) / SUBMAPS_INDEX, {"settings": settings.to_dict(),
                                                     "submaps": [s.to_dict() for s in submaps], **extra})


def _file_state(path: Path) -> tuple:
    """(size, modification time in ns) of ``path``; () when it cannot be read (then
    :func:`~nap3d_graph.fields.load_field` says why)."""
    try:
        stat = path.stat()
    except OSError:
        return ()
    return stat.st_size, stat.st_mtime_ns


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
    settings = SubmapSettings.from_dict(index["settings"])

    scanned: set[tuple] = set()

    def loader(s: Submap):
        def load():
            # A run crossing a floor reads the same submap files again and again (a view through a
            # door renders from three submaps, two kept): each file's weights are scanned for
            # non-finite values at its first read only, unless it changed on disk since (the scan
            # was a quarter of a 6-room traverse's time).
            path = folder / s.file
            key = (s.file, *_file_state(path))
            field = load_field(path, scanned=key in scanned)
            if len(key) > 1:
                scanned.add(key)
            return field if s.R_grid_map is None else FramedField(field, s.R_grid_map)
        return load

    return SubmapField.lazy([loader(s) for s in submaps], submaps, settings)
