"""The torch grid field: rendering contract, short training on a small simulated room,
checkpoints, and the train-field command. Sized to finish in well under three minutes on a
2-core CPU: one 100-frame 128x96 survey, 5 cm voxels, 300 training steps (a step budget, so
the field and the figures do not depend on how busy the machine is)."""

import argparse
import json

import numpy as np
import pytest
import torch

from nap3d_graph import load_field
from nap3d_graph.camera import Intrinsics
from nap3d_graph.fields import FieldError, RadianceField
from nap3d_graph.fields.evaluation import evaluate_field
from nap3d_graph.fields.grid import CHECKPOINT_VERSION, GridField
from nap3d_graph.fields.training_data import split_frames

TRAIN_STEPS = 300
QUICK_STEPS = 40


@pytest.fixture(scope="module")
def survey(field_survey):
    return field_survey


@pytest.fixture(scope="module")
def trained(survey):
    """The grid trained as train-field does: capture timing estimated from the survey."""
    from nap3d_graph.fields.build import build_field

    return build_field(survey, "grid", steps=TRAIN_STEPS, voxel_size_m=0.05, eval_frames=4, seed=1, progress=False)


@pytest.fixture(scope="module")
def quick(survey):
    """A grid trained briefly, without the capture timing or the error measurements: what the
    renderer and checkpoint tests need (a field with surfaces), in a fifth of the time."""
    from nap3d_graph.fields.build import build_field

    return build_field(survey, "grid", steps=QUICK_STEPS, voxel_size_m=0.05, eval_frames=4, seed=1, progress=False,
                       timing=None, measure_error=False, error_growth=False)


def test_split_frames():
    train, held = split_frames(40, every=1, eval_frames=3)
    assert set(train).isdisjoint(held) and len(held) == 3 and len(train) == 36
    train, held = split_frames(40, every=2, eval_frames=100)
    assert list(train) == list(range(0, 40, 2)) and list(held) == list(range(1, 40, 2))
    with pytest.raises(FieldError):
        split_frames(40, every=0)


def test_untrained_field_renders_the_contract():
    field = GridField.empty([[0.0, 0.0, 0.0], [2.0, 3.0, 1.5]], voxel_size=0.1)
    assert isinstance(field, RadianceField)
    np.testing.assert_allclose(field.bounds, [[0, 0, 0], [2.0, 3.0, 1.5]], atol=1e-9)
    K = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.5, 0.7]
    view = field.render(T, K)
    assert view.rgb.shape == (48, 64, 3) and view.rgb.dtype == np.uint8
    assert view.depth_m.shape == (48, 64) and view.depth_m.dtype == np.float32
    assert view.opacity.shape == (48, 64) and view.opacity.dtype == np.float32
    assert np.all(np.isfinite(view.depth_m)) and view.depth_m.min() >= 0.0
    assert 0.0 <= view.opacity.min() and view.opacity.max() <= 1.0
    # A new field is near-transparent: nothing to see, no depth claimed.
    assert view.opacity.max() < 0.05
    assert np.all(view.depth_m[view.opacity < 1e-3] == 0.0)


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_holes_are_not_marched_and_lose_no_surface(backend):
    """A block in empty space: pixels between lattice corners that all saw nothing take their
    corners' opacity instead of marching (empty_cell_opacity), on both backends, and the render
    still matches the brute-force reference on the block and on the empty background."""
    import dataclasses

    field = GridField.empty([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]], voxel_size=0.05, device="cpu")
    block = field.density[0, 0]
    block[20:29, 16:25, 16:25] = 30.0  # world z 1.0-1.4 m, x and y 0.8-1.2 m: a 40 cm cube
    field.mark_changed()
    K = Intrinsics(100.0, 100.0, 63.5, 47.5, 128, 96)
    T = np.eye(4)
    T[:3, 3] = [1.03, 0.97, 0.0]  # looking down world +z at the cube's face, 1 m away
    views = {}
    for skip in (True, False):
        field.render_config = dataclasses.replace(field.render_config, backend=backend,
                                                  empty_cell_opacity=0.02 if skip else 0.0)
        views[skip] = field.render(T, K)
    ref = field.render_reference(T, K, step_vox=0.1)
    on, off = views[True].extras["render_stats"], views[False].extras["render_stats"]
    assert on["empty"] > 2000 and off["empty"] == 0 and on["fallback"] < off["fallback"] - 2000, (on, off)
    solid, clear = ref.opacity > 0.9, ref.opacity < 0.01
    assert 0.1 < solid.mean() < 0.5 and clear.mean() > 0.4
    for view in views.values():
        assert (view.opacity[solid] > 0.9).all() and (view.opacity[clear] < 0.01).all()
        assert np.median(np.abs(view.depth_m - ref.depth_m)[solid]) < 0.002
    np.testing.assert_allclose(views[True].depth_m[solid], views[False].depth_m[solid], atol=1e-5)


