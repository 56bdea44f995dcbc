"""NAP3D alignment: Procrustes, RANSAC, anisotropic residual, covariance honesty, bad input."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from nap3d_graph import RenderedView, RGBDFrame, align_views, correct_pose
from nap3d_graph.baselines.pnp import pnp_align
from nap3d_graph.conventions import inv_T, log_se3, pose_error
from nap3d_graph.evaluation.perturb import random_perturbation
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correspondences import sample_depth
from nap3d_graph.nap3d.ransac import anisotropic_residual_sq, kabsch_batch, ransac_procrustes, weighted_umeyama
from nap3d_graph.sims.sensors import sensor_frame
from nap3d_graph.sims.sequence import default_intrinsics
from nap3d_graph.sims.trajectories import make_trajectory


def random_rigid(rng):
    return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(), rng.normal(size=3)


def test_umeyama_recovers_exact_transform():
    rng = np.random.default_rng(0)
    R, t = random_rigid(rng)
    x = rng.uniform(-2, 2, size=(50, 3)) + [0, 0, 3]
    y = x @ R.T + t
    R_est, t_est = weighted_umeyama(x, y, rng.uniform(0.1, 1, 50))
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-9)
    # Batched Kabsch agrees on minimal samples, and never returns a reflection.
    Rb, tb = kabsch_batch(x[None, :3], y[None, :3])
    np.testing.assert_allclose(Rb[0], R, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(kabsch_batch(rng.normal(size=(20, 3, 3)), rng.normal(size=(20, 3, 3)))[0]),
                               1.0, atol=1e-9)


def test_weights_are_honoured():
    """Two clusters disagreeing on the translation: the weighted fit moves to the heavy one
    exactly as the weighted mean says."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, size=(40, 3))
    y = x.copy()
    y[20:] += [0.1, 0, 0]  # the second half says t = +10 cm in x
    w = np.r_[np.full(20, 1.0), np.full(20, 3.0)]
    R, t = weighted_umeyama(x, y, w)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-2)
    # With an identity rotation the weighted solution is the weighted mean shift: 0.075.
    R_fixed_t = (w[:, None] * (y - x)).sum(0) / w.sum()
    assert t[0] == pytest.approx(R_fixed_t[0], abs=5e-3)
    assert abs(weighted_umeyama(x, y)[1][0] - 0.05) < 5e-3


def test_ransac_recovers_with_half_outliers():
    rng = np.random.default_rng(2)
    R, t = random_rigid(rng)
    t *= 0.1
    x = rng.uniform([-1.5, -1, 1], [1.5, 1, 4], size=(400, 3))
    y = x @ R.T + t + rng.normal(size=(400, 3)) * 0.002
    outliers = rng.random(400) < 0.5
    y[outliers] = rng.uniform([-1.5, -1, 1], [1.5, 1, 4], size=(outliers.sum(), 3))
    s = np.full(400, 0.004)
    res = ransac_procrustes(x, y, np.ones(400), s, s, AlignConfig(seed=3))
    assert res.success
    assert np.linalg.norm(res.t - t) < 2e-3
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(res.R.T @ R).as_rotvec())) < 0.1
    # The consensus is the inlier half, not much more or less.
    assert (res.inliers & ~outliers).sum() > 0.95 * (~outliers).sum()
    assert (res.inliers & outliers).sum() < 0.02 * outliers.sum()


def test_anisotropic_residual_rejects_what_isotropic_accepts():
    """A 2 cm lateral error is far outside a 3 mm lateral sigma although the z-sigma is 3 cm:
    the paper's anisotropic residual rejects it; an isotropic test at the depth scale does not."""
    x = np.array([[0.0, 0.0, 3.0]])
    y = x + [[0.02, 0.0, 0.0]]
    r2_aniso = anisotropic_residual_sq(np.eye(3), np.zeros(3), x, y, np.array([1 / 0.003**2]), np.array([1 / 0.03**2]))
    r2_iso = anisotropic_residual_sq(np.eye(3), np.zeros(3), x, y, np.array([1 / 0.03**2]), np.array([1 / 0.03**2]))
    thr = AlignConfig().inlier_chi2
    assert r2_aniso[0] > thr > r2_iso[0]
    # The same error along the optical axis is accepted by both.
    y_z = x + [[0.0, 0.0, 0.02]]
    assert anisotropic_residual_sq(np.eye(3), np.zeros(3), x, y_z, np.array([1 / 0.003**2]),
                                   np.array([1 / 0.03**2]))[0] < thr


