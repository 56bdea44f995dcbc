"""``nap3d-graph map NEW_SURVEY --extend MAP``: a map grown by another day's survey.

A floor is mapped room by room on different days. The new survey is first posed on its own,
as any map is (:func:`~.build.build_map`'s odometry, keyframes, loops, graph and bundle
adjustment, in a staging folder beside the map, so an interrupted extension resumes). Then:

1. **Found in the map.** Each new keyframe's global descriptor (the map's own vocabulary) ranks
   the map's keyframes; the ``appearance_k`` most similar are aligned with it real-vs-real at
   the map's kept image width (:func:`~.loops.verify_pair`, the relocaliser's thresholds).
   Each verified pair says where the new survey's frame lies in the map (an *anchor*).
2. **One place, not a look-alike.** The anchors are grouped: the largest group that agrees
   within ``agree_m`` / ``agree_deg`` is the placement, and it needs ``min_pairs`` pairs from
   ``min_pairs`` different new keyframes. A second group standing ``rival_m`` or more away with
   ``rival_ratio`` of its support (twin rooms) refuses the extension as ambiguous; no group
   refuses it as a survey of another place. Either way in one line, the map untouched.
3. **One graph re-solved.** The map's keyframes are held where they are (their fields were
   trained at those poses and are kept); the new keyframes are tied to each other by the new
   survey's own solution (consecutive keyframes, with its edges' covariances) and to the map by
   the placement's verified pairs, under the same robust graph (GNC) that judges a survey's
   loops. Every new frame is then placed between its keyframes.
4. **New space, new submaps.** A new frame is *seen* when a map keyframe stands within
   ``seen_m`` / ``seen_deg`` of it; where ``min_new_frames`` or more new frames were not seen,
   they (and the new frames within the submaps' overlap) train new submap fields, one per
   ``max_frames``; where the new survey only saw the map again, no field is trained and the old
   ones answer. The map's field becomes a map of submaps that each know where their cameras
   looked (:class:`~nap3d_graph.fields.submaps.Submap`); its keyframe index grows by the new
   keyframes (relocalisation searches both days).

The merged map is written in a staging copy and swapped in whole: a map folder is never left
half-merged. The new survey's own map (its poses in the map's frame, its cross pairs, its
mesh) stays in ``extensions/NN/``. The same steps fit a run's own keyframes (a later step:
the run would be the new survey).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import inv_T, rotation_angle_deg
from nap3d_graph.datasets.depth_timing import estimate_timing
from nap3d_graph.datasets.posed import PosedSequence
from nap3d_graph.fields.submaps import SUBMAPS_INDEX, Submap, SubmapSettings, write_submaps_index
from nap3d_graph.nap3d.correct import at_width
from nap3d_graph.nap3d.matching import detect_features
from nap3d_graph.pools import SerialPool
from nap3d_graph.progress import progress_bar
from nap3d_graph.trajectory import write_tum_trajectory

from .build import MapResult, MapSettings, align_config, build_map, place_kept_frames
from .folder import MapFolder
from .loops import Keyframe, load_edges, verified_loop
from .mesh import fuse_mesh
from .pose_graph import Edge, floor_covariance, solve
from .relocalise import (
    KEYFRAME_WIDTH,
    KeptFrames,
    RelocaliseSettings,
    load_keyframe_frames,
    pose_gap,
    write_keyframe_frames,
)
from .retrieval import Vocabulary, similarities, vlad
from .submap_fields import submap_job, submap_minutes, train_one_submap
from .submaps import plan_submaps
from .survey import SurveyOdometry

__all__ = ["ExtendSettings", "MapExtensionRefused", "CrossPair", "extend_map", "place_survey"]

log = logging.getLogger(__name__)


class MapExtensionRefused(ValueError):
    """The new survey cannot be joined to the map (the reason in one line); the map is untouched."""


@dataclass(frozen=True)
class ExtendSettings:
    """appearance_k: map keyframes tried per new keyframe, most similar first; agree_m /
    agree_deg: anchors this close are one placement (a survey's own drift between its keyframes
    is centimetres); min_pairs: verified pairs, from as many new keyframes, a placement needs;
    rival_m / rival_ratio: a second placement this far away with this share of the first's
    pairs makes the survey ambiguous (a twin room); seen_m / seen_deg: a new frame this close to
    a map keyframe is of space the map has; min_new_frames: fewer unseen frames than this train
    no new field."""

    appearance_k: int = 4
    agree_m: float = 0.25
    agree_deg: float = 5.0
    min_pairs: int = 3
    rival_m: float = 1.0
    rival_ratio: float = 0.5
    seen_m: float = 0.5
    seen_deg: float = 30.0
    min_new_frames: int = 30

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class CrossPair:
    """A new keyframe (position ``new`` in the new survey's keyframes) against a map keyframe
    (position ``old``): ``T_new_old`` (4, 4) the map keyframe's camera in the new one's,
    ``covariance`` (6, 6, right perturbation at the map keyframe), ``anchor`` (4, 4) where this
    pair puts the new survey's frame in the map; ``status``: 'verified', 'refused' (``reason``),
    then 'placement' (in the agreeing group), 'look-alike' (outside it) and after the graph
    'accepted' or 'rejected'."""

    new: int
    old: int
    inliers: int = 0
    sigma_m: float = float("nan")
    sigma_deg: float = float("nan")
    T_new_old: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.inf))
    anchor: np.ndarray = field(default_factory=lambda: np.full((4, 4), np.nan))
    status: str = "candidate"
    reason: str = ""

    CSV_HEADER = ("new_keyframe", "map_keyframe", "inliers", "sigma_m", "sigma_deg", "status", "reason")

    def csv_row(self) -> list:
        return [self.new, self.old, self.inliers, f"{self.sigma_m:.5f}", f"{self.sigma_deg:.4f}", self.status,
                self.reason]


@dataclass
class _MapIndex:
    """What the map's relocalisation index holds (keyframes.npz, their poses and kept images)."""

    indices: np.ndarray
    surveys: np.ndarray
    descriptors: np.ndarray
    vocabulary: Vocabulary
    matcher: str
    width: int
    T_map_key: np.ndarray
    frames: KeptFrames

    @classmethod
    def read(cls, folder: MapFolder) -> "_MapIndex":
        frames = load_keyframe_frames(folder.keyframe_frames)
        if frames is None:
            raise MapExtensionRefused(f"{folder.root}: its keyframe images ({folder.keyframe_frames.name}) cannot be "
                                      "read; make the map again")
        with np.load(folder.keyframes) as k:
            indices = k["indices"].astype(int)
            surveys = k["surveys"].astype(int) if "surveys" in k.files else np.zeros(len(indices), dtype=int)
            return cls(indices, surveys, k["descriptors"], Vocabulary(k["centres"]), str(k["matcher"]),
                       int(k["width"]), np.load(folder.keyframe_poses), frames)


@dataclass
class _NewKeyframes:
    """The new survey's keyframes as the map sees them, each read once: ``descriptors`` (K1, D)
    in the map's vocabulary at its width, ``frames`` at the map's kept width and their
    ``features``."""

    descriptors: np.ndarray
    frames: list
    features: list

    @classmethod
    def read(cls, sequence, keys: np.ndarray, index: _MapIndex, config, progress: bool = False) -> "_NewKeyframes":
        width = None if index.width < 0 else index.width
        kept = index.frames.intrinsics
        descriptors, frames, features = [], [], []
        for i in progress_bar(keys, desc="new keyframes", unit="keyframe", disable=not progress, mininterval=2.0):
            frame = sequence[int(i)]
            descriptors.append(vlad(detect_features(at_width(frame, width).rgb, 0, matcher=index.matcher).descriptors,
                                    index.vocabulary))
            small = at_width(frame, KEYFRAME_WIDTH)
            if (small.intrinsics.width, small.intrinsics.height) != (kept.width, kept.height):
                raise MapExtensionRefused(f"the new survey's images ({small.intrinsics.width}x{small.intrinsics.height} "
                                          f"at the map's kept width) are not the map's ({kept.width}x{kept.height}): "
                                          "extend a map with the camera that made it")
            frames.append(small)
            features.append(detect_features(small.rgb, config.max_features, matcher=config.matcher))
        return cls(np.stack(descriptors), frames, features)


def extend_map(sequence, map_dir: Path, out: Path | None = None, settings: MapSettings | None = None,
               extend: ExtendSettings | None = None, *, progress: bool = True, say=None, device: str | None = None,
               pool=None, mesh: bool = True) -> MapResult:
    """Grow the map in ``map_dir`` by the survey ``sequence`` (see the module's text); the
    merged map replaces ``map_dir`` (``out`` None) or is written to ``out``. ``settings``: how
    the new survey is posed and its fields trained (the map's matcher is used whatever it says).
    Raises :class:`MapExtensionRefused` (map untouched) when the survey is not found in the map,
    is found in two places, or the map cannot be extended."""
    started = time.perf_counter()
    extend = extend or ExtendSettings()
    map_dir = Path(map_dir)
    if out is not None and Path(out).exists() and Path(out).resolve() != map_dir.resolve() and (
            not Path(out).is_dir() or any(Path(out).iterdir())):
        raise MapExtensionRefused(f"{out} exists and is not an empty folder: the grown map goes to a new folder")
    old = _readable_map(map_dir)
    index = _MapIndex.read(old)
    settings = _with_matcher(settings or MapSettings(), index.matcher)
    number = len(old.info.get("extensions", [])) + 1
    staging = map_dir.parent / f".{map_dir.name}.extend-{number:02d}"
    survey_map = build_map(sequence, staging / "survey", settings, progress=progress, say=say,
                           build_field_stage=False, mesh=False)
    new = MapFolder.read(survey_map.folder)
    keys, T_new_key, survey, (start, stop, lost) = _new_survey(new)
    _say(say, f"extend: the new survey posed on its own ({len(keys)} keyframes over frames {start}:{stop}); "
              "finding it in the map")
    try:
        views = _NewKeyframes.read(sequence, keys, index, align_config(settings), progress)
        pairs = cross_pairs(views, keys, T_new_key, index, settings, extend, progress)
        anchor = place_survey(pairs, extend)
    except MapExtensionRefused:
        shutil.rmtree(staging, ignore_errors=True)  # nothing of the new survey is kept: it is not of this map
        raise
    T_map_newkey, graph_report = _solve_joint(index.T_map_key, T_new_key, anchor, pairs, new, settings)
    T_map_newcam = place_kept_frames(survey, keys, T_map_newkey, start, stop, lost)
    _say(say, f"extend: placed in the map by {graph_report['accepted']} verified pair(s) "
              f"({graph_report['rejected']} turned away by the graph)")
    merged = _merged_copy(map_dir, staging)
    unseen = unseen_frames(T_map_newcam, index.T_map_key, extend)
    submaps, trained = _new_submaps(sequence, T_map_newcam, unseen, merged, old, index, settings, extend, number,
                                    started, device, pool, say)
    _write_index(merged, index, views, keys, T_map_newkey, number)
    record = _write_extension(merged, new, sequence, T_map_newcam, pairs, number, graph_report, unseen, trained,
                              submaps, mesh, progress, say, started)
    merged.info.setdefault("extensions", []).append(record)
    merged.save()
    target = _swap_in(merged.root, map_dir, out)
    shutil.rmtree(staging, ignore_errors=True)
    return MapResult(target, MapFolder.read(target).info)


def _say(say, text: str) -> None:
    log.info(text)
    if say is not None:
        say(text)


def _readable_map(map_dir: Path) -> MapFolder:
    """The map to extend; :class:`MapExtensionRefused` when it lacks what an extension reads."""
    try:
        folder = MapFolder.read(map_dir)
    except FileNotFoundError as exc:
        raise MapExtensionRefused(str(exc)) from None
    needed = [folder.keyframes, folder.keyframe_frames, folder.keyframe_poses]
    missing = [p.name for p in needed if not p.is_file()]
    if not (folder.field.is_file() or (folder.root / SUBMAPS_INDEX).is_file()):
        missing.append("field.pt or submaps.json")
    if missing:
        raise MapExtensionRefused(f"{map_dir}: an unfinished map (no {', '.join(missing)}); finish it with the "
                                  "'nap3d-graph map' command that made it, then extend it")
    return folder


def _with_matcher(settings: MapSettings, matcher: str) -> MapSettings:
    """The new survey's settings with the map's matcher: its descriptors and the map's must be of one kind."""
    import dataclasses

    if settings.matcher != matcher:
        log.info("extend: the new survey uses the map's matcher %s (not %s)", matcher, settings.matcher)
    return dataclasses.replace(settings, matcher=matcher)


def _new_survey(new: MapFolder) -> tuple[np.ndarray, np.ndarray, SurveyOdometry, tuple[int, int, list]]:
    """The new survey's keyframe indices, their poses in its own frame (K1, 4, 4), its odometry
    and kept frames (start, stop and the losses between, never placed), from its staging map."""
    with np.load(new.keyframes) as data:
        keys = data["indices"].astype(int)
    segment = new.info["segment"]
    lost = [tuple(g) for g in segment.get("rejoined", [])]
    return keys, np.load(new.keyframe_poses), SurveyOdometry.load(new.odometry), (segment["start"], segment["stop"],
                                                                                  lost)


def cross_pairs(views: _NewKeyframes, keys: np.ndarray, T_new_key: np.ndarray, index: _MapIndex,
                settings: MapSettings, extend: ExtendSettings, progress: bool = False) -> list[CrossPair]:
    """Every new keyframe against its ``appearance_k`` most similar map keyframes (descriptors in
    the map's vocabulary), aligned at the map's kept width under the relocaliser's rule; each
    verified pair with its anchor ``T_map_newframe`` (where it puts the new survey's frame in the map)."""
    config = align_config(settings)
    rule = RelocaliseSettings().verification
    features: dict[int, object] = {}
    pairs = []
    for a in progress_bar(range(len(keys)), desc="finding the survey in the map", unit="keyframe",
                          disable=not progress, mininterval=2.0):
        query = Keyframe(int(keys[a]), views.frames[a], views.features[a])
        for b in np.argsort(-similarities(views.descriptors[a], index.descriptors), kind="stable")[: extend.appearance_k]:
            b = int(b)
            if b not in features:
                features[b] = detect_features(index.frames.rgb[b], config.max_features, matcher=config.matcher)
            loop = verified_loop(query, Keyframe(int(index.indices[b]), index.frames[b], features[b]), a, b, "map",
                                 config, rule)
            pairs.append(_cross_pair(loop, index.T_map_key[b], T_new_key[a]))
    return pairs


def _cross_pair(loop, T_map_old: np.ndarray, T_new_a: np.ndarray) -> CrossPair:
    """A verified (or refused) alignment of new keyframe ``loop.a`` with map keyframe ``loop.b``
    as a cross pair, with its anchor when verified."""
    pair = CrossPair(loop.a, loop.b, loop.inliers, loop.sigma_m, loop.sigma_deg, status=loop.status, reason=loop.reason)
    if loop.status == "verified":
        pair.T_new_old, pair.covariance = loop.T_a_b, loop.covariance
        # The new keyframe in the map by this pair, then the new survey's frame by its own pose.
        pair.anchor = T_map_old @ inv_T(loop.T_a_b) @ inv_T(T_new_a)
    return pair


def place_survey(pairs: list[CrossPair], extend: ExtendSettings) -> np.ndarray:
    """The new survey's frame in the map (4, 4): the anchor of the largest group of verified
    pairs that agree (each pair's status set: 'placement' or 'look-alike'). Raises
    :class:`MapExtensionRefused` when no group has ``min_pairs`` pairs from as many new
    keyframes (a survey of another place) or a rival group stands ``rival_m`` away with
    ``rival_ratio`` of its support (the survey fits two places: twin rooms)."""
    verified = [p for p in pairs if p.status == "verified"]
    tried = len({p.new for p in pairs})
    if not verified:
        raise MapExtensionRefused(f"the new survey is not found in the map: none of {len(pairs)} pairs of its {tried} "
                                  "keyframes with the map's verified (a survey of another place?)")
    support = [[q for q in verified if _agree(p.anchor, q.anchor, extend)] for p in verified]
    sizes = [len({q.new for q in group}) for group in support]
    best = int(np.argmax(sizes))
    if sizes[best] < extend.min_pairs:
        raise MapExtensionRefused(f"the new survey is not found in the map: {len(verified)} verified pair(s) of "
                                  f"{tried} keyframes, at most {sizes[best]} agreeing on one placement (needs "
                                  f"{extend.min_pairs}; a survey of another place, or too little of it seen before?)")
    anchor = verified[best].anchor
    rivals = [k for k, p in enumerate(verified) if pose_gap(p.anchor, anchor)[0] >= extend.rival_m]
    rival = max(rivals, key=lambda k: sizes[k], default=None)
    if rival is not None and sizes[rival] >= extend.rival_ratio * sizes[best]:
        raise MapExtensionRefused(f"the new survey fits two places of the map {pose_gap(anchor, verified[rival].anchor)[0]:.1f} m "
                                  f"apart ({sizes[best]} and {sizes[rival]} agreeing keyframes): look-alike rooms, or the new survey's "
                                  "own poses are bent; extend with a survey that also sees what tells the rooms apart")
    for p in verified:
        p.status = "placement" if _agree(p.anchor, anchor, extend) else "look-alike"
        if p.status == "look-alike":
            p.reason = "verified, but puts the survey {:.2f} m from where the others do".format(
                pose_gap(p.anchor, anchor)[0])
    return anchor


def _agree(T_a: np.ndarray, T_b: np.ndarray, extend: ExtendSettings) -> bool:
    metres, degrees = pose_gap(T_a, T_b)
    return metres <= extend.agree_m and degrees <= extend.agree_deg


def _solve_joint(T_map_oldkey: np.ndarray, T_new_key: np.ndarray, anchor: np.ndarray, pairs: list[CrossPair],
                 new: MapFolder, settings: MapSettings) -> tuple[np.ndarray, dict]:
    """The new keyframes in the map (K1, 4, 4): the map's keyframes held, the new ones tied to
    each other by their own solution and to the map by the placement's pairs (GNC decides each)."""
    held = len(T_map_oldkey)
    chain_edges, _, _ = load_edges(new.edges)
    chain = []
    for e in chain_edges:  # the new survey's shape as its own graph and bundle solved it
        T_a_b = inv_T(T_new_key[e.a]) @ T_new_key[e.b]
        chain.append(Edge(held + e.a, held + e.b, T_a_b, e.covariance, "alignment"))
    placing = [p for p in pairs if p.status == "placement"]
    loops = [Edge(held + p.new, p.old, p.T_new_old,
                  floor_covariance(p.covariance, settings.edge_floor_rad, settings.edge_floor_m), "loop")
             for p in placing]
    T_init = np.concatenate([T_map_oldkey, anchor[None] @ T_new_key])
    graph = solve(T_init, chain, loops, settings.gate_p, held=held)
    for p, kept, d2 in zip(placing, graph.loop_kept, graph.loop_d2):
        p.status = "accepted" if kept else "rejected"
        p.reason = "" if kept else f"inconsistent with the graph (d2 {d2:.1f})"
    moved = [pose_gap(a, b)[0] for a, b in zip(graph.T_map_key[:held], T_map_oldkey)]
    if moved and max(moved) > 1e-3:  # the held keyframes are priors of 1e-6: this never happens unless GTSAM fails
        raise RuntimeError(f"the map's keyframes moved {max(moved) * 1000:.1f} mm while held")
    return graph.T_map_key[held:], {"accepted": int(graph.loop_kept.sum()),
                                    "rejected": int((~graph.loop_kept).sum())}


def unseen_frames(T_map_newcam: np.ndarray, T_map_oldkey: np.ndarray, extend: ExtendSettings) -> np.ndarray:
    """Indices of the new survey's posed frames with no map keyframe within ``seen_m`` /
    ``seen_deg``: the space the map did not have."""
    out = []
    for i, T in enumerate(T_map_newcam):
        if not np.all(np.isfinite(T)):
            continue
        gaps = np.linalg.norm(T_map_oldkey[:, :3, 3] - T[:3, 3], axis=1)
        near = gaps <= extend.seen_m
        if not any(rotation_angle_deg(T_map_oldkey[k, :3, :3].T @ T[:3, :3]) <= extend.seen_deg
                   for k in np.flatnonzero(near)):
            out.append(i)
    return np.asarray(out, dtype=int)


def _merged_copy(map_dir: Path, staging: Path) -> MapFolder:
    """A copy of the map to merge into (files hard-linked where the disk allows: every file the
    merge changes is replaced, never written into, so the map itself cannot change)."""
    target = staging / "merged"
    if target.exists():
        shutil.rmtree(target)

    def link(src, dst):
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    shutil.copytree(map_dir, target, copy_function=link)
    return MapFolder.read(target)


def _look_points(T_map_cam: np.ndarray, look_ahead_m: float, at_most: int = 400) -> np.ndarray:
    """(M, 3) the points ``look_ahead_m`` in front of the posed cameras, at most ``at_most`` (evenly taken)."""
    T = np.asarray(T_map_cam, dtype=float)
    T = T[np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)]
    points = T[:, :3, 3] + T[:, :3, 2] * look_ahead_m
    step = max(1, int(np.ceil(len(points) / at_most)))
    return points[::step]