def test_render_rejects_a_bad_pose():
    field = GridField.empty([[0, 0, 0], [1, 1, 1]], voxel_size=0.1)
    with pytest.raises(FieldError, match="4x4"):
        field.render(np.full((4, 4), np.nan), Intrinsics(10, 10, 4.5, 4.5, 10, 10))


@pytest.mark.slow
def test_short_training_beats_the_bars(survey, trained):
    field, report = trained
    held = report["held_out"]
    assert report["steps"] == TRAIN_STEPS
    assert held["depth_reference"].startswith("noise-free")
    # Measured after 300 steps on the Kinect-like survey (blur, exposure drift, depth captured
    # 30 ms before colour): 22.4 dB raw, 24.2 after an affine colour fit, 0.31 cm median,
    # 1.6 cm p90, opaque 99.5%, unit check a = 1.001, R^2 0.984 (the same on any machine: the
    # budget is in steps).
    assert held["psnr_affine_db"] >= 22.0 and held["psnr_db"] >= 20.0, held
    assert held["depth_abs_err_m"]["median"] <= 0.008, held
    assert held["depth_abs_err_m"]["p90"] <= 0.035, held
    assert held["opacity_on_surfaces"] >= 0.95 and held["opaque_fraction"] >= 0.95, held
    unit = held["unit_check"]
    assert unit["r2"] >= 0.97 and abs(unit["a"] - 1.0) < 0.05 and abs(unit["b"]) < 0.1, unit
    # ... and far above an untrained field on the same frames.
    blank = GridField.empty(field.bounds, voxel_size=0.1)
    oracle = survey.oracle_field()
    untrained = evaluate_field(blank, survey, held["frames"], oracle)
    assert untrained["psnr_db"] < 12.0 and untrained["depth_abs_err_m"]["median"] is None
    assert untrained["opacity_on_surfaces"] < 0.05 and untrained["opaque_fraction"] == 0.0


@pytest.mark.slow
def test_capture_timing_is_recovered_and_fixes_the_field(survey, trained):
    """The survey's depth is captured 30 ms before its colour and stamped 15 ms after its
    capture: the estimate finds the depth 12-18 ms before its stamp and the colour at its
    own with a global shutter (no readout: the simulator renders every row at once), and a field
    trained without the compensation has several times the depth error."""
    from nap3d_graph.fields.build import build_field

    _, report = trained
    truth = survey.config
    lag = np.asarray(survey.depth_timestamps) - np.asarray(truth["depth_capture_stamps"])
    timing = report["timing"]
    assert abs(timing["depth_offset_s"] + np.median(lag)) <= 0.003, (timing, np.median(lag))
    assert abs(timing["colour_offset_s"]) <= 0.003 and abs(timing["depth_scale"] - 1.0) <= 0.01
    assert timing["readout_s"] == 0.0 and timing["colour_error_px"] == timing["global_shutter_error_px"], timing
    _, ignored = build_field(survey, "grid", steps=TRAIN_STEPS, voxel_size_m=0.05, eval_frames=4, seed=1,
                             timing=None, progress=False)
    with_timing = report["held_out"]["depth_abs_err_m"]["median"]
    assert ignored["held_out"]["depth_abs_err_m"]["median"] > 2.5 * with_timing, (ignored["held_out"], with_timing)


