"""``nap3d-graph map``: a survey's poses from the camera alone, then the field at them.

Stages, each writing its file into the map folder when it finishes (a map interrupted in any
stage resumes from the last finished one; ``map.json`` records the settings, and a folder
made with other settings is refused rather than mixed):

1. ``odometry.npz``: frame-to-frame odometry from the first frame (:mod:`.survey`), and the
   stretches it tracked between its losses of the camera.
2. ``keyframes.npz``: the keyframes, their global descriptors (VLAD over the matcher's local
   descriptors, :mod:`.retrieval`) and the vocabulary: what relocalisation retrieves from.
3. ``loops.csv`` / ``edges.npz``: consecutive keyframes aligned real-vs-real, loop candidates
   by appearance and proximity verified the same way (:mod:`.loops`); the longest run of
   stretches that verified loops join is kept (the keyframe files rewritten for it).
4. ``poses.txt``: the robust pose graph (:mod:`.pose_graph`), every frame placed between its
   keyframes, gauge at the first keyframe, the metric scale from depth.
5. ``field.pt`` and ``field.report.json``: the field of ``model`` trained at those poses
   (:func:`~nap3d_graph.fields.build.build_field`; capture timing estimated from the poses'
   multi-view agreement, and the bundle-like depth refinement of the training poses when
   asked); ``map.png``; ``survey_ate.json`` where the recording has ground truth (never
   read before this last step).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from nap3d_graph.arguments import (
    RUN_MATCHER,
    matcher_option,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    setting,
)
from nap3d_graph.conventions import exp_se3, inv_T, log_se3
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.datasets.posed import PosedSequence
from nap3d_graph.fields.build import build_field
from nap3d_graph.fields.submaps import SubmapSettings
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correct import at_width
from nap3d_graph.nap3d.matching import detect_features
from nap3d_graph.pools import SerialPool, peak_memory_gb
from nap3d_graph.progress import progress_bar
from nap3d_graph.textfiles import write_json_atomic
from nap3d_graph.trajectory import write_tum_trajectory

from .bundle import BundleSettings, PairMatches, agreeing_pairs, bundle_adjust, keyframe_twists
from .depth_check import depth_against_images
from .folder import MAP_INFO, MapFolder
from .loops import (
    Keyframe,
    Loop,
    LoopSettings,
    candidates,
    consecutive_edges,
    load_edges,
    refuse_look_alikes,
    save_edges,
    verify_on_pool,
    write_loops_csv,
)
from .mesh import fuse_mesh
from .pose_graph import Edge, GraphResult, floor_covariance, solve
from .relocalise import load_keyframe_frames, save_keyframe_frames, write_keyframe_frames
from .report import write_outputs
from .retrieval import Vocabulary, vlad
from .submap_fields import submap_minutes, train_submap_fields
from .submaps import plan_submaps, with_viewing_frames
from .survey import (
    SurveyOdometry,
    joined_run,
    keyframe_indices,
    lost_frames,
    segment_keyframes,
    stretch_of,
    track,
    tracked_segments,
)

__all__ = ["MapSettings", "MapResult", "build_map", "training_minutes", "place_frames", "place_kept_frames",
           "index_posed_survey"]

log = logging.getLogger(__name__)

#: Settings of the field alone: changing them re-trains the field, not the poses.
FIELD_SETTINGS = ("model", "minutes", "steps", "refine_rounds", "budget_minutes", "budget_reserve_s",
                  "min_train_minutes", "submaps")

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

    odometry: str = setting("vo", "--odom", choices=("vo", "dense"),
        help="frame-to-frame odometry of the survey: vo (features, the matcher's; default) or dense (OpenCV's "
             "RGB-D odometry at 320 px)")
    matcher: str = setting("xfeat", "--matcher", command_default=RUN_MATCHER, **matcher_option(RUN_MATCHER))
    width: int | None = setting(None, "--width", type=positive_int, metavar="PX",
        help="keyframes and --odom vo work at this width (default: the frames' own)")
    keyframe_every: int = setting(5, "--keyframe-every", type=positive_int,
        help="a keyframe every N frames, sooner after 10 cm or 10 deg of motion (default 5)")
    keyframe_distance_m: float = 0.10
    keyframe_angle_deg: float = 10.0
    max_guesses: int = 3
    vocabulary_k: int = 32
    edge_floor_m: float = 0.002
    edge_floor_rad: float = 0.002
    gate_p: float = 0.999
    model: str = setting("grid", "--model", choices=("grid", "splat", "views"), help="the field (default grid)")
    minutes: float | None = setting(None, "--minutes", type=positive_float,
        help="grid: its own training budget in minutes instead of what --budget-minutes leaves")
    steps: int | None = setting(None, "--steps", type=positive_int,
        help="grid: training budget in steps instead of minutes (the same field on any machine)")
    budget_minutes: float | None = setting(5.0, "--budget-minutes", type=non_negative_float, metavar="MIN",
        help="the whole map's time budget, field included: the grid trains for what the other stages leave (at "
             "least a minute; default 5; 0: no budget, the grid trains for --minutes or 5)")
    budget_reserve_s: float = 90.0
    min_train_minutes: float = 1.0
    refine_rounds: int = setting(0, "--refine-rounds", type=non_negative_int, metavar="N",
        help="rounds of the depth refinement of the training poses (each frame's depth aligned with its "
             "neighbours', the poses solved again) before the field is trained (default 0)")
    seed: int = setting(0, "--seed", type=int, help="random seed (vocabulary, training; default 0)")
    bundle: bool = True
    loops: LoopSettings = field(default_factory=LoopSettings)
    bundle_settings: BundleSettings = field(default_factory=BundleSettings)
    submaps: SubmapSettings = field(default_factory=SubmapSettings)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class MapResult:
    """What ``build_map`` made: ``info`` (map.json's content) and the folder."""

    folder: Path
    info: dict


def _say(say, text: str) -> None:
    log.info(text)
    if say is not None:
        say(text)


def build_map(sequence, out: Path, settings: MapSettings | None = None, *, progress: bool = True, say=None,
              build_field_stage: bool = True, device: str | None = None, mesh: bool = True, pool=None) -> MapResult:
    """Build (or resume) the map of ``sequence`` in ``out``. The sequence's ground truth is
    never read before the survey's poses are final (only ``survey_ate.json`` uses it).
    ``mesh``: fuse ``map.ply`` at the map's poses (:mod:`.mesh`; skipped, with the reason in
    ``map.json``, without Open3D). ``pool``: where a survey cut into submaps trains their fields
    and where many loop candidates are verified (:func:`nap3d_graph.pools.make_pool`; None: one
    after another in this process)."""
    settings = settings or MapSettings()
    started = time.perf_counter()
    folder = _open_folder(sequence, out, settings)
    survey, segments = _odometry_stage(sequence, folder, settings, progress, say)
    keys = segment_keyframes(survey.T_odom_cam, segments, every=settings.keyframe_every,
                             distance_m=settings.keyframe_distance_m, angle_deg=settings.keyframe_angle_deg)
    keys, keyframes, descriptors = _keyframe_stage(sequence, keys, folder, settings, progress)
    keys, chain, loops, chain_matches = _loop_stage(sequence, keys, keyframes, descriptors, survey, segments, folder,
                                                    settings, progress, say, pool)
    del keyframes  # the frames are not needed any more
    start, stop, lost = _kept_frames(survey, segments, keys, folder, say)
    graph, T_map_key, verified = _graph_stage(sequence, keys, survey, chain, loops, chain_matches, folder, settings,
                                              say)
    T_map_cam = place_kept_frames(survey, keys, T_map_key, start, stop, lost)
    _write_poses(sequence, survey, T_map_cam, T_map_key, start, stop, folder)
    if build_field_stage:
        _field_stage(sequence, T_map_cam, folder, settings, started, progress, say, device, pool)
    if mesh:
        _mesh_stage(sequence, T_map_cam, folder, settings, progress, say)
    T_graph_cam = place_kept_frames(survey, keys, graph.T_map_key, start, stop, lost) if settings.bundle else None
    write_outputs(folder, sequence, survey, (start, stop), T_map_cam, T_map_key, T_graph_cam, loops, verified)
    return MapResult(folder.root, folder.info)


def index_posed_survey(sequence, out: Path, T_map_cam: np.ndarray, settings: MapSettings | None = None,
                       progress: bool = False) -> MapFolder:
    """The relocalisation index of a survey whose poses are already known, ``T_map_cam`` (N, 4, 4)
    for every frame of ``sequence`` (motion capture, a simulator's truth): its keyframes chosen
    as ``map`` chooses them, their descriptors, vocabulary and small images, their poses, and
    the look-alike places its loops meet (:func:`_look_alike_stage`); no odometry, graph or
    field (bring the field: a :class:`~.relocalise.Relocaliser` takes any). What a study of
    relocalisation alone reads, apart from every survey error."""
    settings = settings or MapSettings()
    T_map_cam = np.asarray(T_map_cam, dtype=float)
    if T_map_cam.shape != (len(sequence), 4, 4):
        raise ValueError(f"T_map_cam must be ({len(sequence)}, 4, 4) for the survey's frames, got {T_map_cam.shape}")
    folder = _open_folder(sequence, out, settings)
    keys = keyframe_indices(T_map_cam, 0, len(sequence), settings.keyframe_every, settings.keyframe_distance_m,
                            settings.keyframe_angle_deg)
    keys, keyframes, descriptors = _keyframe_stage(sequence, keys, folder, settings, progress)
    _look_alike_stage(sequence, keys, keyframes, descriptors, T_map_cam[keys], folder, settings, progress)
    np.save(folder.keyframe_poses, T_map_cam[keys])
    folder.info["posed_by"] = "given poses (index_posed_survey)"
    folder.save()
    return folder


def _look_alike_stage(sequence, keys: np.ndarray, keyframes: list[Keyframe] | None, descriptors: np.ndarray,
                      T_map_key: np.ndarray, folder: MapFolder, settings: MapSettings, progress: bool) -> None:
    """A posed survey's loops as stage 3 finds them (candidates verified), those that put a
    keyframe a room from its given pose ``T_map_key`` (K, 4, 4) refused as look-alike places
    (:func:`~.loops.refuse_look_alikes`, the given poses standing for the odometry), saved as a
    map saves them: a relocaliser then knows where the survey looks alike, as in a map made
    by ``map``, and a study of placement measures the rules a map's run has. Reused when
    finished before."""
    if folder.finished("loops", folder.edges):
        return
    t0 = time.perf_counter()
    keyframes = _keyframes_read(sequence, keys, keyframes, descriptors, settings, progress)
    pairs = candidates(T_map_key, descriptors, settings.loops)
    loops = verify_on_pool(keyframes, pairs, align_config(settings), settings.loops, None, progress)
    look_alikes = refuse_look_alikes(loops, T_map_key, settings.loops)
    save_edges(folder.edges, [], loops, [])
    folder.done("loops", time.perf_counter() - t0, candidates=len(pairs),
                verified=sum(lp.status == "verified" for lp in loops), look_alikes=look_alikes)


def _keyframes_read(sequence, keys: np.ndarray, keyframes: list[Keyframe] | None, descriptors: np.ndarray,
                    settings: MapSettings, progress: bool) -> list[Keyframe]:
    """``keyframes`` as stage 2 left them, or read again with their ``descriptors`` (K, D) when
    stage 2 finished before (it keeps no keyframes in memory then)."""
    if keyframes is not None:
        return keyframes
    keyframes = read_keyframes(sequence, keys, settings, progress)
    for k, d in zip(keyframes, descriptors):
        k.descriptor = d
    return keyframes


def _open_folder(sequence, out: Path, settings: MapSettings) -> MapFolder:
    """The map folder for this survey and these settings (resumed, or made); a folder holding
    a map of other data or pose settings is refused (``FileExistsError``)."""
    pose_settings = {k: v for k, v in settings.to_dict().items() if k not in FIELD_SETTINGS}
    wanted = {"data": str(getattr(sequence, "path", "")), "frame_range": list(getattr(sequence, "frame_range", ())),
              "recording_id": getattr(sequence, "recording_id", None), "settings": pose_settings}
    if getattr(sequence, "depth_scale_source", "") in ("argument", "intrinsics.json"):
        wanted["depth_units_per_m"] = float(sequence.depth_units_per_m)  # a declared unit: another survey
    if getattr(sequence, "fps", None) is not None:  # stamps from the camera's rate: another clock, another survey
        wanted["fps"] = float(sequence.fps)
    if hasattr(sequence, "registration"):  # 7-Scenes: another colour camera is another survey
        wanted["registration"] = {k: v for k, v in sequence.registration.to_dict().items()
                                  if k in ("colour", "T_colour_depth")}  # not its fit's figures (NaN when given)
    info_path = Path(out) / MAP_INFO
    if info_path.is_file() and json.loads(info_path.read_text()).get("extensions"):
        raise FileExistsError(f"{out} holds a map extended by other surveys: it is not re-made or "
                              "resumed from one survey; choose another folder")
    return MapFolder.open(out, wanted, (*wanted, "depth_units_per_m", "registration"))


def _odometry_stage(sequence, folder: MapFolder, settings: MapSettings, progress: bool, say
                    ) -> tuple[SurveyOdometry, list[tuple[int, int]]]:
    """Stage 1: the survey's odometry (reused when finished before) and the stretches it
    tracked between its losses, ``(survey, [(start, stop), ...])``."""
    if folder.finished("odometry", folder.odometry):
        survey = SurveyOdometry.load(folder.odometry)
        _say(say, "odometry: finished before, reused")
        return survey, tracked_segments(survey.ok, settings.max_guesses)
    t0 = time.perf_counter()
    survey = track(sequence, settings.odometry, settings.matcher, settings.width, progress)
    survey.save(folder.odometry)
    segments = tracked_segments(survey.ok, settings.max_guesses)
    folder.done("odometry", time.perf_counter() - t0, guessed_steps=int((~survey.ok).sum()),
                segments=[list(s) for s in segments])
    return survey, segments


def _kept_frames(survey: SurveyOdometry, segments: list[tuple[int, int]], keys: np.ndarray, folder: MapFolder, say
                 ) -> tuple[int, int, list[tuple[int, int]]]:
    """The frames the map keeps, ``(start, stop, lost)``: from its first keyframe to its last,
    but the ``lost`` stretches ``[(first, stop), ...]`` between them (rejoined by loops, never
    placed); recorded in ``map.json`` and said when the odometry lost the camera."""
    start, stop = int(keys[0]), int(keys[-1]) + 1
    lost = lost_frames(segments, start, stop)
    n = len(survey.ok)
    unplaced = n - (stop - start) + sum(b - a for a, b in lost)
    folder.info["segment"] = {"start": start, "stop": stop, "dropped_frames": unplaced,
                              "rejoined": [list(g) for g in lost], "losses": len(segments) - 1,
                              "guessed_steps": int((~survey.ok[start + 1:stop]).sum())}
    if len(segments) > 1:
        _say(say, f"the odometry lost the camera {len(segments) - 1} time(s); {len(lost)} loss(es) rejoined by "
                  f"verified loops: the map keeps frames {start}:{stop} and leaves {unplaced} unplaced "
                  f"({', '.join(_ranges(start, stop, n) + [f'{a}:{b}' for a, b in lost]) or 'none'})")
    return start, stop, lost


def place_kept_frames(survey: SurveyOdometry, keys: np.ndarray, T_map_key: np.ndarray, start: int, stop: int,
                      lost: list[tuple[int, int]]) -> np.ndarray:
    """Every kept frame in the map (:func:`place_frames`); the frames of a loss NaN (their
    odometry is a guess)."""
    T_map_cam = place_frames(survey.T_odom_cam, keys, T_map_key, start, stop)
    for a, b in lost:
        T_map_cam[a:b] = np.nan
    return T_map_cam


def _keyframe_stage(sequence, keys: np.ndarray, folder: MapFolder, settings: MapSettings, progress: bool
                    ) -> tuple[np.ndarray, list[Keyframe] | None, np.ndarray]:
    """Stage 2: the keyframes read with their features, the vocabulary clustered from them and
    each one's descriptor, saved (with the keyframes' small images for relocalisation);
    ``(keys, keyframes, descriptors)``, the keys as saved (when the stage finished before, those
    the loop stage kept) and the keyframes None when the stage finished before."""
    keyframes = None
    if not folder.finished("keyframes", folder.keyframes):
        t0 = time.perf_counter()
        keyframes = read_keyframes(sequence, keys, settings, progress)
        vocabulary = Vocabulary.fit([k.features.descriptors for k in keyframes], settings.vocabulary_k, settings.seed)
        for k in keyframes:
            k.descriptor = vlad(k.features.descriptors, vocabulary)
        np.savez_compressed(folder.keyframes, indices=keys, descriptors=np.stack([k.descriptor for k in keyframes]),
                            centres=vocabulary.centres, matcher=settings.matcher,
                            width=-1 if settings.width is None else settings.width)
        folder.done("keyframes", time.perf_counter() - t0, keyframes=len(keys))
    with np.load(folder.keyframes) as data:
        keys, descriptors = data["indices"], data["descriptors"]
    if not folder.keyframe_frames.is_file():  # a map made before the relocaliser read them gets them now
        save_keyframe_frames(folder.keyframe_frames, keyframes or read_keyframes(sequence, keys, settings, progress),
                             settings.matcher)
    return keys, keyframes, descriptors


def _loop_stage(sequence, keys: np.ndarray, keyframes: list[Keyframe] | None, descriptors: np.ndarray,
                survey: SurveyOdometry, segments: list[tuple[int, int]], folder: MapFolder, settings: MapSettings,
                progress: bool, say, pool=None) -> tuple[np.ndarray, list[Edge], list[Loop], list[PairMatches]]:
    """Stage 3: consecutive keyframes aligned, loop candidates proposed and verified (the
    keyframes read again when stage 2 ran before; the candidates on ``pool`` when there are
    many, :func:`~.loops.verify_on_pool`); when the odometry lost the camera, only the longest
    run of stretches joined by verified loops kept (:func:`~.survey.joined_run`,
    :func:`_keep_keyframes`); saved; reused when finished before. Returns the keyframes kept,
    the chain's edges, the loops and the chain's matches."""
    if folder.finished("loops", folder.edges):
        _say(say, "loops: finished before, reused")
        return (keys, *load_edges(folder.edges))
    t0 = time.perf_counter()
    keyframes = _keyframes_read(sequence, keys, keyframes, descriptors, settings, progress)
    config = align_config(settings)
    chain, chain_kinds, chain_matches = consecutive_edges(keyframes, survey, config, settings.loops.min_inliers,
                                                          settings.gate_p, settings.edge_floor_rad,
                                                          settings.edge_floor_m)
    chain = _loosen_across_losses(chain, segments, keys)
    pairs = candidates(survey.T_odom_cam[keys], descriptors, settings.loops)
    loops = verify_on_pool(keyframes, pairs, config, settings.loops, pool, progress)
    look_alikes = refuse_look_alikes(loops, survey.T_odom_cam[keys], settings.loops)
    if look_alikes:
        _say(say, f"loops: {look_alikes} verified loop(s) refused as look-alike places (a room or more from where the "
                  "odometry puts them)")
    first, last = joined_run(segments, keys, [(lp.a, lp.b) for lp in loops if lp.status == "verified"],
                             settings.loops.join_loops)
    if (first, last) != (0, len(keys) - 1):
        keys, chain, loops, chain_matches = _keep_keyframes(folder, keys, first, last, chain, loops, chain_matches)
    save_edges(folder.edges, chain, loops, chain_matches)
    folder.done("loops", time.perf_counter() - t0, candidates=len(pairs),
                verified=sum(lp.status == "verified" for lp in loops), look_alikes=look_alikes,
                consecutive_aligned=chain_kinds.count("alignment"), consecutive_odometry=chain_kinds.count("odometry"))
    return keys, chain, loops, chain_matches


#: Sigmas (rad, m) of the odometry's edge across a loss of the camera: its steps there were
#: constant-velocity guesses, wrong by tens of degrees when the camera swept while it saw nothing;
#: the loops that join the stretches place them, not the guess.
LOST_EDGE_SIGMA = (1.0, 3.0)


def _loosen_across_losses(chain: list[Edge], segments: list[tuple[int, int]], keys: np.ndarray) -> list[Edge]:
    """The chain with each odometry edge between two stretches (a loss of the camera) given
    :data:`LOST_EDGE_SIGMA`."""
    stretch = stretch_of(segments, keys)
    lost_cov = np.diag([LOST_EDGE_SIGMA[0] ** 2] * 3 + [LOST_EDGE_SIGMA[1] ** 2] * 3)
    return [replace(e, covariance=lost_cov) if e.kind == "odometry" and stretch[e.a] != stretch[e.b] else e
            for e in chain]


def _keep_keyframes(folder: MapFolder, keys: np.ndarray, first: int, last: int, chain: list[Edge], loops: list[Loop],
                    chain_matches: list[PairMatches]) -> tuple[np.ndarray, list[Edge], list[Loop], list[PairMatches]]:
    """Keyframe positions ``first..last`` kept, the rest dropped: the keyframe files rewritten
    for them, and the chain, the loops and the matches between kept keyframes renumbered from
    ``first``."""
    def kept(a: int, b: int) -> bool:
        return first <= a and b <= last

    def moved(pm: PairMatches | None) -> PairMatches | None:
        return None if pm is None else replace(pm, a=pm.a - first, b=pm.b - first)

    with np.load(folder.keyframes) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["indices"], arrays["descriptors"] = arrays["indices"][first:last + 1], arrays["descriptors"][first:last + 1]
    tmp = folder.keyframes.with_suffix(".tmp.npz")  # atomically: a map stopped here resumes from whole files
    np.savez_compressed(tmp, **arrays)
    tmp.replace(folder.keyframes)
    frames = load_keyframe_frames(folder.keyframe_frames)
    if frames is not None:
        write_keyframe_frames(folder.keyframe_frames, frames[first:last + 1], str(arrays["matcher"]))
    chain = [replace(e, a=e.a - first, b=e.b - first) for e in chain if kept(e.a, e.b)]
    loops = [replace(lp, a=lp.a - first, b=lp.b - first, matches_kept=moved(lp.matches_kept))
             for lp in loops if kept(lp.a, lp.b)]
    chain_matches = [moved(pm) for pm in chain_matches if kept(pm.a, pm.b)]
    return keys[first:last + 1], chain, loops, chain_matches


def _graph_stage(sequence, keys: np.ndarray, survey: SurveyOdometry, chain: list[Edge], loops: list[Loop],
                 chain_matches: list[PairMatches], folder: MapFolder, settings: MapSettings, say
                 ) -> tuple[GraphResult, np.ndarray, list[Loop]]:
    """Stage 4: the robust pose graph over the chain and every verified loop, then the bundle
    adjustment (:func:`graph_and_bundle`; each loop's decision written to ``loops.csv``);
    ``(graph, T_map_key, verified loops)``."""
    t0 = time.perf_counter()
    verified = [lp for lp in loops if lp.status in ("verified", "accepted", "rejected")]
    graph, T_map_key, report = graph_and_bundle(sequence, keys, survey, chain, verified, chain_matches, settings)
    write_loops_csv(folder.loops_table, loops)
    if report is not None:
        folder.info["bundle"] = report
        _say(say, f"bundle adjustment: {report.get('landmarks', 0)} landmarks, {report.get('observations', 0)} "
                  f"observations, colour rows read in {report.get('readout_s', 0) * 1000:.0f} ms, "
                  f"{report.get('loops_admitted', 0)} loop(s) the graph turned away admitted; keyframes moved "
                  f"{report.get('median_keyframe_move_mm', 0):.1f} mm (median)")
    accepted = int(graph.loop_kept.sum())
    admitted = sum(lp.status == "admitted" for lp in verified)
    folder.done("graph", time.perf_counter() - t0, keyframes=len(keys), loops_verified=len(verified),
                loops_accepted=accepted, loops_admitted=admitted, loops_rejected=len(verified) - accepted - admitted)
    if accepted == 0:
        _say(say, "no loop closure found: the map's poses are the odometry's alone (they drift as it does)")
    return graph, T_map_key, verified


def graph_and_bundle(sequence, keys: np.ndarray, survey: SurveyOdometry, chain: list[Edge], verified: list[Loop],
                     chain_matches: list[PairMatches], settings: MapSettings
                     ) -> tuple[GraphResult, np.ndarray, dict | None]:
    """The robust pose graph over ``chain`` and the ``verified`` loops from the odometry's
    keyframe poses (each loop's ``status`` and ``reason`` set: accepted or rejected), then with
    ``settings.bundle`` the bundle adjustment (:func:`adjust_keyframes`: rejected loops its
    poses agree with become 'admitted'); ``(graph, T_map_key (K, 4, 4) final, the bundle's report
    or None)``. What ``map`` solves, and what the fault benchmark solves again with a loop forced in."""
    loop_edges = [Edge(lp.a, lp.b, lp.T_a_b, floor_covariance(lp.covariance, settings.edge_floor_rad,
                                                              settings.edge_floor_m), "loop") for lp in verified]
    graph = solve(survey.T_odom_cam[keys], chain, loop_edges, settings.gate_p)
    for lp, kept, weight, d2 in zip(verified, graph.loop_kept, graph.loop_weights, graph.loop_d2):
        lp.status = "accepted" if kept else "rejected"
        lp.reason = "" if kept else (f"inconsistent with the graph (GNC weight {weight:.2f}, d2 {d2:.1f})")
    if not settings.bundle:
        return graph, graph.T_map_key, None
    twists = keyframe_twists(survey.T_odom_cam, np.asarray(sequence.timestamps, dtype=float), keys)
    bundle_settings = _bundle_settings(sequence, settings)
    T_map_key, report = adjust_keyframes(graph.T_map_key, chain_matches, verified,
                                         _working_intrinsics(sequence, settings), bundle_settings, twists,
                                         odometry=[e for e in chain if e.kind == "odometry"])
    report["baseline_from"] = ("the recording's calibration" if bundle_settings is not settings.bundle_settings
                               else "the settings")
    # The depth against the images, at the final poses over every pair the adjustment used.
    used = chain_matches + [lp.matches_kept for lp in verified
                            if lp.status in ("accepted", "admitted") and lp.matches_kept is not None]
    report["depth_against_images"] = depth_against_images(used, T_map_key, _working_intrinsics(sequence, settings))
    return graph, T_map_key, report


def adjust_keyframes(T_graph_key: np.ndarray, chain_matches: list[PairMatches], verified: list[Loop],
                     intrinsics, bundle_settings: BundleSettings, twists: np.ndarray | None,
                     odometry: list[Edge] | None = None) -> tuple[np.ndarray, dict]:
    """The graph's keyframes (K, 4, 4) adjusted over the chain's matches and every kept loop's,
    each keyframe's observations moved to its middle row along ``twists`` (K, 6); then the
    loops the graph turned away (status 'rejected') whose matches agree with the adjusted
    poses as well as the kept loops' (:func:`~.bundle.agreeing_pairs`) are admitted (status
    'admitted', the reason saying by how much) and the adjustment solved again with them.
    ``odometry``: the chain's edges no keyframe matches measured, held in both solves.

    Why: the graph judged each loop by its relative pose, measured as if the colour camera
    had a global shutter; where the survey turned fast that pose is off by more than its
    covariance says, and the graph turns true loops away. Their matches, once the rolling
    shutter is undone, land where the kept loops' do; a loop between places that are not the
    same lands tens of pixels off or more and stays out."""
    kept = [lp for lp in verified if lp.status == "accepted" and lp.matches_kept is not None]
    pairs = chain_matches + [lp.matches_kept for lp in kept]
    odometry = odometry or []
    T_map_key, report = bundle_adjust(T_graph_key, pairs, intrinsics, bundle_settings, twists, odometry)
    report["loops_admitted"] = 0
    turned_away = [lp for lp in verified if lp.status == "rejected" and lp.matches_kept is not None]
    if "reason" in report or not turned_away:
        return T_map_key, report
    agree, px, gate = agreeing_pairs([lp.matches_kept for lp in turned_away], [lp.matches_kept for lp in kept],
                                     T_map_key, intrinsics, bundle_settings.admit_factor, twists, report["readout_s"])
    report["admission"] = {"gate_px": gate, "turned_away_px": [round(float(v), 2) for v in px]}
    admitted = [lp for lp, ok in zip(turned_away, agree) if ok]
    if not admitted:
        return T_map_key, report
    for lp, ok, value in zip(turned_away, agree, px):
        if ok:
            lp.status = "admitted"
            lp.reason += (f"; admitted by the bundle adjustment: its matches land {value:.1f} px from theirs "
                          f"(gate {gate:.1f} px)")
    T_admitted, second = bundle_adjust(T_map_key, pairs + [lp.matches_kept for lp in admitted], intrinsics,
                                       bundle_settings, twists, odometry)
    if "reason" in second:  # the second solve failed: the first one's poses stand, nothing admitted
        for lp in admitted:
            lp.status = "rejected"
        return T_map_key, report
    second["loops_admitted"] = len(admitted)
    second["admission"] = report["admission"]
    second["before_admission"] = {"readout_s": report["readout_s"], "readout_search": report["readout_search"],
                                  "noise_rounds": report["noise_rounds"]}
    return T_admitted, second


def _write_poses(sequence, survey: SurveyOdometry, T_map_cam: np.ndarray, T_map_key: np.ndarray, start: int,
                 stop: int, folder: MapFolder) -> None:
    """The survey's poses in the map, the odometry's alone and the keyframes' poses, written."""
    stamps = np.asarray(sequence.timestamps, dtype=float)
    posed = np.all(np.isfinite(T_map_cam), axis=(1, 2))
    write_tum_trajectory(folder.poses, stamps[posed], T_map_cam[posed])
    write_tum_trajectory(folder.odometry_poses, stamps[start:stop], survey.T_odom_cam[start:stop])
    np.save(folder.keyframe_poses, T_map_key)


def _field_stage(sequence, T_map_cam: np.ndarray, folder: MapFolder, settings: MapSettings, started: float,
                 progress: bool, say, device: str | None, pool=None) -> None:
    """Stage 5: the field of ``settings.model`` trained at the map's poses (kept when one with
    the same field settings finished before): one ``field.pt`` for a survey of one submap's size,
    else a field per submap (:mod:`.submap_fields`), as jobs on ``pool`` (None: one process)."""
    # As map.json holds them; how a survey is cut matters only once it is cut (a one-field map
    # made before submaps resumes as it was).
    field_settings = {k: v for k, v in settings.to_dict().items() if k in FIELD_SETTINGS and k != "submaps"}
    plan = plan_submaps(T_map_cam, settings.submaps)
    if len(plan) > 1:
        field_settings["submaps"] = settings.submaps.to_dict()
        _submap_field_stage(sequence, T_map_cam, folder, settings, plan, field_settings, started, say, device, pool,
                            progress)
        return
    if folder.info["stages"].get("field", {}).get("settings") == field_settings and folder.field.is_file():
        return
    t0 = time.perf_counter()

    minutes = training_minutes(settings, t0 - started)
    if settings.model == "grid" and settings.steps is None and settings.minutes is None and minutes is not None:
        _say(say, f"field: the grid trains for {minutes:.1f} min (what the {settings.budget_minutes:g}-minute "
                  f"budget leaves)")
    field_obj, report = build_field(PosedSequence(sequence, T_map_cam, "map"), settings.model, steps=settings.steps,
                                    minutes=minutes, seed=settings.seed, device=device, progress=progress,
                                    matcher=settings.matcher, refine_poses=settings.refine_rounds,
                                    refine_method="depth")
    field_obj.meta["map"] = str(folder.root.resolve())
    report["poses"] = "map (self-posed survey)"
    field_obj.save(folder.field)
    write_json_atomic(folder.field_report, report, default=float)
    folder.done("field", time.perf_counter() - t0, model=settings.model, settings=field_settings,
                **({"train_minutes": round(minutes, 2)} if settings.model == "grid" and minutes is not None else {}))


def _submap_field_stage(sequence, T_map_cam: np.ndarray, folder: MapFolder, settings: MapSettings, plan: list,
                        field_settings: dict, started: float, say, device: str | None, pool,
                        progress: bool = False) -> None:
    """Stage 5 for a survey cut into submaps: each its own field and budget (a one-room map's
    budget less its share of the stages before), trained on ``pool``."""
    stage = folder.info["stages"].get("field", {})
    if (stage.get("settings") == field_settings and stage.get("done")
            and all((folder.root / s.file).is_file() for s in plan)):
        return
    t0 = time.perf_counter()
    minutes = settings.minutes
    if settings.model == "grid" and settings.steps is None and minutes is None:
        minutes = submap_minutes(settings.budget_minutes, settings.min_train_minutes, settings.budget_reserve_s,
                                 t0 - started, len(plan))
    _say(say, f"field: the survey is cut into {len(plan)} submaps of at most {settings.submaps.max_frames} frames "
              f"and {settings.submaps.max_length_m:g} m along the floor (each its own field)")
    if folder.field.is_file():
        folder.field.unlink()  # a one-field map of these poses made before: the submaps replace it
    plan = with_viewing_frames(plan, sequence, T_map_cam, settings.submaps, progress)
    train_submap_fields(sequence, T_map_cam, folder, plan, settings, settings.submaps, field_settings, minutes,
                        pool or SerialPool(), device, say)
    folder.info["stages"].setdefault("field", {}).update(seconds=round(time.perf_counter() - t0, 2), model=settings.model,
                                          settings=field_settings, done=True, submap_count=len(plan),
                                          **({"train_minutes": round(minutes, 2)} if minutes is not None else {}),
                                          peak_memory_gb=peak_memory_gb())
    folder.save()


def _mesh_stage(sequence, T_map_cam: np.ndarray, folder: MapFolder, settings: MapSettings, progress: bool,
                say) -> None:
    """Stage 6: ``map.ply``, the survey fused at the map's poses (each depth at its capture
    instant by the field's timing, when there is a field) a submap at a time, and its walls'
    thickness in ``map.json``. Never fails the map: without Open3D, or when nothing could be
    fused, the reason is recorded instead."""
    if folder.finished("mesh", folder.mesh):
        return
    timing = None
    if folder.field_report.is_file():
        timing = CaptureTiming.of(json.loads(folder.field_report.read_text()).get("timing"))
    t0 = time.perf_counter()
    try:
        result = fuse_mesh(PosedSequence(sequence, T_map_cam, "map"), folder.mesh, timing=timing, progress=progress,
                           submaps=plan_submaps(T_map_cam, settings.submaps))
    except ImportError as exc:
        folder.info["mesh"] = {"file": None, "reason": str(exc)}
        folder.save()
        _say(say, f"mesh: not written ({exc})")
        return
    except (ValueError, OSError, RuntimeError) as exc:  # RuntimeError: Open3D's own errors
        folder.info["mesh"] = {"file": None, "reason": f"nothing fused: {exc}"}
        folder.save()
        log.warning("mesh: not written (%s)", exc)
        return
    folder.info["mesh"] = result.to_dict()
    folder.done("mesh", time.perf_counter() - t0, vertices=result.vertices)
    thickness = result.thickness.get("thickness_m")
    _say(say, f"mesh: {folder.mesh.name} ({result.vertices} vertices from {result.frames} frames); walls "
              + (f"{thickness * 100:.1f} cm thick at most" if thickness is not None else "not measured"))


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


def align_config(settings: MapSettings):
    # Both sides are the same camera: no self-calibration of the intrinsics between them, and
    # no depth-scale estimate (nothing in the map reads it).
    return AlignConfig(matcher=settings.matcher, min_opacity=0.5, estimate_intrinsics=False, estimate_scale=False)


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


def read_keyframes(sequence, keys: np.ndarray, settings: MapSettings, progress: bool) -> list[Keyframe]:
    """The keyframes read, at the working width, with their local features."""
    config = align_config(settings)
    out = []
    for i in progress_bar(keys, desc="keyframes", unit="frame", disable=not progress, mininterval=2.0):
        frame = at_width(sequence[int(i)], settings.width)
        features = detect_features(frame.rgb, config.max_features, matcher=config.matcher)
        out.append(Keyframe(int(i), frame, features))
    return out


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
