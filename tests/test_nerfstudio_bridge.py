"""The nerfstudio bridge: export, pose/scale/depth conversions, the adapter, the missing-package
message. None of this needs nerfstudio; the one test that calls it runs only where it imports."""

import importlib.util
import json

import cv2
import numpy as np
import pytest
from conftest import OPTIONAL_EXTRA

from nap3d_graph import RGBDFrame, load_field
from nap3d_graph.camera import Intrinsics
from nap3d_graph.conventions import exp_so3, make_T
from nap3d_graph.fields import FieldError
from nap3d_graph.fields.nerfstudio import (
    DataparserTransform,
    NerfstudioField,
    depth_to_png_mm,
    intrinsics_from_nerfstudio,
    model_depth_to_z_m,
    model_to_world_pose,
    nerfstudio_intrinsics,
    png_mm_to_depth,
    read_dataparser_transforms,
    world_to_model_pose,
    z_m_to_model_depth,
)
from nap3d_graph.fields.nerfstudio_export import export_nerfstudio, read_transforms_poses

HAS_NERFSTUDIO = importlib.util.find_spec("nerfstudio") is not None
K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


class _TinySequence:
    """Four posed frames with known images and depth (no files)."""

    def __init__(self, intrinsics: Intrinsics):
        rng = np.random.default_rng(3)
        self.intrinsics = intrinsics
        self.T_world_cam_gt = np.stack([
            make_T(exp_so3(rng.normal(size=3) * 0.5), rng.normal(size=3)) for _ in range(4)
        ])
        self.timestamps = np.arange(4) * 0.1
        h, w = intrinsics.height, intrinsics.width
        self._frames = []
        for k in range(4):
            rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
            depth = rng.uniform(0.4, 4.0, size=(h, w)).astype(np.float32)
            depth[0, :5] = 0.0  # missing
            self._frames.append(RGBDFrame(rgb, depth, intrinsics, float(self.timestamps[k])))

    def __len__(self):
        return 4

    def __getitem__(self, i):
        return self._frames[i]


# --- export ---------------------------------------------------------------------------------------


