"""``nap3d-graph map``: a survey's poses from the camera alone, then the field at them.

Stages, each writing its file into the map folder when it finishes (a map interrupted in any
stage resumes from the last finished one; ``map.json`` records the settings, and a folder
made with other settings is refused rather than mixed):

1. ``odometry.npz``: frame-to-frame odometry from the first frame (:mod:`.survey`), and the
   longest stretch it tracked.
2. ``keyframes.npz``: the keyframes, their global descriptors (VLAD over the matcher's local
   descriptors, :mod:`.retrieval`) and the vocabulary: what relocalisation retrieves from.
3. ``loops.csv`` / ``edges.npz``: consecutive keyframes aligned real-vs-real, loop candidates
   by appearance and proximity verified the same way (:mod:`.loops`).
4. ``poses.txt``: the robust pose graph (:mod:`.pose_graph`), every frame placed between its
   keyframes, gauge at the first keyframe, the metric scale from depth.
5. ``field.pt`` and ``field.report.json``: the field of ``model`` trained at those poses
   (:func:`~nap3d_graph.fields.build.build_field`; capture timing estimated from the poses'
   multi-view agreement, and the bundle-like depth refinement of the training poses when
   asked); ``map.png``; ``survey_ate.json`` where the recording has ground truth (never
   read before this last step).
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import exp_se3, inv_T, log_se3
from nap3d_graph.textfiles import write_json_atomic

from .bundle import BundleSettings, PairMatches, bundle_adjust
from .loops import Keyframe, Loop, LoopSettings, candidates, verify, verify_pair
from .pose_graph import Edge, floor_covariance, mahalanobis_sq, solve
from .relocalise import KEYFRAME_FRAMES, save_keyframe_frames
from .retrieval import Vocabulary, vlad
from .survey import SurveyOdometry, keyframe_indices, track, tracked_segment

__all__ = ["MapSettings", "MapResult", "build_map", "load_map_info", "MAP_INFO"]

log = logging.getLogger(__name__)

#: Settings of the field alone: changing them re-trains the field, not the poses.
FIELD_SETTINGS = ("model", "minutes", "steps", "refine_rounds", "budget_minutes", "budget_reserve_s",
                  "min_train_minutes")

#: The file that marks a folder as a map.
MAP_INFO = "map.json"


@dataclass(frozen=True)
class MapSettings:
    """What ``map`` does. ``odometry``: 'vo' or 'dense'; ``matcher``: the local features of
    the odometry, the descriptors and the verification; ``width``: keyframes (and ``vo``)
    work at this width in pixels (None: as read); keyframe_*: a keyframe every so many frames
    or after so much motion; ``edge_floor_m`` / ``edge_floor_rad``: added to every edge's
    sigma (what pairwise residuals cannot see); ``model`` and the grid's budget: ``steps``, or
    ``minutes`` of its own, or else what ``budget_minutes`` for the whole map leaves once the
    stages before the field have run and ``budget_reserve_s`` is kept for what follows the
    training (capture timing, held-out scoring, the field's error, the report: 70-80 s on two
    cores for fr1/desk's 277 frames, ``benchmarks/map_speed.py``), at least
    ``min_train_minutes``;
    ``refine_rounds``: the depth refinement of the training poses before the field;
    ``bundle``: refine the pose graph's keyframes by the bundle adjustment over every verified
    match (:mod:`.bundle`)."""

    odometry: str = "vo"
    matcher: str = "xfeat"
    width: int | None = None
    keyframe_every: int = 5
    keyframe_distance_m: float = 0.10
    keyframe_angle_deg: float = 10.0
    max_guesses: int = 3
    vocabulary_k: int = 32
    edge_floor_m: float = 0.002
    edge_floor_rad: float = 0.002
    gate_p: float = 0.999
    model: str = "grid"
    minutes: float | None = None
    steps: int | None = None
    budget_minutes: float | None = 5.0
    budget_reserve_s: float = 90.0
    min_train_minutes: float = 1.0
    refine_rounds: int = 0
    seed: int = 0
    bundle: bool = True
    loops: LoopSettings = field(default_factory=LoopSettings)
    bundle_settings: BundleSettings = field(default_factory=BundleSettings)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class MapResult:
    """What ``build_map`` made: ``info`` (map.json's content) and the folder."""

    folder: Path
    info: dict


def load_map_info(folder) -> dict:
    """``map.json`` of a map folder (``FileNotFoundError`` when it is not one)."""
    path = Path(folder) / MAP_INFO
    if not path.is_file():
        raise FileNotFoundError(f"{folder}: not a map folder (no {MAP_INFO}; make one with 'nap3d-graph map')")
    return json.loads(path.read_text())


def _write_json(path: Path, data: dict) -> None:
    write_json_atomic(path, data, default=float)


def _say(say, text: str) -> None:
    log.info(text)
    if say is not None:
        say(text)


def build_map(sequence, out: Path, settings: MapSettings | None = None, *, progress: bool = True, say=None,
              build_field_stage: bool = True, device: str | None = None) -> MapResult:
    """Build (or resume) the map of ``sequence`` in ``out``. The sequence's ground truth is
    never read before the survey's poses are final (only ``survey_ate.json`` uses it)."""
    settings = settings or MapSettings()
    started = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    info_path = out / MAP_INFO
    pose_settings = {k: v for k, v in settings.to_dict().items() if k not in FIELD_SETTINGS}
    field_settings = {k: getattr(settings, k) for k in FIELD_SETTINGS}
    wanted = {"data": str(getattr(sequence, "path", "")), "frame_range": list(getattr(sequence, "frame_range", ())),
              "recording_id": getattr(sequence, "recording_id", None), "settings": pose_settings}
    if getattr(sequence, "depth_scale_source", "") in ("argument", "intrinsics.json"):
        wanted["depth_units_per_m"] = float(sequence.depth_units_per_m)  # a declared unit: another survey
    info = json.loads(info_path.read_text()) if info_path.is_file() else {}
    expected = json.loads(json.dumps(wanted, default=float))
    if info and any(info.get(k) != expected.get(k) for k in {*wanted, "depth_units_per_m"}):
        raise FileExistsError(f"{out} holds a map of other data or settings; choose another folder or remove it")
    info = {**wanted, "stages": info.get("stages", {}), **{k: v for k, v in info.items() if k not in wanted
                                                            and k != "stages"}}
    _write_json(info_path, info)

    def done(stage: str, seconds: float, **extra) -> None:
        info["stages"][stage] = {"seconds": round(seconds, 2), **extra}
        _write_json(info_path, info)

    # 1. odometry
    odometry_path = out / "odometry.npz"
    if "odometry" in info["stages"] and odometry_path.is_file():
        survey = SurveyOdometry.load(odometry_path)
        _say(say, "odometry: finished before, reused")
    else:
        t0 = time.perf_counter()
        survey = track(sequence, settings.odometry, settings.matcher, settings.width, progress)
        survey.save(odometry_path)
        start, stop = tracked_segment(survey.ok, settings.max_guesses)
        done("odometry", time.perf_counter() - t0, guessed_steps=int((~survey.ok).sum()), segment=[start, stop])
    start, stop = tracked_segment(survey.ok, settings.max_guesses)
    dropped = len(survey.ok) - (stop - start)
    info["segment"] = {"start": start, "stop": stop, "dropped_frames": dropped,
                       "guessed_steps": int((~survey.ok[start + 1:stop]).sum())}
    if dropped:
        _say(say, f"the odometry lost the camera: the map keeps frames {start}:{stop} (its longest tracked stretch) "
                  f"and drops {dropped} frames ({', '.join(_ranges(start, stop, len(survey.ok)))})")

    # 2. keyframes and descriptors
    keys = keyframe_indices(survey.T_odom_cam, start, stop, settings.keyframe_every, settings.keyframe_distance_m,
                            settings.keyframe_angle_deg)
    retrieval_path = out / "keyframes.npz"
    keyframes = None if "keyframes" in info["stages"] and retrieval_path.is_file() else \
        _keyframe_stage(sequence, keys, settings, retrieval_path, done, progress)
    if not (out / KEYFRAME_FRAMES).is_file():  # a map made before the relocaliser read them gets them now
        save_keyframe_frames(out / KEYFRAME_FRAMES, keyframes or _keyframes(sequence, keys, settings, progress))
    with np.load(retrieval_path) as data:
        descriptors = data["descriptors"]

    # 3. consecutive edges and loops
    edges_path = out / "edges.npz"
    loops_csv = out / "loops.csv"
    T_init = survey.T_odom_cam[keys]
    if "loops" in info["stages"] and edges_path.is_file():
        chain, loops, chain_matches = _load_edges(edges_path)
        _say(say, "loops: finished before, reused")
    else:
        chain, loops, chain_matches = _loop_stage(sequence, keys, keyframes, descriptors, survey, settings, edges_path,
                                                  done, progress)
    keyframes = None  # the frames are not needed any more

    # 4. the robust pose graph
    t0 = time.perf_counter()
    verified = [lp for lp in loops if lp.status in ("verified", "accepted", "rejected")]
    loop_edges = [Edge(lp.a, lp.b, lp.T_a_b, floor_covariance(lp.covariance, settings.edge_floor_rad,
                                                              settings.edge_floor_m), "loop") for lp in verified]
    graph = solve(T_init, chain, loop_edges, settings.gate_p)
    for lp, kept, weight, d2 in zip(verified, graph.loop_kept, graph.loop_weights, graph.loop_d2):
        lp.status = "accepted" if kept else "rejected"
        lp.reason = "" if kept else (f"inconsistent with the graph (GNC weight {weight:.2f}, d2 {d2:.1f})")
    _write_loops_csv(loops_csv, loops)
    T_map_key = graph.T_map_key
    if settings.bundle:
        pair_matches = chain_matches + [lp.matches_kept for lp in verified if lp.status == "accepted"
                                        and lp.matches_kept is not None]
        K = _working_intrinsics(sequence, settings)
        bundle_settings = _bundle_settings(sequence, settings)
        T_map_key, bundle_report = bundle_adjust(graph.T_map_key, pair_matches, K, bundle_settings)
        bundle_report["baseline_from"] = ("the recording's calibration" if bundle_settings is not settings.bundle_settings
                                          else "the settings")
        info["bundle"] = bundle_report
        _say(say, f"bundle adjustment: {bundle_report.get('landmarks', 0)} landmarks, "
                  f"{bundle_report.get('observations', 0)} observations; keyframes moved "
                  f"{bundle_report.get('median_keyframe_move_mm', 0):.1f} mm (median)")
    T_graph_cam = place_frames(survey.T_odom_cam, keys, graph.T_map_key, start, stop)
    T_map_cam = place_frames(survey.T_odom_cam, keys, T_map_key, start, stop)
    from nap3d_graph.trajectory import write_tum_trajectory

    stamps = np.asarray(sequence.timestamps, dtype=float)
    posed = np.all(np.isfinite(T_map_cam), axis=(1, 2))
    write_tum_trajectory(out / "poses.txt", stamps[posed], T_map_cam[posed])
    write_tum_trajectory(out / "odometry.txt", stamps[start:stop], survey.T_odom_cam[start:stop])
    accepted = int(graph.loop_kept.sum())
    done("graph", time.perf_counter() - t0, keyframes=len(keys), loops_verified=len(verified), loops_accepted=accepted,
         loops_rejected=len(verified) - accepted)
    if accepted == 0:
        _say(say, "no loop closure found: the map's poses are the odometry's alone (they drift as it does)")
    np.save(out / "keyframe_poses.npy", T_map_key)

    # 5. the field at the map's poses
    from .posed import PosedSequence

    posed_sequence = PosedSequence(sequence, T_map_cam, "map")
    field_path = out / "field.pt"
    field_done = info["stages"].get("field", {}).get("settings") == field_settings and field_path.is_file()
    if build_field_stage and not field_done:
        t0 = time.perf_counter()
        from nap3d_graph.fields.build import build_field

        minutes = training_minutes(settings, t0 - started)
        if settings.model == "grid" and settings.steps is None and settings.minutes is None and minutes is not None:
            _say(say, f"field: the grid trains for {minutes:.1f} min (what the {settings.budget_minutes:g}-minute "
                      f"budget leaves)")
        field_obj, report = build_field(posed_sequence, settings.model, steps=settings.steps, minutes=minutes,
                                        seed=settings.seed, device=device, progress=progress,
                                        matcher=settings.matcher, refine_poses=settings.refine_rounds,
                                        refine_method="depth")
        field_obj.meta["map"] = str(out.resolve())
        report["poses"] = "map (self-posed survey)"
        field_obj.save(field_path)
        _write_json(out / "field.report.json", report)
        done("field", time.perf_counter() - t0, model=settings.model, settings=field_settings,
             **({"train_minutes": round(minutes, 2)} if settings.model == "grid" and minutes is not None else {}))

    # Outputs: the plot and, only now, the comparison with the recording's ground truth.
    info["survey_ate"] = _survey_ate(out, sequence, T_map_cam, survey, start, stop,
                                     T_graph_cam if settings.bundle else None)
    info["loops"] = {"candidates": len(loops), "verified": len(verified), "accepted": accepted,
                     "rejected": len(verified) - accepted}
    info["keyframes"] = int(len(keys))
    _write_json(info_path, info)
    _plot(out / "map.png", T_map_cam, T_map_key, verified, sequence, info.get("survey_ate"))
    from .report import write_map_report

    info["report"] = {"file": "report.md", "past_bad_line": write_map_report(out).bad}
    _write_json(info_path, info)
    return MapResult(out, info)


def training_minutes(settings: MapSettings, elapsed_s: float) -> float | None:
    """The grid's training budget in minutes once ``elapsed_s`` seconds of the map are spent:
    its own ``minutes`` when set (None with ``steps``), else what ``budget_minutes`` leaves
    after the reserve, at least ``min_train_minutes``; None when neither is set (the trainer's
    default)."""
    if settings.steps is not None or settings.minutes is not None or settings.budget_minutes is None:
        return None if settings.steps is not None else settings.minutes
    left_s = settings.budget_minutes * 60.0 - elapsed_s - settings.budget_reserve_s
    return max(settings.min_train_minutes, left_s / 60.0)


def _ranges(start: int, stop: int, n: int) -> list[str]:
    parts = []
    if start > 0:
        parts.append(f"0:{start}")
    if stop < n:
        parts.append(f"{stop}:{n}")
    return parts


def _align_config(settings: MapSettings):
    from nap3d_graph.nap3d.config import AlignConfig

    # Both sides are the same camera: no self-calibration of the intrinsics between them.
    return AlignConfig(matcher=settings.matcher, min_opacity=0.5, estimate_intrinsics=False)


def _bundle_settings(sequence, settings: MapSettings) -> BundleSettings:
    """The bundle's settings with the recording's own stereo baseline (a RealSense file says
    it: a D435's 50 mm, not a Kinect's 75) where the settings keep the default."""
    import dataclasses

    baseline_m = getattr(sequence, "stereo_baseline_m", None)
    if baseline_m is None or settings.bundle_settings.baseline_m != BundleSettings.baseline_m:
        return settings.bundle_settings
    return dataclasses.replace(settings.bundle_settings, baseline_m=float(baseline_m))


def _working_intrinsics(sequence, settings: MapSettings):
    """The keyframes' camera at the map's working width."""
    K = sequence.intrinsics
    if settings.width is not None and K.width > settings.width:
        return K.scaled(settings.width, int(round(K.height * settings.width / K.width)))
    return K


def _keyframe_stage(sequence, keys: np.ndarray, settings: MapSettings, retrieval_path: Path, done,
                    progress: bool) -> list[Keyframe]:
    """Stage 2: the keyframes read with their features, the vocabulary clustered from them and
    each one's descriptor, saved to ``retrieval_path``; the stage marked ``done``."""
    t0 = time.perf_counter()
    keyframes = _keyframes(sequence, keys, settings, progress)
    vocabulary = Vocabulary.fit([k.features.descriptors for k in keyframes], settings.vocabulary_k, settings.seed)
    for k in keyframes:
        k.descriptor = vlad(k.features.descriptors, vocabulary)
    np.savez_compressed(retrieval_path, indices=keys, descriptors=np.stack([k.descriptor for k in keyframes]),
                        centres=vocabulary.centres, matcher=settings.matcher,
                        width=-1 if settings.width is None else settings.width)
    done("keyframes", time.perf_counter() - t0, keyframes=len(keys))
    return keyframes


def _loop_stage(sequence, keys: np.ndarray, keyframes: list[Keyframe] | None, descriptors: np.ndarray,
                survey: SurveyOdometry, settings: MapSettings, edges_path: Path, done, progress: bool
                ) -> tuple[list[Edge], list[Loop], list[PairMatches]]:
    """Stage 3: consecutive keyframes aligned, loop candidates proposed and verified (the
    keyframes read again when stage 2 ran before), saved to ``edges_path``; the stage marked
    ``done``. Returns the chain's edges, the loops and the chain's matches."""
    t0 = time.perf_counter()
    if keyframes is None:
        keyframes = _keyframes(sequence, keys, settings, progress)
        for k, d in zip(keyframes, descriptors):
            k.descriptor = d
    chain, chain_kinds, chain_matches = _chain(keyframes, survey, settings)
    pairs = candidates(survey.T_odom_cam[keys], descriptors, settings.loops)
    loops = verify(keyframes, pairs, _align_config(settings), settings.loops, progress)
    _save_edges(edges_path, chain, loops, chain_matches)
    done("loops", time.perf_counter() - t0, candidates=len(pairs), verified=sum(lp.status == "verified" for lp in loops),
         consecutive_aligned=chain_kinds.count("alignment"), consecutive_odometry=chain_kinds.count("odometry"))
    return chain, loops, chain_matches


def _keyframes(sequence, keys: np.ndarray, settings: MapSettings, progress: bool) -> list[Keyframe]:
    """The keyframes read, at the working width, with their local features."""
    from nap3d_graph.nap3d.correct import at_width
    from nap3d_graph.nap3d.matching import detect_features
    from nap3d_graph.progress import progress_bar

    config = _align_config(settings)
    out = []
    for i in progress_bar(keys, desc="keyframes", unit="frame", disable=not progress, mininterval=2.0):
        frame = at_width(sequence[int(i)], settings.width)
        features = detect_features(frame.rgb, config.max_features, matcher=config.matcher)
        out.append(Keyframe(int(i), frame, features))
    return out


def _chain(keyframes: list[Keyframe], survey: SurveyOdometry, settings: MapSettings
           ) -> tuple[list[Edge], list[str], list[PairMatches]]:
    """Consecutive keyframes tied by their own alignment where it verified and agrees with the
    odometry's chained steps (chi-square gate), else by the chain; and the inlier matches of
    the aligned ones."""
    from nap3d_graph.factors.gate import chi2_threshold

    config = _align_config(settings)
    edges, kinds, matches = [], [], []
    threshold = chi2_threshold(settings.gate_p, 6)
    for a in range(len(keyframes) - 1):
        i, j = keyframes[a].index, keyframes[a + 1].index
        T_odom, cov_odom = survey.between(i, j)
        cov_odom = floor_covariance(cov_odom, settings.edge_floor_rad, settings.edge_floor_m)
        T_align, cov_align, alignment = verify_pair(keyframes[a], keyframes[a + 1], config, a, a + 1)
        if alignment.success and alignment.num_inliers >= settings.loops.min_inliers:
            cov_align = floor_covariance(cov_align, settings.edge_floor_rad, settings.edge_floor_m)
            d2 = mahalanobis_sq(np.eye(4), T_odom, Edge(0, 1, T_align, cov_align + cov_odom, "alignment"))
            if d2 <= threshold:
                edges.append(Edge(a, a + 1, T_align, cov_align, "alignment"))
                kinds.append("alignment")
                matches.append(alignment.diagnostics["matches"])
                continue
        edges.append(Edge(a, a + 1, T_odom, cov_odom, "odometry"))
        kinds.append("odometry")
    return edges, kinds, matches


def _save_edges(path: Path, chain: list[Edge], loops: list[Loop], chain_matches: list[PairMatches]) -> None:
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


def _load_edges(path: Path) -> tuple[list[Edge], list[Loop], list[PairMatches]]:
    with np.load(path) as d:
        bounds = np.concatenate([[0], np.cumsum(d["pm_size"])]).astype(int)
        pairs = [PairMatches(int(a), int(b), d["pm_uv_a"][s:e], d["pm_uv_b"][s:e], d["pm_z_a"][s:e], d["pm_z_b"][s:e])
                 for (a, b), s, e in zip(d["pm_ab"], bounds[:-1], bounds[1:])]
        owners = d["pm_owner"]
        chain = [Edge(int(a), int(b), T, c, str(k)) for (a, b), T, c, k in
                 zip(d["chain_ab"], d["chain_T"], d["chain_cov"], d["chain_kind"])]
        loops = []
        for (a, b, i, j, m, n), T, c, (rmse, sm, sd), (source, status, reason) in zip(
                d["loop_abij"], d["loop_T"], d["loop_cov"], d["loop_stats"], d["loop_text"]):
            status = "verified" if status in ("accepted", "rejected") else str(status)
            loops.append(Loop(int(a), int(b), int(i), int(j), str(source), int(m), int(n), float(rmse), float(sm),
                              float(sd), T, c, status, str(reason)))
    for owner, pair in zip(owners, pairs):
        if owner >= 0:
            loops[owner].matches_kept = pair
    return chain, loops, [p for o, p in zip(owners, pairs) if o < 0]


def _write_loops_csv(path: Path, loops: list[Loop]) -> None:
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(Loop.CSV_HEADER)
        for lp in loops:
            writer.writerow(lp.csv_row())
    tmp.replace(path)


def place_frames(T_odom_cam: np.ndarray, keys: np.ndarray, T_map_key: np.ndarray, start: int, stop: int
                 ) -> np.ndarray:
    """Every frame of ``start:stop`` in the map (N, 4, 4; NaN outside): between two keyframes
    by the odometry from each, the two blended along the way (the disagreement at the far
    keyframe spread linearly, in the tangent space), so the path is continuous."""
    n = len(T_odom_cam)
    out = np.full((n, 4, 4), np.nan)
    for (a, b), (T_a, T_b) in zip(zip(keys[:-1], keys[1:]), zip(T_map_key[:-1], T_map_key[1:])):
        for f in range(a, b + 1):
            from_a = T_a @ inv_T(T_odom_cam[a]) @ T_odom_cam[f]
            from_b = T_b @ inv_T(T_odom_cam[b]) @ T_odom_cam[f]
            w = (f - a) / (b - a)
            out[f] = from_a @ exp_se3(w * log_se3(inv_T(from_a) @ from_b))
    if len(keys) == 1:
        out[keys[0]] = T_map_key[0]
    return out


def _survey_ate(out: Path, sequence, T_map_cam: np.ndarray, survey: SurveyOdometry, start: int, stop: int,
                T_graph_cam: np.ndarray | None = None) -> dict | None:
    """``survey_ate.json`` where the recording has ground truth: the map's poses and the
    odometry's alone against it, each SE(3)-aligned, with per-frame errors and the transform
    ``T_gt_map`` that runs use to score in the ground truth's frame."""
    T_gt = getattr(sequence, "T_world_cam_gt", None)
    if T_gt is None:
        return None
    from nap3d_graph.evaluation.alignment import aligned_errors

    stamps = np.asarray(sequence.timestamps, dtype=float)
    T_odom = np.full_like(T_map_cam, np.nan)
    T_odom[start:stop] = survey.T_odom_cam[start:stop]
    mapped = aligned_errors(stamps, T_gt, T_map_cam)
    if mapped is None:
        return None
    odometry = aligned_errors(stamps, T_gt, T_odom)
    graph_only = None if T_graph_cam is None else aligned_errors(stamps, T_gt, T_graph_cam)
    report = {"ground_truth": "the recording's own (never read to build the map)",
              "map": mapped.summary(), "odometry_only": None if odometry is None else odometry.summary(),
              "pose_graph_only": None if graph_only is None else graph_only.summary(),
              "T_gt_map": mapped.T_ref_est.tolist(),
              "per_frame": {"timestamp": mapped.stamps.tolist(), "error_m": mapped.errors_m.round(6).tolist()}}
    if odometry is not None and mapped.rmse_m > odometry.rmse_m:
        report["warning"] = (f"the map's poses are worse than the odometry's alone ({mapped.rmse_m * 100:.2f} against "
                             f"{odometry.rmse_m * 100:.2f} cm ATE): a wrong loop or a bad edge bent it")
        log.warning(report["warning"])
    _write_json(out / "survey_ate.json", report)
    return {k: report[k] for k in ("map", "odometry_only", "pose_graph_only", "T_gt_map")} | (
        {"warning": report["warning"]} if "warning" in report else {})


def _plot(path: Path, T_map_cam: np.ndarray, T_map_key: np.ndarray, loops: list[Loop], sequence, ate) -> None:
    """Top view (the first camera's x and z) of the path, keyframes and loop edges (accepted
    green, rejected red), and the ground truth moved into the map where known."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    posed = np.all(np.isfinite(T_map_cam), axis=(1, 2))
    if ate and sequence.T_world_cam_gt is not None:
        T_gt_in_map = inv_T(np.asarray(ate["T_gt_map"])) @ np.asarray(sequence.T_world_cam_gt)
        ok = np.all(np.isfinite(T_gt_in_map), axis=(1, 2))
        ax.plot(T_gt_in_map[ok, 0, 3], T_gt_in_map[ok, 2, 3], color="0.6", lw=2, label="ground truth (aligned)")
    ax.plot(T_map_cam[posed, 0, 3], T_map_cam[posed, 2, 3], "b-", lw=1, label="map poses")
    ax.plot(T_map_key[:, 0, 3], T_map_key[:, 2, 3], "b.", ms=4)
    for label, status, colour in (("accepted loops", "accepted", "g"), ("rejected loops", "rejected", "r")):
        first = True
        for lp in loops:
            if lp.status != status:
                continue
            a, b = T_map_key[lp.a, :3, 3], T_map_key[lp.b, :3, 3]
            ax.plot([a[0], b[0]], [a[2], b[2]], colour + "-", lw=0.6, alpha=0.7, label=label if first else None)
            first = False
    title = "map: survey poses from the camera alone"
    if ate:
        title += f"\nATE {ate['map']['rmse_m'] * 100:.2f} cm (odometry alone {ate['odometry_only']['rmse_m'] * 100:.2f})"
    ax.set_title(title)
    ax.set_xlabel("x (m, first camera)")
    ax.set_ylabel("z (m, first camera)")
    ax.axis("equal")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
