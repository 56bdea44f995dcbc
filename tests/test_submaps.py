"""Submaps: a long survey cut by space into parts, each its own field, trained side by side
with the same result as one after another; the map's field renders from the part the camera
looks into, in one frame (no jump at the hand-over)."""

import json

import numpy as np
import pytest

from nap3d_graph.camera import RenderedView
from nap3d_graph.conventions import exp_se3
from nap3d_graph.fields.submaps import FramedField, Submap, SubmapField, SubmapSettings
from nap3d_graph.mapping.submaps import level_frame, plan_submaps


def _walk_along_x(n: int, length_m: float) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.linspace(0.0, length_m, n)
    T[:, 2, 3] = 0.1 * np.sin(np.linspace(0, 6, n))
    return T


def test_a_long_survey_is_cut_into_slabs_of_about_max_frames_with_overlap():
    T = _walk_along_x(700, 21.0)
    T[5] = np.nan  # an unposed frame belongs to no submap
    plan = plan_submaps(T, SubmapSettings(max_frames=300, overlap_m=0.75, max_length_m=10.0))
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


def test_a_survey_that_crosses_rooms_quickly_is_cut_by_length_too():
    """Two rooms surveyed 300 frames each, 12 m apart, and the 100 frames of the walk between
    them: cut by count alone, the middle part runs 10 m (a grid twice a room's); with parts of
    at most 4 m, every core is within 4 m of floor, the cores tile the survey, and every part
    trains on the frames in its core and within its overlap."""
    room = np.linspace(0.0, 3.0, 300)
    x = np.concatenate([room, np.linspace(3.0, 12.0, 100), 12.0 + room])
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, 0, 3], T[:, 1, 3] = x, 0.2 * np.sin(np.arange(len(x)))
    by_count = plan_submaps(T, SubmapSettings(max_frames=300, max_length_m=100.0))
    plan = plan_submaps(T, SubmapSettings(max_frames=300, max_length_m=4.0))
    sign = np.sign(plan[0].axis[0])
    spans = [np.ptp(sign * x[s.frames]) for s in by_count]
    assert len(by_count) == 3 and max(spans) > 9.0
    assert len(plan) == 5
    edges = [sorted(sign * s.core) for s in plan]
    inner = [(max(lo, x.min()), min(hi, x.max())) for lo, hi in edges]
    assert all(hi - lo <= 4.0 + 1e-9 for lo, hi in inner)
    assert all(np.isclose(a[1], b[0]) for a, b in zip(edges, edges[1:]))
    for s, (lo, hi) in zip(plan, edges):
        along = sign * x
        want = np.flatnonzero((along >= lo - 0.75) & (along <= hi + 0.75))
        np.testing.assert_array_equal(np.sort(s.frames), want)
    # A stretch no camera stood in is no part of its own: 30 m of nothing between two rooms (its
    # parts join the next part a camera stood in; that part's grid still holds only what its
    # frames saw).
    T[300:400, 0, 3] = np.linspace(3.0, 33.0, 100)[[0] * 50 + [99] * 50]
    T[400:, 0, 3] = 33.0 + room
    gap = plan_submaps(T, SubmapSettings(max_frames=300, max_length_m=4.0))
    assert len(gap) == 4 and all(len(s.frames) >= 150 for s in gap)
    assert max(np.ptp(s.core) for s in gap[1:-1]) > 25.0


