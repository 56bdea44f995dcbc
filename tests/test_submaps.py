"""Submaps: a long survey cut by space into parts, each its own field, trained side by side
with the same result as one after another; the map's field renders from the part the camera
looks into, in one frame (no jump at the hand-over)."""

import json

import numpy as np
import pytest

from nap3d_graph.camera import RenderedView
from nap3d_graph.conventions import exp_se3
from nap3d_graph.fields.submaps import Submap, SubmapField, SubmapSettings
from nap3d_graph.mapping.submaps import plan_submaps


def _walk_along_x(n: int, length_m: float) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.linspace(0.0, length_m, n)
    T[:, 2, 3] = 0.1 * np.sin(np.linspace(0, 6, n))
    return T


def test_a_long_survey_is_cut_into_slabs_of_about_max_frames_with_overlap():
    T = _walk_along_x(700, 21.0)
    T[5] = np.nan  # an unposed frame belongs to no submap
    plan = plan_submaps(T, SubmapSettings(max_frames=300, overlap_m=0.75))
    assert len(plan) == 3 and all(abs(abs(s.axis[0]) - 1.0) < 1e-3 for s in plan)
    sign = np.sign(plan[0].axis[0])
    cores = [sorted(sign * s.core) for s in plan]
    assert all(233 <= np.sum((sign * T[s.frames, 0, 3] >= c[0]) & (sign * T[s.frames, 0, 3] < c[1])) <= 234
               for s, c in zip(plan, cores))
    # Neighbours share the frames within 0.75 m of their cut (0.03 m a frame: about 25 each side).
    shared = set(plan[0].frames) & set(plan[1].frames)
    assert 40 <= len(shared) <= 60 and 5 not in set().union(*(set(s.frames) for s in plan))
    # A survey of one submap's size is one submap of every posed frame, unbounded: as before submaps.
    one = plan_submaps(_walk_along_x(270, 5.0))
    assert len(one) == 1 and len(one[0].frames) == 270 and np.all(np.isinf(one[0].core))


class _Flat:
    """A field that renders one grey level everywhere (which submap answered)."""

    def __init__(self, level: int, x0: float, x1: float):
        self.level, self.bounds, self.meta = level, np.array([[x0, -1, -1], [x1, 1, 1.0]]), {
            "train_frames": [level], "field_error": {"sigma_m": 0.001 * (level + 1)}}

    def render(self, T_world_cam, intrinsics):
        h, w = intrinsics.height, intrinsics.width
        return RenderedView(np.full((h, w, 3), self.level, np.uint8), np.ones((h, w), np.float32),
                            np.ones((h, w), np.float32), intrinsics)


def test_the_map_field_renders_from_the_submap_the_camera_looks_into():
    from nap3d_graph.sims.sequence import default_intrinsics

    axis = np.array([1.0, 0.0, 0.0])
    submaps = [Submap(0, axis, np.array([-np.inf, 5.0]), np.arange(3)),
               Submap(1, axis, np.array([5.0, np.inf]), np.arange(3, 6))]
    field = SubmapField([_Flat(0, -1, 6), _Flat(1, 4, 11)], submaps, SubmapSettings(look_ahead_m=1.0))
    K = default_intrinsics(8, 6)
    # Camera looking along +x (OpenCV z forward = world +x).
    look_x = np.eye(4)
    look_x[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0.0]])
    levels = []
    for x in (3.0, 3.9, 4.1, 6.0):
        T = look_x.copy()
        T[0, 3] = x
        levels.append(int(field.render(T, K).rgb[0, 0, 0]))
    assert levels == [0, 0, 1, 1]  # hands over once the point 1 m ahead crosses the cut
    back = look_x @ exp_se3(np.array([0, np.pi, 0, 0, 0, 0.0]))  # turned round at 5.5 m: looks into submap 0
    back[0, 3] = 5.5
    assert int(field.render(back, K).rgb[0, 0, 0]) == 0
    np.testing.assert_allclose(field.bounds, [[-1, -1, -1], [11, 1, 1]])
    assert field.meta["field_error"]["sigma_m"] == 0.002 and field.meta["train_frames"] == [0, 1]
    with pytest.raises(ValueError, match="one field per submap"):
        SubmapField([_Flat(0, 0, 1)], submaps)