def test_degenerate_and_too_few_points():
    s = np.full(10, 0.01)
    collinear = np.c_[np.linspace(0, 1, 10), np.zeros(10), np.full(10, 2.0)]
    res = ransac_procrustes(collinear, collinear, np.ones(10), s, s)
    assert not res.success and "degenerate" in res.reason
    two = ransac_procrustes(collinear[:2], collinear[:2], np.ones(2), s[:2], s[:2])
    assert not two.success and "too few" in two.reason


def test_sample_depth_subpixel_and_edges():
    depth = np.full((10, 10), 2.0, np.float32)
    depth[:, 5:] = 4.0  # an edge between columns 4 and 5
    depth[0, 0] = 0.0
    z = sample_depth(depth, np.array([[2.5, 2.5], [4.4, 3.0], [4.6, 3.0], [0.2, 0.2], [20.0, 3.0]]))
    assert z[0] == pytest.approx(2.0)
    assert z[1] == 2.0 and z[2] == 4.0  # nearest across the edge, never a mix
    assert z[3] == pytest.approx(2.0) or np.isnan(z[3])  # a hole next to it: nearest valid or missing
    assert np.isnan(z[4])
    # Inverse-depth bilinear is exact on a slanted plane: 1/z linear in u.
    u = np.arange(10)
    plane = (1.0 / (0.25 + 0.02 * u))[None, :].repeat(10, 0).astype(np.float64)
    zs = sample_depth(plane, np.array([[3.3, 4.0]]), max_rel_jump=0.2)
    assert zs[0] == pytest.approx(1.0 / (0.25 + 0.02 * 3.3), rel=1e-9)


@pytest.fixture(scope="module")
def scenarios(room):
    """(frame, T_world_cam_gt, T_world_cam_est) triples in the hold-out room at 320x240."""
    scene, _ = room
    K = default_intrinsics(320, 240)
    traj = make_trajectory("traverse", scene, np.random.default_rng(0), 20.0)
    rng = np.random.default_rng(5)
    out = []
    for _ in range(8):
        T_world_cam_gt = traj.T_world_cam(rng.uniform(0, 20))
        out.append((sensor_frame(scene, T_world_cam_gt, K, rng), T_world_cam_gt, T_world_cam_gt @ random_perturbation(rng)))
    return out


def test_align_views_corrects_perturbed_pose(room, scenarios):
    _, field = room
    errors = {"refined": [], "plain": [], "pnp": []}
    for frame, T_world_cam_gt, T_world_cam_est in scenarios:
        view = field.render(T_world_cam_est, frame.intrinsics)
        for method in ("refined", "plain"):
            a = align_views(frame, view, AlignConfig(method=method))
            assert a.success, a.reason
            assert a.num_inliers >= 30 and a.num_inliers <= a.num_matches
            errors[method].append(pose_error(a.corrected_pose(T_world_cam_est), T_world_cam_gt))
        p = pnp_align(frame, view)
        assert p.success
        errors["pnp"].append(pose_error(p.corrected_pose(T_world_cam_est), T_world_cam_gt))
    med = {k: np.median(np.array(v), axis=0) for k, v in errors.items()}
    # From +-10 cm / +-5 deg down to millimetres.
    assert med["refined"][0] < 0.003 and med["refined"][1] < 0.06
    assert med["plain"][0] < 0.008
    # The refinement uses the pixel positions: never less accurate than PnP on the same matches.
    assert med["refined"][0] <= med["pnp"][0] * 1.15
    assert med["refined"][0] < med["plain"][0]


