"""Finding a frame in a map: retrieval, alignment to the field, verification.

The map's keyframes carry a global descriptor (:mod:`.retrieval`) and their pose. For a
query frame: its descriptor against theirs gives the ``top_k`` most similar keyframes. At
each, the frame is first aligned real-vs-real with the keyframe's own colour and depth
(``keyframe_frames.npz``, kept by ``map`` at a small width): real images match across wider
baselines than a render does, so this puts the frame near where it is even when it stands
far from the keyframe. The field then renders there and NAP3D aligns the frame to it,
re-rendering at the corrected pose (:func:`~nap3d_graph.nap3d.correct.correct_pose`); where
the real-vs-real step fails (or the map has no keyframe images), the render starts at the
keyframe's pose. A candidate is verified when its alignment to the field succeeded with
enough inliers and a tight covariance. Once one is verified, the survey keyframes beside
where it landed are tried next (a second view of the same answer), then the retrieval's
remaining candidates. Among the verified ones the tightest wins, and how many others land
within ``agree_m`` of it says how sure the answer is. No verified candidate: a clear refusal,
never a guess.

A frame caught while the camera turns is not one pose: its colour rows were read one after
another, and its depth at another instant. Given the camera's twist (a run knows it from its
odometry), each alignment undoes both as a run's keyframe correction does, with the capture
timing the map's field recorded: the depth moved to the colour's instant, the colour's rows to
the middle row's (:mod:`~nap3d_graph.nap3d.rolling_shutter`), the answer moved to the frame's
stamp. Without a twist the frame is taken as one instant.
"""

from __future__ import annotations

import dataclasses
import logging
import struct
import time
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics, RGBDFrame
from nap3d_graph.conventions import inv_T, log_se3
from nap3d_graph.datasets.depth_timing import resolve_capture_timing
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correct import at_width, correct_pose, real_features
from nap3d_graph.nap3d.matching import Features, detect_features
from nap3d_graph.nap3d.rolling_shutter import at_one_instant

from .folder import MapFolder, load_map_info
from .loops import LOOK_ALIKE_REASON, Keyframe, verify_pair
from .retrieval import Vocabulary, shared_matches, similarities, vlad
from .verification import Verification, worst_sigmas

__all__ = ["KeptFeatures", "KeptFrames", "Relocalisation", "Relocaliser", "RelocaliseSettings", "save_keyframe_frames",
           "write_keyframe_frames", "load_keyframe_frames", "pose_gap", "add_look_alike", "look_alike_offsets"]

log = logging.getLogger(__name__)

#: Width in pixels of the kept keyframe images (a correction's render size; ~0.3 MB a keyframe compressed).
KEYFRAME_WIDTH = 320


def save_keyframe_frames(path: Path, keyframes, matcher: str) -> None:
    """The survey keyframes' colour and depth at ``KEYFRAME_WIDTH``, with their features by
    ``matcher``, in one file (:func:`write_keyframe_frames`)."""
    write_keyframe_frames(path, [at_width(k.frame, KEYFRAME_WIDTH) for k in keyframes], matcher)


def write_keyframe_frames(path: Path, frames: list[RGBDFrame], matcher: str) -> None:
    """Frames already at the kept width, one camera: colour (K, H, W, 3) uint8 and depth (K, H, W)
    uint16 millimetres (0: none), with the camera and each frame's local features as the
    relocaliser detects them (``matcher``, :class:`AlignConfig`'s ``max_features``): keypoints
    ``uv`` (M, 2) float32 and ``descriptors`` (M, D) float32 of all frames in order, frame ``k``'s
    rows ``feature_offsets[k]:feature_offsets[k + 1]``. Written atomically and uncompressed, so a
    run maps the file and reads only the keyframes it tries (:func:`load_keyframe_frames`): read
    whole, a 6-room floor's 609 kept images and their features were 350 MB of the run."""
    K = frames[0].intrinsics
    max_features = AlignConfig().max_features
    features = [detect_features(f.rgb, max_features, matcher=matcher) for f in frames]
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, rgb=np.stack([f.rgb for f in frames]), depth_mm=np.stack([_depth_mm(f.depth_m) for f in frames]),
             camera=np.array([K.fx, K.fy, K.cx, K.cy, K.width, K.height], dtype=float),
             uv=np.concatenate([f.uv for f in features]).astype(np.float32).reshape(-1, 2),
             descriptors=np.concatenate([f.descriptors for f in features]).astype(np.float32),
             feature_offsets=np.cumsum([0] + [len(f) for f in features]), feature_matcher=np.array(matcher),
             feature_max=np.array(max_features))
    tmp.replace(path)