def test_a_submap_trains_in_a_level_frame_along_the_floor():
    """Cameras that pan and tilt (never roll) on a floor, seen in a first camera's tilted frame:
    the submap's grid frame is the floor's (down, along the cut)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    T_floor_cam = np.tile(np.eye(4), (60, 1, 1))
    T_floor_cam[:, :3, :3] = Rotation.from_euler("YX", np.c_[rng.uniform(-3, 3, 60), rng.uniform(-0.5, 0.1, 60)]
                                                 ).as_matrix()
    T_floor_cam[:, :3, 3] = np.c_[np.linspace(0, 9, 60), np.full(60, -1.4), rng.uniform(0, 4, 60)]
    T_map_floor = np.eye(4)
    T_map_floor[:3, :3] = Rotation.from_euler("xyz", [0.3, 0.2, 0.1]).as_matrix()
    T_map_cam = T_map_floor @ T_floor_cam
    axis = T_map_floor[:3, 0]  # the floor's x in the map's frame
    R_grid_map = level_frame(T_map_cam, axis)
    np.testing.assert_allclose(R_grid_map @ T_map_floor[:3, :3], np.eye(3), atol=1e-9)
    plan = plan_submaps(T_map_cam, SubmapSettings(max_frames=25))
    assert len(plan) == 3 and all(s.R_grid_map is not None for s in plan)
    for s in plan:  # each level (its down the floor's), along the survey's principal direction
        R_grid_floor = s.R_grid_map @ T_map_floor[:3, :3]
        np.testing.assert_allclose(R_grid_floor[1], [0, 1, 0], atol=1e-6)
        assert np.isclose(np.linalg.det(R_grid_floor), 1.0) and abs(R_grid_floor[0] @ (T_map_floor[:3, :3].T @ s.axis)) > 0.99
    assert plan_submaps(T_map_cam[:20])[0].R_grid_map is None  # one submap: the map's frame, as before


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


def test_what_a_submap_leaves_empty_is_rendered_from_the_one_further_along_the_view():
    """The camera in submap 0 looking along +x; its field holds only the left half of the view
    (the rest lies past its grid, through a door): the right half comes from submap 1, which
    holds the point 4 m along the empty pixels' mean ray."""
    from nap3d_graph.sims.sequence import default_intrinsics

    class _LeftHalf(_Flat):
        def render(self, T_world_cam, intrinsics):
            view = super().render(T_world_cam, intrinsics)
            view.opacity[:, intrinsics.width // 2:] = 0.0
            view.depth_m[:, intrinsics.width // 2:] = 0.0
            return view

    axis = np.array([1.0, 0.0, 0.0])
    submaps = [Submap(0, axis, np.array([-np.inf, 5.0]), np.arange(3)),
               Submap(1, axis, np.array([5.0, 9.0]), np.arange(3, 6)),
               Submap(2, axis, np.array([9.0, np.inf]), np.arange(6, 9))]
    field = SubmapField([_LeftHalf(10, -1, 6), _Flat(20, 4, 10), _Flat(30, 8, 14)], submaps,
                        SubmapSettings(look_ahead_m=1.0))
    K = default_intrinsics(8, 6)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0.0]])  # OpenCV z forward = world +x
    T[0, 3] = 2.5
    view = field.render(T, K)
    assert np.all(view.rgb[:, :4, 0] == 10) and np.all(view.rgb[:, 4:, 0] == 20) and np.all(view.opacity == 1.0)
    # A view its own submap fills leaves the others unread.
    T[0, 3] = 6.0
    assert np.all(field.render(T, K).rgb[..., 0] == 20) and set(field._loaded) == {0, 1}


def test_a_run_keeps_only_the_resident_submap_fields_loaded():
    """Three submaps read when rendered: at most two in memory, the least recently used let go
    (before the next is read, so a read never holds three) and read again when the camera comes back; a field in its own frame answers in the map's."""
    from nap3d_graph.sims.sequence import default_intrinsics

    axis = np.array([1.0, 0.0, 0.0])
    submaps = [Submap(k, axis, np.array([lo, hi]), np.arange(3)) for k, (lo, hi) in
               enumerate([(-np.inf, 5.0), (5.0, 10.0), (10.0, np.inf)])]
    reads = []

    held_at_read = []  # fields in memory while one more is read: a read's peak

    def loader(k):
        def load():
            reads.append(k)
            held_at_read.append(len(getattr(field, "_loaded", {})))
            return _Flat(k, 5 * k - 1, 5 * k + 6)
        return load

    field = None
    field = SubmapField.lazy([loader(k) for k in range(3)], submaps, SubmapSettings(look_ahead_m=0.0, resident=2))
    assert reads == [0, 1, 2] and field.meta["train_frames"] == [0, 1, 2]  # read once for the records
    np.testing.assert_allclose(field.bounds, [[-1, -1, -1], [16, 1, 1]])
    K = default_intrinsics(8, 6)
    T = np.eye(4)
    levels = []
    for x in (1.0, 6.0, 11.0, 1.0, 6.0):
        T[0, 3] = x
        levels.append(int(field.render(T, K).rgb[0, 0, 0]))
    assert levels == [0, 1, 2, 0, 1] and reads[3:] == [0, 1, 2, 0, 1] and len(field._loaded) == 2
    assert max(held_at_read) == 1  # the least recently used is let go before the next is read
    T[0, 3] = 6.5  # still resident: not read again
    assert int(field.render(T, K).rgb[0, 0, 0]) == 1 and len(reads) == 8

    class _Seen(_Flat):
        def render(self, T_world_cam, intrinsics):
            self.seen = T_world_cam
            return super().render(T_world_cam, intrinsics)

    R = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])  # grid x = map z
    inner = _Seen(0, 0, 1)
    framed = FramedField(inner, R)
    framed.render(T, K)
    np.testing.assert_allclose(inner.seen[:3, :3], R)
    np.testing.assert_allclose(inner.seen[:3, 3], R @ T[:3, 3])
    np.testing.assert_allclose(framed.bounds, [[-1, -1, 0], [1, 1, 1]])