def _old_submaps(merged: MapFolder, old: MapFolder, index: _MapIndex, look_ahead_m: float) -> list[Submap]:
    """The map's submaps, each with the points its keyframes looked at; a one-field map's
    ``field.pt`` becomes submap 0 (moved to ``submaps/00.pt`` in the merged copy)."""
    path = old.root / SUBMAPS_INDEX
    if path.is_file():
        submaps = [Submap.from_dict(d) for d in json.loads(path.read_text())["submaps"]]
    else:
        submaps = [Submap(0, np.array([1.0, 0.0, 0.0]), np.array([-np.inf, np.inf]),
                          index.indices[index.surveys == 0])]
        (merged.root / "submaps").mkdir(exist_ok=True)
        os.replace(merged.field, merged.root / submaps[0].file)
    for s in submaps:
        if s.look_points is None:
            mine = (index.surveys == s.survey) & np.isin(index.indices, s.frames)
            s.look_points = _look_points(index.T_map_key[mine], look_ahead_m)
    return submaps


def _new_submaps(sequence, T_map_newcam: np.ndarray, unseen: np.ndarray, merged: MapFolder, old: MapFolder,
                 index: _MapIndex, settings: MapSettings, extend: ExtendSettings, number: int, started: float,
                 device: str | None, pool, say) -> tuple[list[Submap], list[int]]:
    """The merged map's submaps: the map's, then new ones over the unseen space when there is
    enough of it (their fields trained on ``pool``). Returns all submaps and the new ones' indices."""
    submap_settings = settings.submaps
    submaps = _old_submaps(merged, old, index, submap_settings.look_ahead_m)
    if len(unseen) < extend.min_new_frames:
        _say(say, f"extend: {len(unseen)} frame(s) of new space (< {extend.min_new_frames}): no new field, the map's "
                  "fields answer there")
        return submaps, []
    T_unseen = np.full_like(T_map_newcam, np.nan)
    T_unseen[unseen] = T_map_newcam[unseen]
    plan = plan_submaps(T_unseen, submap_settings)
    posed = np.all(np.isfinite(T_map_newcam.reshape(len(T_map_newcam), -1)), axis=1)
    first = len(submaps)
    jobs, added = [], []
    for k, part in enumerate(plan):
        # The unseen frames of this part and the new frames looking within the overlap of them.
        near = _within(T_map_newcam, part.frames, submap_settings.overlap_m) & posed
        submap = Submap(first + k, part.axis, part.core, np.flatnonzero(near), number,
                        _look_points(T_map_newcam[part.frames], submap_settings.look_ahead_m), part.R_grid_map)
        submaps.append(submap)
        added.append(submap.index)
        jobs.append(submap)
    minutes = settings.minutes
    if settings.model == "grid" and settings.steps is None and minutes is None:
        minutes = submap_minutes(settings.budget_minutes, settings.min_train_minutes, settings.budget_reserve_s,
                                 time.perf_counter() - started, len(jobs))
    timing = estimate_timing(PosedSequence(sequence, T_map_newcam, "map"))
    pool = pool or SerialPool()
    _say(say, f"extend: {len(unseen)} frames of new space: {len(jobs)} new submap field(s) on {pool.name}")
    timing_dict = None if timing is None else timing.to_dict()
    handles = [pool.submit(train_one_submap, submap_job(sequence, T_map_newcam, s, settings, minutes, device,
                                                        timing_dict, merged.root / s.file)) for s in jobs]
    reports = {}
    pending = list(handles)
    while pending:
        finished, pending = pool.wait_any(pending)
        for ref in finished:
            report = pool.result(ref)
            reports[handles.index(ref)] = report
    merged.info.setdefault("extension_fields", {})[str(number)] = {
        str(s.index): {k: reports[i].get(k) for k in ("train_seconds", "submap_seconds", "train_frames")}
        for i, s in enumerate(jobs)}
    return submaps, added