@pytest.mark.slow
def test_fast_renderer_agrees_with_reference(survey, trained):
    """On the fully trained grid: a fuzzy, briefly trained one is semi-transparent where the
    two renderers' opacity cut-offs differ."""
    field, report = trained
    i = report["held_out"]["frames"][0]
    K = survey.intrinsics
    fast = field.render(survey.T_world_cam_gt[i], K)
    ref = field.render_reference(survey.T_world_cam_gt[i], K, step_vox=0.1)
    both = (fast.opacity > 0.9) & (ref.opacity > 0.9)
    # (The two disagree near opacity 0.9 itself, where a semi-transparent edge crosses it.)
    assert both.sum() > 0.9 * (ref.opacity > 0.9).sum()
    assert np.median(np.abs(fast.depth_m - ref.depth_m)[both]) < 0.002
    mse = np.mean(((fast.rgb.astype(float) - ref.rgb.astype(float)) / 255.0) ** 2)
    assert -10 * np.log10(mse) > 30.0


def test_compiled_and_torch_renderers_agree(survey, quick):
    """The compiled CPU kernels (the default on a CPU) and the torch path (the GPU's) run one
    algorithm: same depths, opacities and colours to float precision on every held-out view
    (a level of a colour value where rounding falls either way; a pixel whose hierarchy
    decision flips on a float's last bit may differ more)."""
    import dataclasses

    from nap3d_graph.fields.grid_render import RenderConfig

    field, report = quick
    torch_field = GridField(field.density[0, 0], field.color[0], field.grid_min, field.voxel_size,
                            render_config=dataclasses.replace(field.render_config, backend="torch"),
                            color_voxel_size=field.color_voxel_size)
    K = survey.intrinsics
    for i in report["held_out"]["frames"]:
        fast = field.render(survey.T_world_cam_gt[i], K)
        slow = torch_field.render(survey.T_world_cam_gt[i], K)
        assert fast.extras["render_stats"]["backend"] == "compiled"
        assert slow.extras["render_stats"]["backend"] == "torch"
        both = (fast.opacity > 0.5) & (slow.opacity > 0.5)
        assert both.sum() >= 0.99 * (slow.opacity > 0.5).sum() > 0
        dz = np.abs(fast.depth_m - slow.depth_m)[both]
        assert np.percentile(dz, 99) < 1e-4 and dz.max() < 0.01, (np.percentile(dz, 99), dz.max())
        assert np.percentile(np.abs(fast.opacity - slow.opacity), 99.9) < 1e-4
        rgb_diff = np.abs(fast.rgb.astype(int) - slow.rgb.astype(int))
        assert (rgb_diff > 1).mean() < 0.002 and (rgb_diff > 0).mean() < 0.01, ((rgb_diff > 1).mean(), (rgb_diff > 0).mean())
    with pytest.raises(FieldError, match="backend"):
        RenderConfig(backend="cuda")
    # A run's keyframe thread renders while its odometry goes on: the kernels drop the GIL.
    from nap3d_graph.fields import grid_kernels

    assert grid_kernels.render_depth.targetoptions["nogil"] and grid_kernels.shade.targetoptions["nogil"]


def test_without_numba_the_torch_renderer_takes_over(quick, survey, monkeypatch, caplog):
    """numba is in the "full" extra; a core install without it still renders (torch), and says
    once how to get the compiled renderer."""
    import sys

    from nap3d_graph.fields import grid_render

    field, report = quick
    i = report["held_out"]["frames"][0]
    compiled = field.render(survey.T_world_cam_gt[i], survey.intrinsics)
    import nap3d_graph.fields

    monkeypatch.setitem(sys.modules, "nap3d_graph.fields.grid_kernels", None)  # import fails
    monkeypatch.delattr(nap3d_graph.fields, "grid_kernels", raising=False)
    grid_render._compiled_kernels.cache_clear()
    try:
        with caplog.at_level("WARNING", logger="nap3d_graph.fields.grid_render"):
            fallback = field.render(survey.T_world_cam_gt[i], survey.intrinsics)
            field.render(survey.T_world_cam_gt[i], survey.intrinsics)
    finally:
        grid_render._compiled_kernels.cache_clear()
    assert fallback.extras["render_stats"]["backend"] == "torch"
    assert sum("pip install numba" in r.getMessage() for r in caplog.records) == 1
    both = (compiled.opacity > 0.5) & (fallback.opacity > 0.5)
    assert np.percentile(np.abs(compiled.depth_m - fallback.depth_m)[both], 99) < 1e-4