@pytest.mark.slow
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
        assert isinstance(a, FramedField)  # each trained in its level frame along the floor
        for key, value in a.field.state_dict().items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, b.field.state_dict()[key]), key
    # Each submap's grid covers its own part of the room, not the whole survey's bounds.
    spans = [np.ptp(f.bounds, axis=0) for f in serial.fields]
    assert all(np.prod(s) < np.prod(np.ptp(serial.bounds, axis=0)) for s in spans)
    # Rendered in the map's frame from the submap each camera looks into (each field trained in
    # its own frame): the room's true depth all along the survey.
    from nap3d_graph.sims.sequence import default_intrinsics

    K = default_intrinsics(64, 48)
    oracle = survey.oracle_field()
    cover, errors = [], []
    for i in range(0, len(T), 3):
        got, want = serial.render(T[i], K).depth_m, oracle.render(T[i], K).depth_m
        ok = (got > 0) & (want > 0)
        cover.append(ok.mean())
        errors.append(np.median(np.abs(got[ok] - want[ok])))
    assert min(cover) > 0.7 and np.median(errors) < 0.015 and max(errors) < 0.03, (cover, errors)


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


def test_a_slab_keeps_the_depth_points_of_its_part_of_the_floor():
    """A camera 2 m before a wall across x at 5 m, looking along +x: every pixel's point has
    x = 5 m; a slab to 4.5 m drops them all, one to 5.5 m none, an open end none."""
    from nap3d_graph.fields.training_data import outside_slab
    from nap3d_graph.sims.sequence import default_intrinsics

    K = default_intrinsics(16, 12)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0.0]])  # OpenCV z forward = world +x
    T[0, 3] = 3.0
    depth = np.full((12, 16), 2.0)  # a plane 2 m ahead: z-depth 2 at every pixel
    depth[0, 0] = 0.0  # no depth: not outside
    assert outside_slab(depth, K, T, (1.0, 0.0, 0.0, 0.0, 4.5)).sum() == depth.size - 1
    assert not outside_slab(depth, K, T, (1.0, 0.0, 0.0, 0.0, 5.5)).any()
    assert not outside_slab(depth, K, T, (1.0, 0.0, 0.0, None, None)).any()
    # Along y the wall spans the frustum: the pixels left of the optical axis (world +y) are out.
    left = outside_slab(depth, K, T, (0.0, 1.0, 0.0, None, 0.0))
    assert left[1:, : int(K.cx) - 1].all() and not left[:, int(K.cx) + 1:].any()