def test_correct_pose_iterates_and_improves(room, scenarios):
    _, field = room
    one, three = [], []
    for frame, T_world_cam_gt, T_world_cam_est in scenarios[:5]:
        c1 = correct_pose(frame, field, T_world_cam_est, iterations=1)
        c3 = correct_pose(frame, field, T_world_cam_est, iterations=3)
        assert c1.success and c3.success and c1.iterations == 1 and 2 <= c3.iterations <= 3
        assert c3.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(c3.covariance) > 0)
        one.append(pose_error(c1.T_world_cam_corrected, T_world_cam_gt)[0])
        three.append(pose_error(c3.T_world_cam_corrected, T_world_cam_gt)[0])
    assert np.median(three) < np.median(one)
    assert np.median(three) < 0.0015


def _disturb_global_random_state():
    """What other code in a process may do: reseed and advance OpenCV's RNG (PnP-RANSAC,
    FLANN's randomised trees) and the C library's rand()."""
    import ctypes

    import cv2

    cv2.setRNGSeed(12345)
    rng = np.random.default_rng(0)
    a, b = rng.random((300, 128), np.float32), rng.random((300, 128), np.float32)
    cv2.FlannBasedMatcher({"algorithm": 1, "trees": 5}, {"checks": 32}).knnMatch(a, b, k=2)
    cv2.randu(np.zeros((8, 8)), 0, 1)
    ctypes.CDLL(None).srand(ctypes.c_uint(777))


def test_alignment_does_not_depend_on_what_ran_before(room, scenarios):
    """The same pairs aligned in two orders, with other code disturbing OpenCV's and the C
    library's random state in between, give bit-identical results."""
    _, field = room
    pairs = [(frame, field.render(T_world_cam_est, frame.intrinsics)) for frame, _, T_world_cam_est in scenarios[:4]]

    def run(order):
        out = {}
        for k in order:
            _disturb_global_random_state()
            frame, view = pairs[k]
            for config in (AlignConfig(), AlignConfig(method="plain"), AlignConfig(nn_search="flann")):
                a = align_views(frame, view, config)
                out[(k, config.method, config.nn_search)] = (a.T_real_rendered, a.covariance, a.num_inliers)
            p = pnp_align(frame, view)
            out[(k, "pnp", "")] = (p.T_real_rendered, p.covariance, p.num_inliers)
        return out

    forward, backward = run([0, 1, 2, 3]), run([3, 2, 1, 0])
    assert forward.keys() == backward.keys()
    for key in forward:
        np.testing.assert_array_equal(forward[key][0], backward[key][0], err_msg=str(key))
        np.testing.assert_array_equal(forward[key][1], backward[key][1], err_msg=str(key))
        assert forward[key][2] == backward[key][2]


# The configurations the covariance is used in: the pipeline (one render-align round at
# 320x240, the odometry's prediction a few centimetres off), Evaluation K (one round,
# +-10 cm / 5 deg) and correct_pose iterating; the paper's plain method and the refined one.
NEES_CASES = {
    "pipeline-refined": dict(method="refined", rounds=1, max_trans_m=0.03, max_rot_deg=1.5),
    "pipeline-plain": dict(method="plain", rounds=1, max_trans_m=0.03, max_rot_deg=1.5),
    "eval-k-refined": dict(method="refined", rounds=1, max_trans_m=0.10, max_rot_deg=5.0),
    "iterated-refined": dict(method="refined", rounds=3, max_trans_m=0.10, max_rot_deg=5.0),
}