def _within(T_map_cam: np.ndarray, frames: np.ndarray, metres: float) -> np.ndarray:
    """(N,) which posed cameras stand within ``metres`` of one of ``frames``' cameras."""
    centres = T_map_cam[:, :3, 3]
    out = np.zeros(len(T_map_cam), dtype=bool)
    ref = centres[frames]
    for i, c in enumerate(centres):
        if np.all(np.isfinite(c)):
            out[i] = bool(np.min(np.linalg.norm(ref - c, axis=1)) <= metres)
    return out


def _write_index(merged: MapFolder, index: _MapIndex, views: _NewKeyframes, keys: np.ndarray,
                 T_map_newkey: np.ndarray, number: int) -> None:
    """The merged relocalisation index: the map's keyframes then the new ones (descriptors in the
    map's vocabulary, images at its kept width, poses in the map), each with its survey."""
    _replace(merged.keyframes, lambda p: np.savez_compressed(
        p, indices=np.concatenate([index.indices, keys]),
        surveys=np.concatenate([index.surveys, np.full(len(keys), number)]),
        descriptors=np.concatenate([index.descriptors, views.descriptors]), centres=index.vocabulary.centres,
        matcher=index.matcher, width=index.width))
    _replace(merged.keyframe_frames, lambda p: write_keyframe_frames(p, [*index.frames, *views.frames], index.matcher))
    _replace(merged.keyframe_poses, lambda p: np.save(p, np.concatenate([index.T_map_key, T_map_newkey])))