@pytest.mark.slow
def test_a_submap_of_a_floor_keeps_its_grid_to_its_part_of_the_floor(tmp_path):
    """A three-room floor cut into three submaps: each grid ends ``reach_m`` beyond its core,
    the middle one is its part of the floor (before, a middle room's grid ran down the floor:
    its cameras see through the doors)."""
    import dataclasses

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.build import MapSettings
    from nap3d_graph.mapping.folder import MapFolder
    from nap3d_graph.mapping.submap_fields import train_submap_fields
    from nap3d_graph.pools import SerialPool
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    survey = open_sequence(simulate_sequence(tmp_path / "survey", SimConfig(
        frames=120, path="mapping", rooms=3, width=80, height=60, fps=0.56, seed=1)))
    T = np.asarray(survey.T_world_cam_gt)
    # Cut by count alone (the length's cut has its own test): a middle part longer than a room.
    settings = dataclasses.replace(MapSettings(matcher="sift", steps=10),
                                   submaps=SubmapSettings(max_frames=40, max_length_m=100.0))
    plan = plan_submaps(T, settings.submaps)
    assert len(plan) == 3
    folder = MapFolder.open(tmp_path / "map", {"data": "survey"}, ("data",))
    (folder.root / "map.json").write_text('{"data": "survey", "stages": {}}')
    folder = MapFolder.read(folder.root)
    merged = train_submap_fields(survey, T, folder, plan, settings, settings.submaps, {"steps": 10}, None,
                                 SerialPool(), "cpu")
    field = resolve_field(str(folder.root))
    floor = survey.oracle_field().scene
    # The map's held-out figures are its field's as a run renders it, on frames no submap trained on.
    held = merged["held_out"]
    assert held["frames"] and not set(held["frames"]) & set(field.meta["train_frames"])
    own = [s["held_out"]["opaque_fraction"] for s in merged["submaps"]]
    assert held["opaque_fraction"] > min(own) and held["psnr_db"] > 5.0, (held, own)
    reach_m = settings.submaps.reach_m
    for s, f in zip(plan, field.fields):
        lo, hi = np.asarray(f.field.bounds, dtype=float)  # its grid's box, in its grid's frame
        ax, ay, az, start, end = s.slab_m(reach_m)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        along = corners @ np.array([ax, ay, az])
        assert (start is None or along.min() > start - 0.5) and (end is None or along.max() < end + 0.5), (s.core, along)
    middle = np.ptp(field.fields[1].field.bounds, axis=0)  # in its grid's frame: x along the floor
    length_m = floor.walls_x[-1] - floor.walls_x[0]
    assert middle[0] < np.ptp(plan[1].core) + 2 * reach_m + 0.5 < length_m - 3.0, middle


class _LookingAlongX:
    """A survey of cameras looking along +x, each seeing a wall ``depth_m[i]`` ahead (0: none)."""

    def __init__(self, T_map_cam: np.ndarray, depth_m: np.ndarray):
        from nap3d_graph.sims.sequence import default_intrinsics

        self.T, self.depth_m, self.K = T_map_cam, depth_m, default_intrinsics(32, 24)

    def __len__(self) -> int:
        return len(self.T)

    def __getitem__(self, i: int):
        from nap3d_graph.camera import RGBDFrame

        depth = np.full((24, 32), self.depth_m[i], dtype=np.float32)
        return RGBDFrame(np.zeros((24, 32, 3), np.uint8), depth, self.K)


def _along_x_looking_forward(n: int, length_m: float) -> np.ndarray:
    T = _walk_along_x(n, length_m)
    T[:, :3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0.0]])  # OpenCV z forward = world +x
    return T


def test_a_submap_also_trains_on_the_frames_that_looked_into_it_from_elsewhere():
    """900 cameras along 18 m cut into three submaps; twenty of the first submap's cameras see a
    wall 7 m ahead (the middle submap's part of the floor), the rest one 0.5 m ahead (their own):
    the middle submap takes those twenty and no other, the others take none, and the cap holds."""
    from nap3d_graph.mapping.submaps import with_viewing_frames

    T = _along_x_looking_forward(900, 18.0)
    depth = np.full(900, 0.5)
    depth[100:120] = 7.0  # cameras at x = 2.0-2.4 m look at x = 9.0-9.4 m
    depth[300] = 0.0  # a frame without depth looks nowhere
    survey = _LookingAlongX(T, depth)
    settings = SubmapSettings(max_frames=300, overlap_m=0.5, max_length_m=10.0)
    plan = plan_submaps(T, settings)
    assert len(plan) == 3
    grown = with_viewing_frames(plan, survey, T, settings)
    middle = next(k for k, s in enumerate(plan) if s.distance_m(np.array([9.2, 0.0, 0.0])) == 0.0)
    for k, (before, after) in enumerate(zip(plan, grown)):
        added = sorted(set(after.frames) - set(before.frames))
        assert added == (list(range(100, 120)) if k == middle else []), k
        assert set(before.frames) <= set(after.frames) and np.array_equal(after.core, before.core)
    capped = with_viewing_frames(plan, survey, T, SubmapSettings(max_frames=300, overlap_m=0.5, max_length_m=10.0,
                                                                 viewing_frames=5))
    assert len(set(capped[middle].frames) - set(plan[middle].frames)) == 5
    off = with_viewing_frames(plan, survey, T, SubmapSettings(max_frames=300, viewing_frames=0))
    assert all(np.array_equal(a.frames, b.frames) for a, b in zip(off, plan))