@pytest.mark.parametrize("case", list(NEES_CASES))
@pytest.mark.slow
def test_covariance_is_honest_nees(room, case):
    """NEES of the corrected pose over 100 trials in the hold-out room (never used to
    calibrate the covariance), for the 6-dof pose and each 3-dof block (rotation,
    translation): inside chi2's 99% band of the mean."""
    settings = NEES_CASES[case]
    scene, field = room
    K = default_intrinsics(320, 240)
    traj = make_trajectory("traverse", scene, np.random.default_rng(1), 20.0)
    rng = np.random.default_rng(7)
    config = AlignConfig(method=settings["method"])
    nees = []
    attempts = 0
    while len(nees) < 100:
        attempts += 1  # a bounded loop: a method that fails most frames fails the test, never hangs it
        assert attempts <= 150, f"{len(nees)} successes in {attempts - 1} attempts"
        T_world_cam_gt = traj.T_world_cam(rng.uniform(0, 20))
        frame = sensor_frame(scene, T_world_cam_gt, K, rng)
        T_world_cam_est = T_world_cam_gt @ random_perturbation(rng, settings["max_trans_m"], settings["max_rot_deg"])
        c = correct_pose(frame, field, T_world_cam_est, iterations=settings["rounds"], config=config)
        if not c.success:
            continue
        e = log_se3(inv_T(c.T_world_cam_corrected) @ T_world_cam_gt)
        P = c.covariance
        nees.append([e @ np.linalg.solve(P, e), e[:3] @ np.linalg.solve(P[:3, :3], e[:3]),
                     e[3:] @ np.linalg.solve(P[3:, 3:], e[3:])])
    means = np.mean(nees, axis=0)
    n = len(nees)
    for value, dof, block in zip(means, (6, 3, 3), ("pose", "rotation", "translation")):
        lo, hi = chi2.ppf([0.005, 0.995], dof * n) / n
        assert lo <= value <= hi, f"{case} {block}: NEES mean {value:.2f} outside [{lo:.2f}, {hi:.2f}] (chi2({dof}))"


def _blank_view(K, depth=2.0):
    return RenderedView(np.full((K.height, K.width, 3), 128, np.uint8), np.full(K.shape, depth, np.float32),
                        np.ones(K.shape, np.float32), K)


def test_bad_input_returns_reasons(room, scenarios):
    _, field = room
    frame, T_world_cam_gt, T_world_cam_est = scenarios[0]
    K = frame.intrinsics
    view = field.render(T_world_cam_est, K)
    blank = align_views(RGBDFrame(np.zeros((K.height, K.width, 3), np.uint8), frame.depth_m, K), view)
    assert not blank.success and "no keypoints in the real image" in blank.reason
    assert "no keypoints in the rendered view" in align_views(frame, _blank_view(K)).reason
    nan_depth = RGBDFrame(frame.rgb, np.full(K.shape, np.nan, np.float32), K)
    res = align_views(nan_depth, view)
    assert not res.success and "no valid depth" in res.reason
    # A view the field is not sure of anywhere: features are only detected where it is opaque.
    dark = RenderedView(view.rgb, view.depth_m, np.full(K.shape, 0.1, np.float32), K)
    assert "no keypoints in the rendered view" in align_views(frame, dark).reason
    # Matches whose rendered pixels the field is not sure of: low opacity, said so.
    from nap3d_graph.nap3d.correspondences import build_correspondences
    from nap3d_graph.nap3d.matching import Matches

    uv = np.array([[40.0, 30.0], [100.0, 80.0], [200.0, 150.0]])
    corr = build_correspondences(frame, dark, Matches(uv, uv, np.full(3, 0.5)), AlignConfig())
    assert len(corr) == 0 and corr.reason == "low opacity at the matches"
    strict = align_views(frame, view, AlignConfig(min_matches=100000))
    assert not strict.success and "too few matches" in strict.reason
    assert np.all(np.isinf(strict.covariance)) and np.array_equal(strict.T_real_rendered, np.eye(4))
    # correct_pose with a field that fails or covers nothing never raises.

    class BrokenField:
        def render(self, T, K):
            raise RuntimeError("GPU fell off")

    c = correct_pose(frame, BrokenField(), T_world_cam_est)
    assert not c.success and "render failed" in c.reason
    np.testing.assert_array_equal(c.T_world_cam_corrected, T_world_cam_est)

    class EmptyField:
        def render(self, T, K):
            return RenderedView(np.zeros((K.height, K.width, 3), np.uint8), np.zeros(K.shape, np.float32),
                                np.zeros(K.shape, np.float32), K)

    assert "low opacity" in correct_pose(frame, EmptyField(), T_world_cam_est).reason
    with pytest.raises(ValueError, match="method"):
        AlignConfig(method="magic")


