"""Loop candidates between the survey's keyframes and their verification.

Candidates come two ways: by appearance (the most similar keyframes by VLAD,
:mod:`.retrieval`) and by proximity in the current estimate (camera centres close and
looking the same way). Each candidate pair is verified with NAP3D's own aligner run
real-vs-real: keyframe j plays the rendered view with its own depth (opaque where the sensor
measured), keyframe i the real frame, so a verified loop is ``T_i_j`` (keyframe j's camera
in keyframe i's) with the alignment's 6x6 covariance, as a correction would be.
Verification cannot tell a repeated texture from a revisit. A look-alike a room away is
refused against the survey's own odometry (:func:`refuse_look_alikes`); a nearer one is left
to the robust pose graph (:mod:`.pose_graph`).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.camera import RenderedView, RGBDFrame, project
from nap3d_graph.conventions import adjoint, inv_T, rotation_angle_deg
from nap3d_graph.factors.gate import chi2_threshold
from nap3d_graph.nap3d.align import align_correspondences, prepare_correspondences
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.matching import Features
from nap3d_graph.progress import progress_bar
from nap3d_graph.results import Alignment
from nap3d_graph.torch_threads import torch_threads

from .bundle import PairMatches
from .pose_graph import Edge, floor_covariance, mahalanobis_sq
from .retrieval import similarities
from .verification import Verification, worst_sigmas

__all__ = ["Keyframe", "Loop", "LoopSettings", "as_view", "candidates", "verify", "verify_pair", "consecutive_edges",
           "save_edges", "load_edges", "write_loops_csv", "refuse_look_alikes", "LOOK_ALIKE_REASON", "verify_on_pool", "verify_chunk", "verified_loop",
           "POOL_MIN_PAIRS"]

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """One survey keyframe: its frame index, the frame (at the map's working size), its
    features, its global descriptor."""

    index: int
    frame: RGBDFrame
    features: Features
    descriptor: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class LoopSettings:
    """How loops are found and verified.

    appearance_k: candidates per keyframe by appearance; proximity_m / proximity_deg: camera
    centres this close and optical axes within this angle are candidates (at most
    ``proximity_k`` nearest per keyframe); min_gap: keyframes nearer in time than this are
    not loop candidates (their consecutive edge already ties them); min_inliers, max_sigma_m,
    max_sigma_deg: what a verified loop must reach; max_jump_m, drift_per_m: a verified loop
    that puts its keyframes further from where the survey's odometry puts them than
    ``max_jump_m`` plus ``drift_per_m`` of the path walked between them is refused (a twin room
    or a repeated picture a room away, not the place revisited: :func:`refuse_look_alikes`).
    2.5 m and 10%: twin rooms stand a room (4-6 m) apart and a floor's survey walks 10 m or more
    between them, while the tests' fast one-room surveys drift up to 2.3 m over a few metres;
    a survey whose odometry drifts more than that loses true loops (the report's loop row
    shows it). join_loops: two stretches of the survey either side of a loss of the camera
    are one when this many verified loops tie them (:func:`~.survey.joined_run`)."""

    appearance_k: int = 4
    proximity_m: float = 0.6
    proximity_deg: float = 40.0
    proximity_k: int = 4
    min_gap: int = 2
    min_inliers: int = 30
    max_sigma_m: float = 0.02
    max_sigma_deg: float = 1.5
    max_jump_m: float = 2.5
    drift_per_m: float = 0.1
    join_loops: int = 3

    @property
    def verification(self) -> Verification:
        """The thresholds a verified loop must reach, as the rule shared with relocalisation."""
        return Verification(self.min_inliers, self.max_sigma_m, self.max_sigma_deg)


@dataclass
class Loop:
    """A candidate pair (keyframe positions ``a`` < ``b`` in the keyframe list; ``i``, ``j``
    their frame indices) and what its verification gave. ``T_a_b`` (4, 4): keyframe b's
    camera in keyframe a's; ``covariance`` (6, 6) of ``T_a_b`` (right perturbation, GTSAM
    order). ``status``: 'verified', 'refused' (the aligner's reason in ``reason``) and after
    the graph 'accepted' or 'rejected'; a rejected loop the bundle adjustment let in after all
    is 'admitted' (:func:`~nap3d_graph.mapping.build.adjust_keyframes`)."""

    a: int
    b: int
    i: int
    j: int
    source: str
    matches: int = 0
    inliers: int = 0
    rmse_m: float = float("nan")
    sigma_m: float = float("nan")
    sigma_deg: float = float("nan")
    T_a_b: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.inf))
    status: str = "candidate"
    reason: str = ""
    matches_kept: object = None  # PairMatches of a verified pair, for the bundle adjustment

    CSV_HEADER = ("keyframe_a", "keyframe_b", "frame_i", "frame_j", "source", "matches", "inliers", "rmse_m",
                  "sigma_m", "sigma_deg", "status", "reason")

    def csv_row(self) -> list:
        return [self.a, self.b, self.i, self.j, self.source, self.matches, self.inliers, f"{self.rmse_m:.5f}",
                f"{self.sigma_m:.5f}", f"{self.sigma_deg:.4f}", self.status, self.reason]


def as_view(frame: RGBDFrame) -> RenderedView:
    """A real frame as the 'rendered' side of an alignment: its colour, its own depth, opaque
    exactly where the sensor measured depth."""
    depth = np.nan_to_num(frame.depth_m).astype(np.float32)
    opacity = (np.isfinite(frame.depth_m) & (frame.depth_m > 0)).astype(np.float32)
    return RenderedView(frame.rgb, depth, opacity, frame.intrinsics)


def candidates(T_map_key: np.ndarray, descriptors: np.ndarray, settings: LoopSettings) -> list[tuple[int, int, str]]:
    """``(a, b, source)`` with a < b: the pairs worth verifying, by appearance, proximity or
    both. ``T_map_key`` (K, 4, 4): the keyframes' current poses; ``descriptors`` (K, D)."""
    n = len(T_map_key)
    found: dict[tuple[int, int], set] = {}
    if settings.appearance_k > 0 and len(descriptors):
        for a in range(n):
            score = similarities(descriptors[a], descriptors)
            far = np.abs(np.arange(n) - a) >= settings.min_gap
            order = [b for b in np.argsort(-score) if far[b]][: settings.appearance_k]
            for b in order:
                found.setdefault((min(a, b), max(a, b)), set()).add("appearance")
    centres = T_map_key[:, :3, 3]
    axes = T_map_key[:, :3, 2]
    for a in range(n):
        distance = np.linalg.norm(centres - centres[a], axis=1)
        angle = np.degrees(np.arccos(np.clip(axes @ axes[a], -1.0, 1.0)))
        near = (distance <= settings.proximity_m) & (angle <= settings.proximity_deg)
        near &= np.abs(np.arange(n) - a) >= settings.min_gap
        for b in [b for b in np.argsort(distance) if near[b]][: settings.proximity_k]:
            found.setdefault((min(a, b), max(a, b)), set()).add("proximity")
    return [(a, b, "+".join(sorted(s))) for (a, b), s in sorted(found.items())]


def verify_pair(key_a: Keyframe, key_b: Keyframe, config: AlignConfig, a: int = 0, b: int = 0
                ) -> tuple[np.ndarray, np.ndarray, object]:
    """``(T_a_b, covariance, alignment)``: keyframe b's camera in keyframe a's by NAP3D (a real,
    b as the view), the covariance moved onto ``T_a_b`` (the alignment gives it for the
    corrected pose of a's camera; ``T_a_b``'s right perturbation is b's). On success
    ``alignment.diagnostics["matches"]`` holds the inlier pixel pairs (a
    :class:`~nap3d_graph.mapping.bundle.PairMatches` of positions ``a``, ``b``) for the bundle
    adjustment."""

    view = as_view(key_b.frame)
    try:
        corr, reason = prepare_correspondences(key_a.frame, view, config, feats_real=key_a.features,
                                               feats_view=key_b.features.where(view.opacity >= config.min_opacity))
        alignment = Alignment.failure(reason) if corr is None else align_correspondences(corr, key_a.frame.intrinsics,
                                                                                         config)
    except (ValueError, np.linalg.LinAlgError) as exc:  # numerical trouble is a refused pair, not a crash
        alignment = Alignment.failure(f"numerical failure: {exc}")
    if not alignment.success:
        return np.eye(4), np.full((6, 6), np.inf), alignment
    mask = alignment.inlier_mask if alignment.inlier_mask is not None else np.ones(len(corr), bool)
    uv_b, z_b = project(corr.x[mask], key_b.frame.intrinsics)
    alignment.diagnostics["matches"] = PairMatches(a, b, corr.uv_real[mask], uv_b, corr.y[mask, 2], z_b)
    # T_real_rendered = T_a_b (b's points into a's camera). The alignment's covariance is of
    # T_world_a_true = T_world_b @ inv(T_a_b) perturbed on the right (a's frame); the same
    # uncertainty on T_a_b, perturbed on the right (b's frame), is Ad(T_b_a) cov Ad(T_b_a)^T.
    T_a_b = alignment.T_real_rendered
    A = adjoint(inv_T(T_a_b))
    cov = A @ alignment.covariance @ A.T
    return T_a_b, 0.5 * (cov + cov.T), alignment


def verify(keyframes: list[Keyframe], pairs: list[tuple[int, int, str]], config: AlignConfig,
           settings: LoopSettings, progress: bool = True) -> list[Loop]:
    """Every candidate pair aligned and checked; returns each with its status and reason."""
    return [verified_loop(keyframes[a], keyframes[b], a, b, source, config, settings.verification)
            for a, b, source in progress_bar(pairs, desc="loop verification", unit="pair", disable=not progress,
                                             mininterval=2.0)]


def verified_loop(key_a: Keyframe, key_b: Keyframe, a: int, b: int, source: str, config: AlignConfig,
                  rule: Verification) -> Loop:
    """One candidate pair aligned (:func:`verify_pair`) and checked against ``rule`` (a survey's
    loop settings', or the relocaliser's for another survey's keyframes)."""
    loop = Loop(a, b, key_a.index, key_b.index, source)
    T_a_b, cov, alignment = verify_pair(key_a, key_b, config, a, b)
    loop.matches_kept = alignment.diagnostics.get("matches")
    loop.matches, loop.inliers = alignment.num_matches, alignment.num_inliers
    if not alignment.success:
        loop.status, loop.reason = "refused", alignment.reason
        return loop
    loop.rmse_m = float(alignment.inlier_rmse_m)
    loop.sigma_m, loop.sigma_deg = worst_sigmas(cov)
    loop.T_a_b, loop.covariance = T_a_b, cov
    loop.reason = rule.refusal(loop.inliers, loop.sigma_m, loop.sigma_deg)
    loop.status = "refused" if loop.reason else "verified"
    return loop


#: Fewer candidate pairs than this are verified in the map's own process: starting workers
#: (a second or more each, importing the aligner) costs more than these pairs take.
POOL_MIN_PAIRS = 200


def verify_chunk(job: dict) -> list[Loop]:
    """One job of :func:`verify_on_pool` (runs in a worker): ``job`` holds the keyframes its
    pairs name (by position), the pairs, the aligner's config and the loop settings."""
    keyframes = job["keyframes"]
    with torch_threads(1):
        return [verified_loop(keyframes[a], keyframes[b], a, b, source, job["config"], job["settings"].verification)
                for a, b, source in job["pairs"]]


def verify_on_pool(keyframes: list[Keyframe], pairs: list[tuple[int, int, str]], config: AlignConfig,
                   settings: LoopSettings, pool=None, progress: bool = True, min_pairs: int = POOL_MIN_PAIRS
                   ) -> list[Loop]:
    """:func:`verify` with the pairs cut into jobs on ``pool`` (:mod:`nap3d_graph.pools`: processes
    or Ray tasks), four per worker, each carrying the keyframes its pairs name; the loops in the
    pairs' order, the same as :func:`verify`'s (each pair's alignment is seeded, not shared).
    One process (:func:`verify`) without a pool of two or more workers, or under ``min_pairs``."""
    workers = getattr(pool, "workers", 1)
    if pool is None or workers < 2 or len(pairs) < min_pairs:
        return verify(keyframes, pairs, config, settings, progress)
    chunks = [c for c in np.array_split(np.arange(len(pairs)), 4 * workers) if len(c)]
    handles = []
    for chunk in chunks:
        mine = [pairs[i] for i in chunk]
        named = {k: keyframes[k] for a, b, _ in mine for k in (a, b)}
        handles.append(pool.submit(verify_chunk, {"keyframes": named, "pairs": mine, "config": config,
                                                  "settings": settings}))
    results: dict = {}
    pending = list(handles)
    with progress_bar(total=len(pairs), desc=f"loop verification ({workers} workers)", unit="pair",
                      disable=not progress, mininterval=2.0) as bar:
        while pending:
            finished, pending = pool.wait_any(pending)
            for ref in finished:
                results[handles.index(ref)] = pool.result(ref)
                bar.update(len(results[handles.index(ref)]))
    return [loop for k in range(len(handles)) for loop in results[k]]


#: How a loop refused as a look-alike place begins its reason (``edges.npz`` keeps it: a run's
#: placement reads the map's look-alike pairs back from there).
LOOK_ALIKE_REASON = "look-alike place"


def refuse_look_alikes(loops: list[Loop], T_odom_key: np.ndarray, settings: LoopSettings) -> int:
    """Refuse each verified loop whose measured ``T_a_b`` puts keyframe b further from where
    the odometry ``T_odom_key`` (K, 4, 4) puts it (seen from a) than ``max_jump_m`` plus
    ``drift_per_m`` of the path between them: the odometry cannot have drifted that far, so
    the two views are two look-alike places (twin rooms), which verification alone cannot
    tell from a revisit. Returns how many were refused."""
    centres = np.asarray(T_odom_key, dtype=float)[:, :3, 3]
    walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])
    refused = 0
    for loop in loops:
        if loop.status != "verified":
            continue
        T_a_b_odom = inv_T(T_odom_key[loop.a]) @ T_odom_key[loop.b]
        jump = float(np.linalg.norm(loop.T_a_b[:3, 3] - T_a_b_odom[:3, 3]))
        allowed = settings.max_jump_m + settings.drift_per_m * abs(walked[loop.b] - walked[loop.a])
        if jump > allowed:
            loop.status = "refused"
            loop.reason = (f"{LOOK_ALIKE_REASON}: the loop moves keyframe b {jump:.2f} m from where the odometry puts it "
                           f"(> {allowed:.2f} m it can have drifted)")
            refused += 1
    return refused