def test_submap_fields_trained_side_by_side_equal_those_trained_one_after_another(sim_walk, tmp_path):
    """Two submaps of a simulated survey (posed by the simulator: the field stage alone), grid
    fields of 40 steps, on two worker processes and in this process: the same checkpoints."""
    import dataclasses

    import torch

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.build import MapSettings
    from nap3d_graph.mapping.folder import MapFolder
    from nap3d_graph.mapping.submap_fields import train_submap_fields
    from nap3d_graph.pools import LocalPool, SerialPool

    survey = open_sequence(sim_walk(48, fps=2.0, path="mapping"))
    T = np.asarray(survey.T_world_cam_gt)
    settings = dataclasses.replace(MapSettings(matcher="sift", steps=40), submaps=SubmapSettings(max_frames=26))
    plan = plan_submaps(T, settings.submaps)
    assert len(plan) == 2
    fields = {}
    for name, pool in (("serial", SerialPool()), ("two_workers", LocalPool(2))):
        folder = MapFolder.open(tmp_path / name, {"data": "survey"}, ("data",))
        (folder.root / "map.json").write_text('{"data": "survey", "stages": {}}')
        folder = MapFolder.read(folder.root)
        try:
            merged = train_submap_fields(survey, T, folder, plan, settings, settings.submaps, {"steps": 40}, None, pool,
                                         "cpu")
        finally:
            pool.close()
        assert len(merged["submaps"]) == 2 and merged["held_out"]["frames"]
        assert (folder.root / "submaps.json").is_file()
        fields[name] = resolve_field(str(folder.root))
    serial, parallel = fields["serial"], fields["two_workers"]
    assert isinstance(serial, SubmapField) and len(serial.fields) == 2
    for a, b in zip(serial.fields, parallel.fields):
        for key, value in a.state_dict().items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, b.state_dict()[key]), key
    # Each submap's grid covers its own part of the room, not the whole survey's bounds.
    spans = [np.ptp(f.bounds, axis=0) for f in serial.fields]
    assert all(np.prod(s) < np.prod(np.ptp(serial.bounds, axis=0)) for s in spans)


@pytest.mark.slow
def test_map_cut_into_submaps_through_the_command_line_then_run_in_it(sim_walk, tmp_path, capsys):
    """`map --submap-frames` on a simulated room's survey: two submaps trained on two workers,
    their index, the mesh and the rerun recording; `run --field MAP` renders from them."""
    from nap3d_graph.cli import main
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.run.viz import keyframe_entries

    survey = sim_walk(120, fps=3.75, path="mapping", width=240, height=180)
    walk = sim_walk(40, fps=6.0, seed=6, width=240, height=180)
    out = tmp_path / "map"
    assert main(["map", str(survey), "--out", str(out), "--matcher", "sift", "--steps", "40", "--submap-frames", "70",
                 "--workers", "2", "--viz", str(tmp_path / "map.rrd"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "cut into 2 submaps" in printed and "field: 2 submaps" in printed and "mesh:" in printed
    field = resolve_field(str(out))
    assert isinstance(field, SubmapField) and len(field.fields) == 2 and not (out / "field.pt").exists()
    entries = keyframe_entries(tmp_path / "map.rrd")
    assert {"/world/mesh", "/world/keyframes/submap_00", "/world/keyframes/submap_01", "/map/report"} <= set(entries)
    assert main(["run", "--data", str(walk), "--field", str(out), "--matcher", "sift", "--odom", "vo",
                 "--out", str(tmp_path / "run")]) == 0
    metrics = json.loads((tmp_path / "run" / "latest" / "metrics.json").read_text())
    placement = metrics["map"]["placement"]
    assert placement["placed"] and placement["placed_at_frame"] is not None, placement
    # Scored through the survey's alignment: the corrections from the submaps' fields hold the run.
    assert metrics["corrections_accepted"] >= 3 and metrics["estimate"]["ate_m"]["rmse"] < 0.05, metrics["estimate"]


def test_loop_candidates_verified_on_two_workers_equal_those_verified_in_one_process(sim_walk):
    """Loop verification as jobs on a pool (what `map --workers/--ray-address` does with a long
    survey's candidates): the same loops, in the same order, as in one process."""
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.mapping.build import MapSettings, align_config, read_keyframes
    from nap3d_graph.mapping.loops import LoopSettings, verify, verify_on_pool
    from nap3d_graph.pools import LocalPool

    sequence = open_sequence(sim_walk(30, fps=15.0, seed=0, width=320, height=240, path="mapping", scene_seed=3))
    settings = MapSettings(matcher="sift")
    keyframes = read_keyframes(sequence, np.arange(0, 30, 3), settings, progress=False)
    pairs = [(a, b, "test") for a in range(len(keyframes)) for b in range(a + 2, len(keyframes))]
    config = align_config(settings)
    serial = verify(keyframes, pairs, config, LoopSettings(), progress=False)
    pool = LocalPool(2)
    try:
        pooled = verify_on_pool(keyframes, pairs, config, LoopSettings(), pool, progress=False, min_pairs=0)
    finally:
        pool.close()

    def summary(loops):
        return [(lp.a, lp.b, lp.status, lp.inliers, lp.reason) for lp in loops]

    assert summary(pooled) == summary(serial) and sum(lp.status == "verified" for lp in serial) >= 5
    for p, s in zip(pooled, serial):
        np.testing.assert_allclose(p.T_a_b, s.T_a_b, atol=1e-9)