def test_export_round_trips_poses_through_opengl(tmp_path):
    small = K.scaled(64, 48)
    seq = _TinySequence(small)
    path = export_nerfstudio(seq, tmp_path / "ns", every=2)
    meta = json.loads(path.read_text())
    assert [f["file_path"] for f in meta["frames"]] == ["images/frame_00000.png", "images/frame_00002.png"]
    assert meta["w"] == 64 and meta["h"] == 48
    assert meta["fl_x"] == pytest.approx(small.fx) and meta["fl_y"] == pytest.approx(small.fy)
    # nerfstudio's pixel centres sit at i + 0.5.
    assert meta["cx"] == pytest.approx(small.cx + 0.5) and meta["cy"] == pytest.approx(small.cy + 0.5)

    T_back, intrinsics_back, frames = read_transforms_poses(path)
    np.testing.assert_allclose(T_back, seq.T_world_cam_gt[[0, 2]], atol=1e-12)
    assert intrinsics_back == small
    for k, i in enumerate((0, 2)):
        T_cv = seq.T_world_cam_gt[i]
        T_gl = np.asarray(frames[k]["transform_matrix"])
        # Same centre; OpenGL looks down its -z, OpenCV down its +z; y flips (up vs down).
        np.testing.assert_allclose(T_gl[:3, 3], T_cv[:3, 3], atol=1e-12)
        np.testing.assert_allclose(-T_gl[:3, 2], T_cv[:3, 2], atol=1e-12)
        np.testing.assert_allclose(-T_gl[:3, 1], T_cv[:3, 1], atol=1e-12)
        np.testing.assert_allclose(T_gl[:3, 0], T_cv[:3, 0], atol=1e-12)
        # Images and 16-bit millimetre depth.
        rgb = cv2.cvtColor(cv2.imread(str(path.parent / frames[k]["file_path"])), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(rgb, seq[i].rgb)
        depth_png = cv2.imread(str(path.parent / frames[k]["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert depth_png.dtype == np.uint16
        np.testing.assert_array_equal(depth_png, np.round(seq[i].depth_m * 1000).astype(np.uint16))
        assert depth_png[0, 0] == 0


def test_export_refuses_bad_every_and_unposed(tmp_path):
    seq = _TinySequence(K.scaled(32, 24))
    with pytest.raises(FieldError, match="every"):
        export_nerfstudio(seq, tmp_path / "a", every=0)
    seq.T_world_cam_gt = None
    with pytest.raises(FieldError, match="poses"):
        export_nerfstudio(seq, tmp_path / "b")


def test_depth_png_millimetres():
    depth = np.array([[0.0, np.nan, 1.2344, 1.2346], [65.535, 70.0, -1.0, 0.0004]], dtype=np.float32)
    mm = depth_to_png_mm(depth)
    np.testing.assert_array_equal(mm, [[0, 0, 1234, 1235], [65535, 65535, 0, 0]])
    np.testing.assert_allclose(png_mm_to_depth(mm)[0, 2], 1.234, atol=1e-6)


def test_intrinsics_round_trip_and_half_pixel():
    meta = nerfstudio_intrinsics(K)
    assert (meta["cx"], meta["cy"]) == (320.0, 240.0)
    assert intrinsics_from_nerfstudio(meta) == K
    with pytest.raises(FieldError, match="undistorted"):
        nerfstudio_intrinsics(Intrinsics(500, 500, 320, 240, 640, 480, (0.1, 0, 0, 0, 0)))


# --- dataparser transform, scale and depth (hand-computed answers) ----------------------------------


@pytest.fixture
def dataparser_file(tmp_path):
    # 90 degrees about z, then a shift; scale one half. Written the way nerfstudio writes it.
    path = tmp_path / "dataparser_transforms.json"
    path.write_text(json.dumps({
        "transform": [[0.0, -1.0, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, -1.0]],
        "scale": 0.5,
    }))
    return path


def test_world_to_model_pose_matches_hand_computation(dataparser_file):
    dp = read_dataparser_transforms(dataparser_file)
    assert dp.scale == 0.5 and dp.transform.shape == (4, 4)
    # An OpenCV camera at world (1, 0, 0) with the identity orientation.
    T_world_cam = make_T(np.eye(3), [1.0, 0.0, 0.0])
    T_model = world_to_model_pose(T_world_cam, dp)
    # By hand: OpenGL flip diag(1, -1, -1); rotate by Rz(90): columns (0,1,0), (1,0,0), (0,0,-1);
    # centre Rz(90) (1,0,0) + (0.5, 0, -1) = (0.5, 1, -1), times 0.5 = (0.25, 0.5, -0.5).
    expected = np.array([
        [0.0, 1.0, 0.0, 0.25],
        [1.0, 0.0, 0.0, 0.5],
        [0.0, 0.0, -1.0, -0.5],
        [0.0, 0.0, 0.0, 1.0],
    ])
    np.testing.assert_allclose(T_model, expected, atol=1e-12)
    np.testing.assert_allclose(model_to_world_pose(T_model, dp), T_world_cam, atol=1e-12)


def test_model_depth_to_metric_z_by_hand():
    # Principal point: ray norm 1; a pixel 0.75 focal lengths right of it: norm 1.25.
    norms = np.array([[1.0, 1.25]])
    ray_model = np.array([[1.0, 1.25]])
    # scale 0.5 model units per metre: z = ray / norm / scale = 2 m for both.
    np.testing.assert_allclose(model_depth_to_z_m(ray_model, norms, 0.5), [[2.0, 2.0]])
    np.testing.assert_allclose(z_m_to_model_depth([[2.0, 2.0]], norms, 0.5), ray_model)
    # And with our intrinsics' own norms: the pixel at u = cx + 0.75 fx.
    intr = Intrinsics(100.0, 100.0, 10.0, 5.0, 100, 11)
    assert intr.ray_norms()[5, 85] == pytest.approx(1.25)


def test_dataparser_transform_validation(tmp_path):
    with pytest.raises(FieldError, match="rotation"):
        DataparserTransform(np.diag([2.0, 1.0, 1.0, 1.0]), 1.0)
    with pytest.raises(FieldError, match="scale"):
        DataparserTransform(np.eye(4), 0.0)
    with pytest.raises(FieldError, match="not found"):
        read_dataparser_transforms(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{\"transform\": 3}")
    with pytest.raises(FieldError, match="not a valid"):
        read_dataparser_transforms(bad)


# --- the adapter, with a stand-in model ---------------------------------------------------------------


class _WallModel:
    """Stands in for a nerfstudio model: a wall at z = 2 m in front of every camera, reported
    the way nerfstudio does (ray length along the unit ray, in scaled model units)."""

    def __init__(self, intrinsics, scale, drop=()):
        self.norms = intrinsics.ray_norms()
        self.scale = scale
        self.cameras = []
        self.drop = drop

    def get_outputs_for_camera(self, camera):
        import torch

        self.cameras.append(camera)
        h, w = self.norms.shape
        expected = torch.as_tensor(z_m_to_model_depth(np.full((h, w), 2.0), self.norms, self.scale), dtype=torch.float32)
        median = torch.as_tensor(z_m_to_model_depth(np.full((h, w), 2.1), self.norms, self.scale), dtype=torch.float32)
        outputs = {
            "rgb": torch.full((h, w, 3), 0.5),
            "expected_depth": expected[..., None],  # the wall at 2 m
            "depth": median[..., None],  # nerfacto's median: 10 cm off here, to tell them apart
            "accumulation": torch.ones((h, w, 1)),
        }
        return {k: v for k, v in outputs.items() if k not in self.drop}


def test_adapter_converts_pose_intrinsics_and_depth(dataparser_file):
    dp = read_dataparser_transforms(dataparser_file)
    small = K.scaled(40, 30)
    model = _WallModel(small, dp.scale)

    def factory(c2w, fx, fy, cx, cy, width, height):
        return {"c2w": c2w.numpy(), "fx": fx, "fy": fy, "cx": cx, "cy": cy, "w": width, "h": height}

    field = NerfstudioField(model, dp, cameras_factory=factory)
    T_world_cam = make_T(exp_so3([0.1, -0.2, 0.3]), [0.4, 1.0, -2.0])
    view = field.render(T_world_cam, small)
    np.testing.assert_allclose(view.depth_m, 2.0, atol=1e-5)
    assert view.opacity.min() == 1.0 and view.rgb.dtype == np.uint8 and view.rgb[0, 0, 0] == 128
    camera = model.cameras[0]
    np.testing.assert_allclose(camera["c2w"][0], world_to_model_pose(T_world_cam, dp)[:3, :4], atol=1e-6)
    assert camera["cx"] == pytest.approx(small.cx + 0.5) and camera["w"] == 40
    # The median depth on request; a missing output is an error, never a silent substitute.
    median = NerfstudioField(model, dp, cameras_factory=factory, depth_key="depth").render(T_world_cam, small)
    np.testing.assert_allclose(median.depth_m, 2.1, atol=1e-5)
    no_expected = NerfstudioField(_WallModel(small, dp.scale, drop=("expected_depth",)), dp, cameras_factory=factory)
    with pytest.raises(FieldError, match="no 'expected_depth'.*depth_key"):
        no_expected.render(T_world_cam, small)
    no_opacity = NerfstudioField(_WallModel(small, dp.scale, drop=("accumulation",)), dp, cameras_factory=factory)
    with pytest.raises(FieldError, match="no 'accumulation'"):
        no_opacity.render(T_world_cam, small)


def test_load_field_on_config_without_nerfstudio_says_how_to_install(tmp_path, monkeypatch):
    if HAS_NERFSTUDIO:  # hide it: this test is about the machine that lacks it
        import sys

        monkeypatch.setitem(sys.modules, "nerfstudio", None)
    config = tmp_path / "outputs" / "room" / "depth-nerfacto" / "2024" / "config.yml"
    config.parent.mkdir(parents=True)
    config.write_text("!!python/object:nerfstudio.engine.trainer.TrainerConfig {}\n")
    with pytest.raises(FieldError, match=r"pip install") as info:
        load_field(config)
    assert "nerfstudio" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.skipif(not HAS_NERFSTUDIO, reason=f"{OPTIONAL_EXTRA} nerfstudio (pip install 'nap3d-graph[nerfstudio]')")
def test_real_nerfstudio_cameras_agree_with_our_rays(dataparser_file):  # pragma: no cover - optional
    """Where nerfstudio imports: its ray through each pixel, mapped back to our world, is ours."""
    import torch

    from nap3d_graph.fields.nerfstudio import _nerfstudio_cameras

    dp = read_dataparser_transforms(dataparser_file)
    small = K.scaled(16, 12)
    T_world_cam = make_T(exp_so3([0.2, 0.1, -0.3]), [1.0, 2.0, 0.5])
    T_model = world_to_model_pose(T_world_cam, dp)
    ns = nerfstudio_intrinsics(small)
    camera = _nerfstudio_cameras(torch.as_tensor(T_model[:3, :4], dtype=torch.float32)[None], ns["fl_x"],
                                 ns["fl_y"], ns["cx"], ns["cy"], ns["w"], ns["h"])
    bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
    dirs_model = bundle.directions.reshape(-1, 3).numpy()
    R_world_model = np.linalg.inv(dp.transform)[:3, :3]
    dirs_world = dirs_model @ R_world_model.T
    v, u = np.mgrid[0:12, 0:16]
    ours = np.stack([(u - small.cx) / small.fx, (v - small.cy) / small.fy, np.ones_like(u, float)], -1).reshape(-1, 3)
    ours = ours @ T_world_cam[:3, :3].T
    ours /= np.linalg.norm(ours, axis=1, keepdims=True)
    np.testing.assert_allclose(dirs_world, ours, atol=1e-5)


def test_export_masks_the_undistortion_corners_of_real_frames(tmp_path):
    from conftest import TUM_FR1_XYZ

    from nap3d_graph.camera import colour_coverage
    from nap3d_graph.datasets import TumSequence

    seq = TumSequence(TUM_FR1_XYZ)
    path = export_nerfstudio(seq, tmp_path / "ns", every=6)
    frames = json.loads(path.read_text())["frames"]
    assert len(frames) == 2 and {f["mask_path"] for f in frames} == {"masks/coverage.png"}
    mask = cv2.imread(str(path.parent / "masks" / "coverage.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (480, 640) and set(np.unique(mask)) == {0, 255}
    np.testing.assert_array_equal(mask > 0, colour_coverage(seq))
    rgb = cv2.imread(str(path.parent / frames[0]["file_path"]))
    assert (rgb[mask == 0].sum(axis=1) == 0).mean() > 0.85 and (rgb[mask > 0].sum(axis=1) > 0).all()
    # A camera without distortion holds data everywhere: no masks.
    plain = export_nerfstudio(_TinySequence(K.scaled(32, 24)), tmp_path / "plain")
    assert not any("mask_path" in f for f in json.loads(plain.read_text())["frames"])
    assert not (plain.parent / "masks").exists()