def relative_motion(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two poses."""
    T = inv_T(T_a) @ T_b
    return float(np.linalg.norm(T[:3, 3])), float(rotation_angle_deg(T[:3, :3]))


def consecutive_edges(keyframes: list[Keyframe], survey, config: AlignConfig, min_inliers: int, gate_p: float,
                      floor_rad: float, floor_m: float) -> tuple[list[Edge], list[str], list[PairMatches]]:
    """Consecutive keyframes tied by their own alignment where it has ``min_inliers`` and
    agrees with the odometry's chained steps (``survey.between``; chi-square gate at
    ``gate_p``), else by the odometry; every edge's covariance floored (``floor_rad``,
    ``floor_m``). Returns the edges, each one's kind ('alignment' or 'odometry') and the inlier
    matches of the aligned ones."""
    edges, kinds, matches = [], [], []
    threshold = chi2_threshold(gate_p, 6)
    for a in range(len(keyframes) - 1):
        i, j = keyframes[a].index, keyframes[a + 1].index
        T_odom, cov_odom = survey.between(i, j)
        cov_odom = floor_covariance(cov_odom, floor_rad, floor_m)
        T_align, cov_align, alignment = verify_pair(keyframes[a], keyframes[a + 1], config, a, a + 1)
        if alignment.success and alignment.num_inliers >= min_inliers:
            cov_align = floor_covariance(cov_align, floor_rad, floor_m)
            d2 = mahalanobis_sq(np.eye(4), T_odom, Edge(0, 1, T_align, cov_align + cov_odom, "alignment"))
            if d2 <= threshold:
                edges.append(Edge(a, a + 1, T_align, cov_align, "alignment"))
                kinds.append("alignment")
                matches.append(alignment.diagnostics["matches"])
                continue
        edges.append(Edge(a, a + 1, T_odom, cov_odom, "odometry"))
        kinds.append("odometry")
    return edges, kinds, matches


# --- the loop stage's files -------------------------------------------------------------


def save_edges(path: Path, chain: list[Edge], loops: list[Loop], chain_matches: list[PairMatches]) -> None:
    """The chain's edges, the loops and every inlier match, in one compressed file (``edges.npz``)."""
    pairs = list(chain_matches) + [lp.matches_kept for lp in loops if lp.matches_kept is not None]
    owner = [-1] * len(chain_matches) + [n for n, lp in enumerate(loops) if lp.matches_kept is not None]
    sizes = [len(p.z_a) for p in pairs]
    np.savez_compressed(
        path,
        pm_owner=np.array(owner, dtype=int), pm_ab=np.array([[p.a, p.b] for p in pairs], dtype=int).reshape(-1, 2),
        pm_size=np.array(sizes, dtype=int),
        pm_uv_a=np.concatenate([p.uv_a for p in pairs]).reshape(-1, 2) if pairs else np.zeros((0, 2)),
        pm_uv_b=np.concatenate([p.uv_b for p in pairs]).reshape(-1, 2) if pairs else np.zeros((0, 2)),
        pm_z_a=np.concatenate([p.z_a for p in pairs]) if pairs else np.zeros(0),
        pm_z_b=np.concatenate([p.z_b for p in pairs]) if pairs else np.zeros(0),
        chain_ab=np.array([[e.a, e.b] for e in chain], dtype=int).reshape(-1, 2),
        chain_T=np.array([e.T_a_b for e in chain]).reshape(-1, 4, 4),
        chain_cov=np.array([e.covariance for e in chain]).reshape(-1, 6, 6),
        chain_kind=np.array([e.kind for e in chain]),
        loop_abij=np.array([[lp.a, lp.b, lp.i, lp.j, lp.matches, lp.inliers] for lp in loops], dtype=int).reshape(-1, 6),
        loop_T=np.array([lp.T_a_b for lp in loops]).reshape(-1, 4, 4),
        loop_cov=np.array([lp.covariance for lp in loops]).reshape(-1, 6, 6),
        loop_stats=np.array([[lp.rmse_m, lp.sigma_m, lp.sigma_deg] for lp in loops]).reshape(-1, 3),
        loop_text=np.array([[lp.source, lp.status, lp.reason] for lp in loops], dtype=str).reshape(-1, 3))