def test_checkpoint_round_trip_is_bit_identical(survey, quick, tmp_path):
    field, _ = quick
    path = field.save(tmp_path / "field.pt")
    loaded = load_field(path)
    assert isinstance(loaded, GridField)
    assert loaded.voxel_size == field.voxel_size and loaded.meta["steps"] == field.meta["steps"]
    T, K = survey.T_world_cam_gt[3], survey.intrinsics
    a, b = field.render(T, K), loaded.render(T, K)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    np.testing.assert_array_equal(a.opacity, b.opacity)
    # Plain tensors and values only: loads with weights_only=True.
    state = torch.load(path, weights_only=True)
    assert state["version"] == CHECKPOINT_VERSION and state["voxel_size_m"] == field.voxel_size


def test_a_loaded_grid_holds_one_copy_of_its_colour_while_rendering(survey, quick, tmp_path):
    """The compiled renderer reads the colour channel-last: a loaded grid moves its colour to that
    layout once (no second copy beside the checkpoint's), renders as before, saves the same."""
    field, _ = quick
    path = field.save(tmp_path / "field.pt")
    loaded = load_field(path)
    T, K = survey.T_world_cam_gt[3], survey.intrinsics
    before = field.render(T, K)
    view = loaded.render(T, K)
    colour_grid = loaded._numpy_grids()[2]
    assert np.shares_memory(colour_grid, loaded.color.numpy())  # the renderer's colour is the field's own
    np.testing.assert_array_equal(view.rgb, before.rgb)
    np.testing.assert_array_equal(view.depth_m, before.depth_m)
    again = load_field(loaded.save(tmp_path / "again.pt"))
    assert torch.equal(again.color, field.color) and torch.equal(again.density, field.density)


def test_corrupt_and_foreign_checkpoints_fail_clearly(quick, tmp_path):
    field, _ = quick
    good = field.save(tmp_path / "good.pt")

    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a checkpoint at all")
    with pytest.raises(FieldError, match="not a readable field checkpoint"):
        GridField.load(garbage)

    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:5000])
    with pytest.raises(FieldError, match="not a readable field checkpoint"):
        load_field(truncated)

    state = torch.load(good, weights_only=True)
    state["version"] = CHECKPOINT_VERSION + 98
    old = tmp_path / "future.pt"
    torch.save(state, old)
    with pytest.raises(FieldError, match=rf"version {CHECKPOINT_VERSION + 98}.*retrain"):
        load_field(old)

    # One NaN in the colour (checked a chunk at a time, the last chunk here) refuses the file.
    state = torch.load(good, weights_only=True)
    state["color_raw"][-1, -1, -1, -1] = float("nan")
    torch.save(state, tmp_path / "nan.pt")
    with pytest.raises(FieldError, match="non-finite weights"):
        load_field(tmp_path / "nan.pt")

    pickled = tmp_path / "pickled.pt"
    torch.save({"format": "nap3d-graph grid field", "config": argparse.Namespace(a=1)}, pickled)
    with pytest.raises(FieldError, match="pickled objects"):
        load_field(pickled)

    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(FieldError, match="not a nap3d-graph field checkpoint"):
        load_field(foreign)

    with pytest.raises(FieldError, match="no such"):
        GridField.load(tmp_path / "missing.pt")


@pytest.mark.slow
def test_train_field_command_writes_checkpoint_and_report(survey, tmp_path, capsys):
    from nap3d_graph.cli import main

    out = tmp_path / "run" / "field.pt"
    assert main(["train-field", str(survey.path), "--out", str(out), "--model", "grid", "--steps", "60",
                 "--voxel-size", "0.08", "--every", "2", "--eval-frames", "2", "--quiet"]) == 0
    assert out.is_file()
    report = json.loads((out.parent / "field.report.json").read_text())
    held = report["held_out"]
    for key in ("psnr_db", "psnr_affine_db", "depth_abs_err_m", "opaque_fraction", "unit_check"):
        assert key in held
    assert {"median", "p90"} <= set(held["depth_abs_err_m"]) and {"a", "b", "r2"} <= set(held["unit_check"])
    assert report["steps"] == 60 and report["train_frames"] == 50
    assert "held-out (128x96): PSNR" in capsys.readouterr().out
    assert isinstance(load_field(out), GridField)