def test_real_tum_frames_align_to_mocap(tum_path):
    """Frames i and i+k of fr1/xyz, one playing the rendered view (opacity 1 where depth is
    valid), recover the motion-capture relative pose."""
    from nap3d_graph.datasets import TumSequence

    seq = TumSequence(tum_path)
    errors = []
    for i in (0, 1, 2, 3):
        k = 8
        a_frame, b_frame = seq[i + k], seq[i]
        view = RenderedView(b_frame.rgb, b_frame.depth_m, (b_frame.depth_m > 0).astype(np.float32), b_frame.intrinsics)
        a = align_views(a_frame, view)
        assert a.success, a.reason
        T_true = inv_T(seq.T_world_cam_gt[i + k]) @ seq.T_world_cam_gt[i]  # T_real_rendered
        errors.append(pose_error(a.T_real_rendered, T_true))
    med = np.median(np.array(errors), axis=0)
    assert med[0] < 0.012 and med[1] < 0.8, med


def test_self_calibration_recovers_pose_under_wrong_intrinsics(room, scenarios):
    """With the camera's intrinsics off by the paper's HARSH shift (x1.10 focal, +10 px), the
    refinement that also estimates them recovers the pose and the true intrinsics."""
    from nap3d_graph.nap3d.align import align_correspondences, prepare_correspondences
    from nap3d_graph.nap3d.refine import refine_pose

    _, field = room
    errors, plain_errors = [], []  # a failed fit scores the uncorrected error, as in Evaluation K
    for frame, T_world_cam_gt, T_world_cam_est in scenarios[:5]:
        K_true = frame.intrinsics
        given = frame.with_intrinsics(K_true.shifted(1.10, 10.0))
        view = field.render(T_world_cam_est, K_true)
        corr, _ = prepare_correspondences(given, view)
        a = align_correspondences(corr, given.intrinsics, AlignConfig(estimate_intrinsics=True))
        b = align_correspondences(corr, given.intrinsics, AlignConfig(estimate_intrinsics=False))
        auto = align_correspondences(corr, given.intrinsics, AlignConfig())  # the default: "auto"
        assert auto.diagnostics["intrinsics_model"] == "calibrated" and "intrinsics" in auto.diagnostics
        assert a.success
        errors.append(pose_error(a.corrected_pose(T_world_cam_est), T_world_cam_gt)[0])
        plain_errors.append(pose_error(b.corrected_pose(T_world_cam_est) if b.success else T_world_cam_est, T_world_cam_gt)[0])
        # The focal length comes back (the principal point trades off against rotation and
        # is held by its prior: it is the pose that matters).
        sub = corr.__class__(corr.x[a.inlier_mask], corr.y[a.inlier_mask], corr.uv_real[a.inlier_mask],
                             corr.opacity[a.inlier_mask], corr.num_matches, "", corr.depth_grad[a.inlier_mask])
        *_, K_est, _ = refine_pose(a.T_real_rendered[:3, :3], a.T_real_rendered[:3, 3], sub, given.intrinsics,
                                   AlignConfig(estimate_intrinsics=True), return_intrinsics=True)
        assert abs(K_est.fx - K_true.fx) < 0.25 * abs(given.intrinsics.fx - K_true.fx)
    print("self-calibrated translation errors (m):", np.round(errors, 4), "without:", np.round(plain_errors, 4))
    assert np.median(errors) < 0.005
    assert np.median(plain_errors) > 5 * np.median(errors)