def load_edges(path: Path) -> tuple[list[Edge], list[Loop], list[PairMatches]]:
    """What :func:`save_edges` wrote: the chain's edges, the loops (decisions of the graph
    forgotten: it decides again) and the chain's matches."""
    with np.load(path) as d:
        bounds = np.concatenate([[0], np.cumsum(d["pm_size"])]).astype(int)
        # Each d[key] reads the whole array from the archive again: read each once (a slice of
        # a fresh read per pair kept every pair's own copy alive: 7 GB for a 3-room floor).
        uv_a, uv_b, z_a, z_b = (d[k] for k in ("pm_uv_a", "pm_uv_b", "pm_z_a", "pm_z_b"))
        pairs = [PairMatches(int(a), int(b), uv_a[s:e], uv_b[s:e], z_a[s:e], z_b[s:e])
                 for (a, b), s, e in zip(d["pm_ab"], bounds[:-1], bounds[1:])]
        owners = d["pm_owner"]
        chain = [Edge(int(a), int(b), T, c, str(k)) for (a, b), T, c, k in
                 zip(d["chain_ab"], d["chain_T"], d["chain_cov"], d["chain_kind"])]
        loops = []
        for (a, b, i, j, m, n), T, c, (rmse, sm, sd), (source, status, reason) in zip(
                d["loop_abij"], d["loop_T"], d["loop_cov"], d["loop_stats"], d["loop_text"]):
            status = "verified" if status in ("accepted", "rejected", "admitted") else str(status)
            loops.append(Loop(int(a), int(b), int(i), int(j), str(source), int(m), int(n), float(rmse), float(sm),
                              float(sd), T, c, status, str(reason)))
    for owner, pair in zip(owners, pairs):
        if owner >= 0:
            loops[owner].matches_kept = pair
    return chain, loops, [p for o, p in zip(owners, pairs) if o < 0]


def write_loops_csv(path: Path, loops: list[Loop]) -> None:
    """Every loop, its verification and decision, as CSV (atomically)."""
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(Loop.CSV_HEADER)
        for lp in loops:
            writer.writerow(lp.csv_row())
    tmp.replace(path)