class KeptFrames(Sequence):
    """The kept keyframe images as :func:`write_keyframe_frames` stores them, colour (K, H, W, 3)
    uint8 and depth (K, H, W) uint16 millimetres, each :class:`RGBDFrame` (float depth in
    metres) made when it is asked for: a float depth image of every keyframe held at once was
    190 MB of a run on a 6-room floor's map. A slice gives a list of frames; an item can be
    replaced by a frame of the same camera (in memory: a mapped file is never written)."""

    def __init__(self, rgb: np.ndarray, depth_mm: np.ndarray, intrinsics: Intrinsics):
        self.rgb, self.depth_mm, self.intrinsics = rgb, depth_mm, intrinsics

    def __len__(self) -> int:
        return len(self.rgb)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(len(self))[k]]
        return RGBDFrame(np.array(self.rgb[k]), self.depth_mm[k].astype(np.float32) / np.float32(1000.0),
                         self.intrinsics)

    def __setitem__(self, k: int, frame: RGBDFrame) -> None:
        self.rgb[k], self.depth_mm[k] = frame.rgb, _depth_mm(frame.depth_m)


class KeptFeatures:
    """The kept keyframes' local features as :func:`write_keyframe_frames` stored them (arrays
    that may be mapped from the file): keyframe ``k``'s :class:`Features` made when asked for."""

    def __init__(self, arrays: dict, intrinsics: Intrinsics):
        self.uv, self.descriptors, self.offsets = arrays["uv"], arrays["descriptors"], arrays["feature_offsets"]
        self.matcher, self.max_features = str(arrays["feature_matcher"]), int(arrays["feature_max"])
        self.image_size = (intrinsics.width, intrinsics.height)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, k: int) -> Features:
        a, b = int(self.offsets[k]), int(self.offsets[k + 1])
        return Features(np.asarray(self.uv[a:b], dtype=float), np.array(self.descriptors[a:b]), self.matcher,
                        self.image_size)


def _depth_mm(depth_m: np.ndarray) -> np.ndarray:
    """Depth (H, W) in metres (0 or NaN where missing) as uint16 millimetres (0: none)."""
    return np.rint(np.clip(np.nan_to_num(depth_m), 0, 65.535) * 1000).astype(np.uint16)


#: Arrays of a kept-frames file smaller than this are read; larger ones are mapped from it.
MAP_FROM_BYTES = 1 << 20