def _replace(path: Path, write) -> None:
    """``path`` replaced by what ``write(tmp)`` writes (a new file: a hard-linked original is kept)."""
    tmp = path.with_name(path.stem + ".new" + path.suffix)
    write(tmp)
    os.replace(tmp, path)


def _write_extension(merged: MapFolder, new: MapFolder, sequence, T_map_newcam: np.ndarray, pairs: list[CrossPair],
                     number: int, graph_report: dict, unseen: np.ndarray, trained: list[int], submaps: list[Submap],
                     mesh: bool, progress: bool, say, started: float) -> dict:
    """``extensions/NN/``: the new survey's own map, its frames in the map's frame, its cross
    pairs and mesh; ``submaps.json`` of the merged map. Returns the record for ``map.json``."""
    folder = merged.root / "extensions" / f"{number:02d}"
    folder.parent.mkdir(exist_ok=True)
    shutil.copytree(new.root, folder)
    stamps = np.asarray(sequence.timestamps, dtype=float)
    posed = np.all(np.isfinite(T_map_newcam.reshape(len(T_map_newcam), -1)), axis=1)
    write_tum_trajectory(folder / "poses_in_map.txt", stamps[posed], T_map_newcam[posed])
    with open(folder / "cross_pairs.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CrossPair.CSV_HEADER)
        writer.writerows(p.csv_row() for p in pairs)
    old_index = json.loads((merged.root / SUBMAPS_INDEX).read_text()) if (merged.root / SUBMAPS_INDEX).is_file() else {}
    kept = SubmapSettings.from_dict(old_index["settings"]) if "settings" in old_index else SubmapSettings()
    write_submaps_index(merged.root, submaps, kept,  # written atomically: a new file
                        {k: v for k, v in old_index.items() if k not in ("settings", "submaps")})
    mesh_record = _extension_mesh(sequence, T_map_newcam, folder / "map.ply", progress) if mesh else None
    counts = {s: sum(p.status == s for p in pairs) for s in ("refused", "look-alike", "accepted", "rejected")}
    return {"number": number, "data": str(getattr(sequence, "path", "")),
            "frame_range": list(getattr(sequence, "frame_range", ())), "folder": str(folder.relative_to(merged.root)),
            "keyframes": int(len(np.load(new.keyframe_poses))), "pairs": len(pairs), **counts,
            "unseen_frames": int(len(unseen)), "new_submaps": trained, "mesh": mesh_record,
            "seconds": round(time.perf_counter() - started, 1), "graph": graph_report}


def _extension_mesh(sequence, T_map_cam: np.ndarray, path: Path, progress: bool) -> dict | None:
    """The new survey fused at its poses in the map (``map.ply`` of the extension); None, with a
    log line, without Open3D or when nothing fused."""
    try:
        result = fuse_mesh(PosedSequence(sequence, T_map_cam, "map"), path, progress=progress)
    except (ImportError, ValueError, OSError, RuntimeError) as exc:
        log.warning("extension mesh not written (%s)", exc)
        return None
    return {"file": path.name, "vertices": result.vertices}


def _swap_in(merged: Path, map_dir: Path, out: Path | None) -> Path:
    """The merged map moved to ``out``, or in place of ``map_dir`` (the old one renamed aside
    first, removed once the new one is in: at every instant one whole map is there)."""
    if out is not None and Path(out).resolve() != map_dir.resolve():
        out = Path(out)
        if out.exists():
            out.rmdir()  # empty: checked before the work
        os.replace(merged, out)
        return out
    aside = map_dir.parent / f".{map_dir.name}.before-extend"
    if aside.exists():
        shutil.rmtree(aside)
    os.replace(map_dir, aside)
    os.replace(merged, map_dir)
    shutil.rmtree(aside)
    return map_dir