def test_a_submap_grid_holds_its_slab_not_the_cameras_that_looked_in_from_afar():
    """Two cameras see the same wall at x = 2 m, one standing in the slab [0, 3] m at x = 1, one
    5 m before it: with the slab the box spans the first camera and the wall (plus the margin);
    without, the far camera stretches it to x = -5."""
    from nap3d_graph.fields.training_data import scene_bounds_from_depth
    from nap3d_graph.sims.sequence import default_intrinsics

    T = _along_x_looking_forward(2, 1.0)
    T[:, 0, 3] = [1.0, -5.0]
    T[:, 2, 3] = 0.0
    depth = np.stack([np.full((12, 16), 1.0), np.full((12, 16), 7.0)])
    K = default_intrinsics(16, 12)
    slab = scene_bounds_from_depth(depth, T, K, margin_m=0.1, slab_m=(1.0, 0.0, 0.0, 0.0, 3.0))
    assert slab[0, 0] == pytest.approx(0.9) and slab[1, 0] == pytest.approx(2.1)
    assert scene_bounds_from_depth(depth, T, K, margin_m=0.1)[0, 0] == pytest.approx(-5.1)


def test_a_submap_file_read_again_is_scanned_for_non_finite_weights_only_at_its_first_read(tmp_path, monkeypatch):
    """A run crossing a floor reads the same submap checkpoints again and again: each is scanned
    once, unless it changed on disk since (then a corrupt one is refused as at its first read)."""
    import os

    import torch

    import nap3d_graph.fields.grid as grid
    from nap3d_graph.fields import FieldError, load_field
    from nap3d_graph.fields.grid import GridField
    from nap3d_graph.fields.submaps import load_submap_field, write_submaps_index

    axis = np.array([1.0, 0.0, 0.0])
    submaps = [Submap(k, axis, np.array(core), np.arange(3)) for k, core in enumerate([(-np.inf, 1.0), (1.0, np.inf)])]
    for s, x0 in zip(submaps, (0.0, 1.0)):
        (tmp_path / s.file).parent.mkdir(exist_ok=True)
        GridField.empty([[x0, -0.5, -0.5], [x0 + 1.0, 0.5, 0.5]], voxel_size=0.1, device="cpu").save(tmp_path / s.file)
    write_submaps_index(tmp_path, submaps, SubmapSettings(resident=1), {})
    scans = []
    real_scan = grid._all_finite
    monkeypatch.setattr(grid, "_all_finite", lambda t, *a: scans.append(t.ndim) or real_scan(t, *a))
    field = load_submap_field(tmp_path, load_field)
    assert len(scans) == 4  # each file's density and colour, read once for the records
    for k in (0, 1, 0, 1):  # one resident: every read here reads a file again
        field.field_of(k)
    assert len(scans) == 4 and list(field._loaded) == [1]
    bad = GridField.empty([[0.0, -0.5, -0.5], [1.0, 0.5, 0.5]], voxel_size=0.1, device="cpu")
    with torch.no_grad():
        bad.density[0, 0, 0, 0, 0] = float("nan")
    bad.save(tmp_path / submaps[0].file)
    stat = (tmp_path / submaps[0].file).stat()
    os.utime(tmp_path / submaps[0].file, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # a new file on disk
    with pytest.raises(FieldError, match="non-finite"):
        field.field_of(0)