def _npz_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz``: those stored uncompressed and larger than ``MAP_FROM_BYTES``
    mapped from the file (copy-on-write: pages read when touched, shared with the page cache,
    never written back), the rest read (a compressed file, as maps before this one wrote it,
    is read whole)."""
    out = {}
    with zipfile.ZipFile(path) as archive, open(path, "rb") as f:
        for info in archive.infolist():
            name = info.filename.removesuffix(".npy")
            if info.compress_type != zipfile.ZIP_STORED:
                out[name] = np.load(archive.open(info))
                continue
            f.seek(info.header_offset + 26)
            name_len, extra_len = struct.unpack("<HH", f.read(4))
            f.seek(info.header_offset + 30 + name_len + extra_len)  # the member's .npy, as written
            version = np.lib.format.read_magic(f)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(f)
            size = int(np.prod(shape)) * dtype.itemsize
            if size < MAP_FROM_BYTES or dtype.hasobject:
                f.seek(info.header_offset + 30 + name_len + extra_len)
                out[name] = np.lib.format.read_array(f, allow_pickle=False)
            else:
                out[name] = np.memmap(path, dtype=dtype, mode="c", offset=f.tell(), shape=shape,
                                      order="F" if fortran else "C")
    return out


def load_keyframe_frames(path: Path, with_features: bool = False):
    """The frames :func:`write_keyframe_frames` kept (:class:`KeptFrames`, mapped from the file
    where it is uncompressed), or None when the map has none or the file cannot be read
    (relocalisation then renders at the keyframes' poses alone). ``with_features``: a pair,
    the frames and their :class:`KeptFeatures` (None when the file holds none: a map made
    before they were kept)."""
    if not path.is_file():
        return (None, None) if with_features else None
    try:
        arrays = _npz_arrays(path)
        fx, fy, cx, cy, w, h = arrays["camera"]
        K = Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h))
        frames = KeptFrames(arrays["rgb"], arrays["depth_mm"], K)
        features = KeptFeatures(arrays, K) if "feature_offsets" in arrays else None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, struct.error) as exc:
        log.warning("%s unreadable (%s): relocalising from renders at the keyframes' poses alone", path, exc)
        return (None, None) if with_features else None
    return (frames, features) if with_features else frames


@dataclass(frozen=True)
class RelocaliseSettings:
    """top_k: keyframes tried at most, in order of similarity, each with ``iterations``
    render-align rounds, until one verified candidate has ``min_agreeing`` others within
    ``agree_m`` / ``agree_deg`` (the tightest of them then gets one more round from where it
    landed); min_inliers, max_sigma_m, max_sigma_deg: what a verified candidate must reach.
    One candidate alone, however many inliers it has, can be a wrong view of a similar
    place (on fr1/desk 3 of 40 lone answers were 7-13 cm off); two renders from different
    keyframes that land together rarely are. ``neighbours``: once a candidate is verified with
    no other agreeing yet, the survey keyframes nearest to where it landed (within
    ``neighbour_m`` / ``neighbour_deg``, not yet tried) are tried next, at most this many:
    retrieval ranks by appearance, so its next candidates can lie elsewhere in the map, while
    a keyframe beside the answer sees what the frame sees from another viewpoint, the
    independent second view the agreement asks for (0: retrieval order alone).
    ``shortlist``: the global descriptor's most similar keyframes, this many, are re-ranked by
    how many distinctive local matches (ratio below ``distinct_ratio``) each shares with the
    frame before the ``top_k`` are tried: the descriptor summarises a whole image, so a
    keyframe that sees the frame's part of the place from 30 cm away can rank below others of
    the same texture, while the matches count what the two views share (0: the descriptor's
    order alone; needs the map's kept keyframe images). ``start_min_inliers``: the inliers the
    real-vs-real step needs for its answer to be where the field is rendered (else the
    keyframe's pose): that answer only places the render, which the verification then judges,
    so it can ask less than a verified candidate does (12: chosen on the tuning sets of
    ``benchmarks/map_relocalise_rules.py``, where it found more of simulated room 3 than 30 and
    lost nothing on fr1/xyz).

    Rivals: a floor repeats itself (offices with the same furniture), and a frame of one can
    verify in its twin as well as in itself: the first answer found is not the only one there.
    Once an answer is found, the shortlist's keyframes that stand more than ``rival_m`` from it
    and whose real-vs-real step puts the frame that far from it too are tried, the best-ranked
    ``rival_checks`` of them; a verified answer there (or one among those already tried) with at
    least ``rival_ratio`` of the answer's inliers is a *rival*:
    the relocalisation reports it, and a run that is not yet placed stays unplaced
    (:class:`~.start.MapPlacement`) until a frame that only one place explains. 1 m: twins
    are a room apart, while the answers one place gives agree within centimetres (0: no
    rivals looked for)."""

    top_k: int = 6
    shortlist: int = 20
    distinct_ratio: float = 0.8
    neighbours: int = 2
    neighbour_m: float = 0.40
    neighbour_deg: float = 30.0
    iterations: int = 1
    min_agreeing: int = 1
    min_inliers: int = 30
    start_min_inliers: int = 12
    max_sigma_m: float = 0.03
    max_sigma_deg: float = 2.0
    agree_m: float = 0.05
    agree_deg: float = 3.0
    rival_m: float = 1.0
    rival_checks: int = 2
    rival_ratio: float = 0.5

    @property
    def verification(self) -> Verification:
        """What a verified candidate must reach, as the rule shared with the survey's loops
        (looser here: a render is farther from the frame than a keyframe pair)."""
        return Verification(self.min_inliers, self.max_sigma_m, self.max_sigma_deg)


@dataclass
class Relocalisation:
    """``T_map_cam`` (4, 4) where the frame is in the map, ``covariance`` (6, 6), the
    keyframe (frame index in the survey) it was found from, its inliers and sigmas,
    ``agreeing``: how many other verified candidates land within the agreement radius,
    ``tried`` the candidates aligned, ``seconds``; ``success`` False with ``reason``."""

    success: bool
    T_map_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.inf))
    keyframe: int = -1
    inliers: int = 0
    sigma_m: float = float("inf")
    sigma_deg: float = float("inf")
    agreeing: int = 0
    tried: int = 0
    seconds: float = 0.0
    reason: str = ""
    wide_baseline: int = 0
    #: Other places the frame verified in (:class:`RelocaliseSettings`' rivals): each
    #: ``{"T_map_cam": (4, 4), "keyframe": survey frame, "inliers": n, "distance_m": from this answer}``.
    rivals: list = field(default_factory=list)
    #: Keyframes looked at for rivals after the answer was found (not in ``tried``).
    rival_checks: int = 0

    @property
    def ambiguous(self) -> bool:
        """Whether another place answered as well (a twin room): where the frame is is not known."""
        return bool(self.rivals)

    def describe(self) -> str:
        """One line: where it started and how sure it is (or why it could not)."""
        if not self.success:
            return f"not found in the map: {self.reason}"
        t = self.T_map_cam[:3, 3]
        return (f"found in the map at ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}) m from survey keyframe {self.keyframe}: "
                f"{self.inliers} inliers, sigma {self.sigma_m * 100:.1f} cm / {self.sigma_deg:.2f} deg, "
                f"{self.agreeing} of {max(self.tried - 1, 0)} other candidates tried agree ({self.seconds:.2f} s)"
                + (f"; ambiguous: {len(self.rivals)} other place(s) {self.rivals[0]['distance_m']:.1f} m or more away "
                   "answer as well" if self.rivals else ""))

    def to_dict(self) -> dict:
        return {"success": self.success, "T_map_cam": self.T_map_cam.tolist(), "keyframe": self.keyframe,
                "inliers": self.inliers, "sigma_m": self.sigma_m, "sigma_deg": self.sigma_deg,
                "agreeing": self.agreeing, "tried": self.tried, "seconds": round(self.seconds, 3),
                "reason": self.reason, "wide_baseline": self.wide_baseline,
                "rivals": [{**r, "T_map_cam": np.asarray(r["T_map_cam"]).tolist()} for r in self.rivals],
                "rival_checks": self.rival_checks}


class Relocaliser:
    """Relocalise frames in a map folder (``nap3d-graph map``) with its field."""

    def __init__(self, map_dir, field_obj, config: AlignConfig | None = None,
                 render_intrinsics: Intrinsics | None = None, settings: RelocaliseSettings | None = None):
        folder = MapFolder(Path(map_dir))
        with np.load(folder.keyframes) as data:
            self.indices = data["indices"].astype(int)
            self.descriptors = data["descriptors"]
            self.vocabulary = Vocabulary(data["centres"])
            self.matcher = str(data["matcher"])
            width = int(data["width"])
            self.width = None if width < 0 else width
        self.T_map_key = np.load(folder.keyframe_poses)
        #: Whether the map repeats itself: its survey found look-alike places a room apart (loops
        #: refused against its odometry); None when the map does not say (made without a loop stage).
        self.look_alikes = _look_alikes(folder)
        #: The map-frame moves (4, 4) from a place to its look-alike that its survey met
        #: (:func:`look_alike_offsets`): a start is placed only once it has ruled them out.
        self.look_alike_offsets = look_alike_offsets(folder, self.T_map_key)
        self.field = field_obj
        # The capture timing the map's field recorded: what a frame given its twist is aligned with.
        self.timing, _ = resolve_capture_timing(field_obj)
        # No depth-scale estimate: nothing here reads it, and its RANSAC is a tenth of an attempt.
        self.config = dataclasses.replace(config or AlignConfig(matcher=self.matcher), estimate_scale=False)
        self.render_intrinsics = render_intrinsics
        self.settings = settings or RelocaliseSettings()
        self.keyframe_frames, kept = load_keyframe_frames(folder.keyframe_frames, with_features=True)
        # The features the map kept, when they are what this relocaliser would detect.
        self._kept_features = kept if (kept is not None and kept.matcher == self.config.matcher
                                       and kept.max_features == self.config.max_features) else None
        self._keyframe_features: dict[int, object] = {}
        if self.keyframe_frames is not None and self._kept_features is None and self.settings.shortlist > 0:
            # Every kept keyframe's features now (~15 ms each at 320 px), not while a frame
            # waits: the ranking's shortlist asks for 20 of them at the first attempt.
            t0 = time.perf_counter()
            for k in range(len(self.keyframe_frames)):
                self._features(k)
            log.info("relocaliser: features of %d keyframes detected in %.2f s", len(self.keyframe_frames),
                     time.perf_counter() - t0)

    def descriptor(self, frame: RGBDFrame) -> np.ndarray:
        """The frame's global descriptor, its features detected as the map's keyframes' were."""
        features = detect_features(at_width(frame, self.width).rgb, 0, matcher=self.matcher)
        return vlad(features.descriptors, self.vocabulary)

    def _start_pose(self, query, k: int) -> tuple[np.ndarray, bool]:
        """``(T_map_cam, wide)``: where to render for candidate keyframe ``k``: the query
        aligned real-vs-real with the keyframe's own image (``wide`` True), else the keyframe's
        pose. ``query``: the query frame at the kept images' width with its features."""
        if self.keyframe_frames is None or query is None:
            return self.T_map_key[k], False
        survey = Keyframe(int(self.indices[k]), self.keyframe_frames[k], self._features(k))
        T_query_key, _, alignment = verify_pair(query, survey, self.config)
        if not alignment.success or alignment.num_inliers < self.settings.start_min_inliers:
            return self.T_map_key[k], False
        return self.T_map_key[k] @ inv_T(T_query_key), True

    def _features(self, k: int):
        """Kept keyframe ``k``'s local features: as the map kept them, else detected once (all of
        them when the relocaliser is made, unless the ranking is off)."""
        if self._kept_features is not None:
            return self._kept_features[k]
        if k not in self._keyframe_features:
            rgb = self.keyframe_frames.rgb[k]  # type: ignore[union-attr]  # the colour alone: no depth made
            self._keyframe_features[k] = detect_features(rgb, self.config.max_features, matcher=self.config.matcher)
        return self._keyframe_features[k]

    def _ranked(self, frame: RGBDFrame, query) -> list[int]:
        """The shortlist of candidate keyframes (indices into the map's keyframes), most likely
        first: the global descriptor's ``shortlist`` most similar, re-ranked by the distinctive
        local matches each shares with ``query`` (ties: the descriptor's order); the first
        ``top_k`` are the candidates, the rest where rivals are looked for."""
        s = self.settings
        order = [int(k) for k in np.argsort(-similarities(self.descriptor(frame), self.descriptors), kind="stable")]
        if s.shortlist <= 0 or query is None:
            return order[: max(s.shortlist, s.top_k)]
        short = order[: max(s.shortlist, s.top_k)]
        shared = [shared_matches(query.features.descriptors, self._features(k).descriptors, s.distinct_ratio)
                  for k in short]
        return [short[i] for i in np.argsort(-np.asarray(shared), kind="stable")]

    def _query(self, frame: RGBDFrame, detected=None):
        """The query at the kept images' width with its features (None without kept images);
        ``detected``: ``(shape, features)`` of the frame already detected at that shape."""
        if self.keyframe_frames is None:
            return None
        kept_width = self.keyframe_frames.intrinsics.width
        small = at_width(frame, kept_width)
        if small.intrinsics.width != kept_width:
            return None  # a query narrower than the map's images: render from the keyframes' poses
        if detected is not None and detected[0] == small.intrinsics.shape:
            return Keyframe(-1, small, detected[1])
        return Keyframe(-1, small, detect_features(small.rgb, self.config.max_features, matcher=self.config.matcher))

    def _neighbours(self, T_map_cam: np.ndarray, tried: set) -> list[int]:
        """The survey keyframes (indices into the map's keyframes) nearest to ``T_map_cam``
        within the neighbourhood, nearest first, not in ``tried``, at most ``neighbours``."""
        s = self.settings
        if s.neighbours <= 0:
            return []
        gaps = [(pose_gap(T_map_cam, T), k) for k, T in enumerate(self.T_map_key) if k not in tried]
        near = [(m, k) for (m, deg), k in gaps if m <= s.neighbour_m and deg <= s.neighbour_deg]
        return [k for _, k in sorted(near)[: s.neighbours]]

    def _agreeing(self, found: list) -> list:
        """The largest group of verified candidates that agree with one of them (that one
        first), or all of them when none agree (each its own group)."""
        s = self.settings
        best: list = found[:1]
        for f in found:
            group = [f] + [g for g in found if g is not f and _close(f[2], g[2], s.agree_m, s.agree_deg)]
            if len(group) > len(best):
                best = group
        return best

    def locate(self, frame: RGBDFrame, twist: np.ndarray | None = None) -> Relocalisation:
        """Where ``frame`` is in the map; never raises on data (``success`` False, ``reason``).
        ``twist``: (6,) the camera's body twist per second (GTSAM order) while it took the frame,
        or None (see the module's text)."""
        started = time.perf_counter()
        s = self.settings
        frame, motion, shift = self._at_one_instant(frame, twist)
        found, reasons, wide = [], [], 0
        # The frame's features at the render's size, detected once for every candidate's correction
        # (and for the real-vs-real step and the ranking too when the kept images are that size).
        render_intrinsics = self.render_intrinsics or frame.intrinsics
        feats_real, _ = real_features(frame, render_intrinsics, self.config)
        query = self._query(frame, (render_intrinsics.shape, feats_real))
        ranked = self._ranked(frame, query)
        queue, tried_keys = ranked[: s.top_k], set()
        while queue:
            k = queue.pop(0)
            if k in tried_keys:
                continue
            tried_keys.add(k)
            verified, refusal, started_wide = self._candidate(frame, query, k, feats_real, motion)
            wide += started_wide
            if verified is None:
                reasons.append(refusal)
                continue
            found.append(verified)
            if len(self._agreeing(found)) > s.min_agreeing:
                break
            if len(found) == 1:  # the first verified answer: its neighbours next, for a second view of it
                queue = self._neighbours(verified[2], tried_keys) + queue
        tried = len(reasons) + len(found)
        every_verified, found = found, self._agreeing(found)
        if len(found) <= s.min_agreeing:
            if found:
                reasons.append(f"{len(found)} verified candidate(s) but fewer than {s.min_agreeing} other(s) agreeing")
            found = []
        if not found:
            why = "; ".join(sorted(set(reasons))[:3]) or "no candidate"
            return Relocalisation(False, tried=tried, seconds=time.perf_counter() - started, wide_baseline=wide,
                                  reason=f"none of the {tried} most similar keyframes verified ({why})")
        sigma_m, k, T, cov, inliers, sigma_deg = self._tightest_again(frame, found, feats_real, motion)
        # Rivals are weighed against the answer's first round, as theirs is (the extra round from
        # where it landed gives the answer alone more inliers).
        first_round = max(f[4] for f in found)
        rivals = self._rivals(frame, query, feats_real, motion, (T, first_round), every_verified, ranked, tried_keys)
        return Relocalisation(True, T @ shift, cov, int(self.indices[k]), inliers, sigma_m, sigma_deg, len(found) - 1,
                              tried, time.perf_counter() - started, wide_baseline=wide, rival_checks=len(tried_keys) - tried,
                              rivals=[{**r, "T_map_cam": r["T_map_cam"] @ shift} for r in rivals])

    def _rivals(self, frame: RGBDFrame, query, feats_real, motion, answer: tuple, verified: list, ranked: list[int],
                tried_keys: set) -> list[dict]:
        """Other places the frame verifies in (see :class:`RelocaliseSettings`): among the
        candidates ``verified`` already and the ``rival_checks`` best of ``ranked`` whose
        keyframes stand over ``rival_m`` from ``answer`` (``(T_map_cam, inliers)``), each one
        landing over ``rival_m`` from it with ``rival_ratio`` of its inliers; ``tried_keys`` grows."""
        s = self.settings
        if s.rival_m <= 0:
            return []
        T_answer, inliers = answer
        checked = 0
        for k in ranked:
            if checked >= s.rival_checks:
                break
            if k in tried_keys or pose_gap(T_answer, self.T_map_key[k])[0] <= s.rival_m:
                continue
            tried_keys.add(k)
            # The real-vs-real step says cheaply where this keyframe puts the frame: a keyframe
            # across the same room that sees the same wall puts it where the answer is (no rival
            # there, and no render spent on it).
            start = self._start_pose(query, k)
            if not start[1] or pose_gap(T_answer, start[0])[0] <= s.rival_m:
                continue
            checked += 1
            candidate = self._candidate(frame, query, k, feats_real, motion, start)[0]
            if candidate is not None:
                verified = verified + [candidate]
        rivals = []
        for _, k, T, _, n, _ in verified:
            distance_m = pose_gap(T_answer, T)[0]
            if distance_m > s.rival_m and n >= s.rival_ratio * inliers:
                rivals.append({"T_map_cam": T, "keyframe": int(self.indices[k]), "inliers": int(n),
                               "distance_m": round(distance_m, 3)})
        return sorted(rivals, key=lambda r: -r["inliers"])

    def _at_one_instant(self, frame: RGBDFrame, twist: np.ndarray | None) -> tuple[RGBDFrame, object, np.ndarray]:
        """``(frame, motion, shift)`` of :func:`~nap3d_graph.nap3d.rolling_shutter.at_one_instant` with
        the field's capture timing; the frame as it is, None and the identity without a twist
        or a capture timing."""
        if twist is None or not np.all(np.isfinite(twist)) or self.timing is None:
            return frame, None, np.eye(4)
        return at_one_instant(frame, self.timing, np.asarray(twist, dtype=float), float(self.timing.readout_s), 1.0)

    def _candidate(self, frame: RGBDFrame, query, k: int, feats_real, motion=None, start: tuple | None = None
                   ) -> tuple[tuple | None, str, bool]:
        """``(verified, refusal, wide)``: keyframe ``k`` as a candidate, its render started
        where :meth:`_start_pose` puts it (or ``start``, its answer already had; ``wide``:
        real-vs-real); ``verified``: ``(sigma_m,
        k, T_map_cam, covariance, inliers, sigma_deg)`` when the correction passes the
        verification, else None with ``refusal`` saying why."""
        s = self.settings
        T_start, wide = start if start is not None else self._start_pose(query, k)
        correction = correct_pose(frame, self.field, T_start, iterations=s.iterations, config=self.config,
                                  render_intrinsics=self.render_intrinsics, feats_real=feats_real, motion=motion)
        if not correction.success:
            return None, correction.reason, wide
        cov, inliers = correction.covariance, correction.alignment.num_inliers
        sigma_m, sigma_deg = worst_sigmas(cov)
        refusal = s.verification.refusal(inliers, sigma_m, sigma_deg)
        if refusal:
            return None, refusal, wide
        return (sigma_m, k, correction.T_world_cam_corrected, cov, inliers, sigma_deg), "", wide

    def _tightest_again(self, frame: RGBDFrame, found: list, feats_real, motion=None) -> tuple:
        """The tightest of the agreeing candidates ``found`` after one more round from where it
        landed (a nearer render), or as it was when that round is no tighter than the rule."""
        s = self.settings
        sigma_m, k, T, cov, inliers, sigma_deg = min(found, key=lambda f: f[0])
        again = correct_pose(frame, self.field, T, iterations=1, config=self.config,
                             render_intrinsics=self.render_intrinsics, feats_real=feats_real, motion=motion)
        if again.success and again.alignment.num_inliers >= s.min_inliers:
            s2, d2 = worst_sigmas(again.covariance)
            if s2 <= s.max_sigma_m:
                return s2, k, again.T_world_cam_corrected, again.covariance, again.alignment.num_inliers, d2
        return sigma_m, k, T, cov, inliers, sigma_deg


def _look_alikes(folder: MapFolder) -> bool | None:
    """``map.json``'s count of survey loops refused as look-alike places, as a flag (None: the
    map does not record it)."""
    try:
        count = load_map_info(folder.root)["stages"]["loops"].get("look_alikes")
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return None if count is None else bool(count)


#: Look-alike moves (metres) closer than this are one move. Two twin pairs of a row of rooms can
#: stand 10.4 and 11.3 m apart: at a metre, the second pair's move was taken for the first's,
#: and a start in one of them was "ruled out" of its own room at a pose 0.9 m off (and placed in
#: its twin). One pair's moves from loops over a floor spread by a few decimetres (a tenth of a
#: degree turns a move 20 m from the map's origin by 3 cm).
SAME_LOOK_ALIKE_M = 0.5


def add_look_alike(offsets: list[np.ndarray], offset: np.ndarray) -> None:
    """Add the map-frame move ``offset`` (4, 4) from a place to its look-alike to ``offsets``,
    both ways, unless one within ``SAME_LOOK_ALIKE_M`` is there already (one per look-alike pair:
    its answers a few centimetres apart are the same move)."""
    for T in (np.asarray(offset, dtype=float), inv_T(offset)):
        if all(np.linalg.norm(T[:3, 3] - known[:3, 3]) > SAME_LOOK_ALIKE_M for known in offsets):
            offsets.append(T)


def look_alike_offsets(folder: MapFolder, T_map_key: np.ndarray) -> list[np.ndarray]:
    """The moves between look-alike places the map's survey met (:func:`add_look_alike`): a
    loop refused as a look-alike place matched keyframe b's view to keyframe a's as if b stood
    at ``T_map_a @ T_a_b``, so ``T_map_a @ T_a_b @ inv(T_map_b)`` moves b's place to where
    it looks the same. ``T_map_key`` (K, 4, 4): the map's keyframe poses. [] when the map keeps
    no loops (``edges.npz``) or met no look-alike."""
    try:
        with np.load(folder.edges) as data:
            pairs, T_a_b, text = data["loop_abij"][:, :2], data["loop_T"], data["loop_text"]
    except (OSError, KeyError, ValueError):
        return []
    offsets: list[np.ndarray] = []
    for (a, b), T, (_, status, reason) in zip(pairs, T_a_b, text):
        if status == "refused" and str(reason).startswith(LOOK_ALIKE_REASON) and max(a, b) < len(T_map_key):
            add_look_alike(offsets, T_map_key[a] @ T @ inv_T(T_map_key[b]))
    return offsets


def pose_gap(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """``(metres, degrees)`` between two poses: the norms of the translation and rotation parts
    of ``log(inv(T_a) @ T_b)``."""
    d = log_se3(inv_T(T_a) @ T_b)
    return float(np.linalg.norm(d[3:])), float(np.degrees(np.linalg.norm(d[:3])))


def _close(T_a: np.ndarray, T_b: np.ndarray, metres: float, degrees: float) -> bool:
    """Whether two poses are within ``metres`` and ``degrees`` of each other."""
    m, deg = pose_gap(T_a, T_b)
    return m <= metres and deg <= degrees