@pytest.mark.slow
def test_train_field_builds_a_splat_field(survey, tmp_path, capsys):
    """The other model: splats fused from the survey, which render the held-out views of the
    simulated room within a stated error of the exact renderer."""
    from nap3d_graph.cli import main
    from nap3d_graph.fields.splat import SplatField

    out = tmp_path / "splat.pt"
    assert main(["train-field", str(survey.path), "--out", str(out), "--model", "splat", "--eval-frames", "4",
                 "--quiet"]) == 0
    field = load_field(out)
    assert isinstance(field, SplatField) and field.meta["model"] == "splat"
    report = json.loads((tmp_path / "splat.report.json").read_text())
    held = report["held_out"]
    assert held["depth_reference"].startswith("noise-free")
    # Measured: depth 0.61 cm median against the exact room, opaque 91%, 18.2 dB after an affine
    # colour fit (a 128x96 survey with motion blur: the splats average its blurred colours).
    assert held["depth_abs_err_m"]["median"] <= 0.01, held["depth_abs_err_m"]
    assert held["opaque_fraction"] >= 0.85 and held["psnr_affine_db"] >= 16.0, held
    assert len(field.meta["train_timestamps"]) == report["train_frames"]


@pytest.mark.parametrize(("extra", "message"), [
    (["--minutes", "0"], "--minutes: must be a finite number > 0, got 0"),
    (["--model", "nerf"], "--model: invalid choice: 'nerf'"),
    (["--steps", "0"], "--steps: must be an integer >= 1, got 0"),
    (["--out", "f.txt"], "must name a .pt checkpoint"),
    (["--out", "under_a_file/f.pt"], "under_a_file is a file, not a folder"),
    (["--out", "a_folder.pt"], "is a folder; name the file to write"),
])
def test_train_field_rejects_bad_arguments_at_once(survey, tmp_path, capsys, monkeypatch, extra, message):
    """One line, exit code 2, and before any training (the checks come first)."""
    from nap3d_graph.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "under_a_file").write_text("a file where a folder should be")
    (tmp_path / "a_folder.pt").mkdir()
    args = ["train-field", str(survey.path), "--out", "f.pt", *extra]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err


def test_train_field_on_missing_data_is_one_line(tmp_path, capsys):
    from nap3d_graph.cli import main

    assert main(["train-field", str(tmp_path / "nowhere"), "--out", str(tmp_path / "f.pt")]) == 2
    err = capsys.readouterr().err.strip()
    assert "nowhere" in err and len(err.splitlines()) == 1


def test_export_nerfstudio_command(survey, tmp_path, capsys):
    from nap3d_graph.cli import main

    assert main(["export-nerfstudio", str(survey.path), str(tmp_path / "ns"), "--every", "8"]) == 0
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    assert len(meta["frames"]) == 13 and "ns-train" in capsys.readouterr().out
    # A second export into the same (now non-empty) folder is refused without --force.
    assert main(["export-nerfstudio", str(survey.path), str(tmp_path / "ns")]) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(["export-nerfstudio", str(survey.path), str(tmp_path / "ns"), "--every", "8", "--force"]) == 0


def test_train_field_summary_when_too_few_held_out_frames_aligned():
    """Some held-out frames aligned, too few to measure the field's error: said, not a crash."""
    from nap3d_graph.cli.train_field import summary

    report = {"field_error": {"frames": 2, "failed": 6, "sigma_m": 0.0, "sigma_rad": 0.0}}
    text = summary("field", report, "f.pt", "f.report.json")
    assert "field error: not measured (2 held-out frames aligned, too few; 6 failed)" in text
    measured = {"frames": 8, "failed": 0, "matcher": "sift", "sigma_m": 0.007, "sigma_rad": 0.009,
                "nees_median_before": 30.0, "nees_median_after": 6.0}
    assert "7.0 mm, 0.52 deg" in summary("field", {"field_error": measured}, "f.pt", "f.report.json")
