"""The map's mesh: the survey fused at its poses into a coloured PLY that Open3D reads back,
and the thickness of its walls, millimetres when the poses are right and the doubling itself
when part of the survey is shifted."""

import numpy as np
import pytest

from nap3d_graph.conventions import exp_se3


@pytest.fixture(scope="module")
def room_survey(sim_walk):
    from nap3d_graph.datasets import open_sequence

    return open_sequence(sim_walk(60, fps=1.875, path="mapping"))


def test_a_right_survey_has_thin_walls_and_a_doubled_one_says_how_far(room_survey, tmp_path):
    import open3d as o3d

    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.mapping.mesh import WALL_THICKNESS_BAD_M, MeshSettings, fuse_mesh

    T = np.asarray(room_survey.T_world_cam_gt)
    right = fuse_mesh(PosedSequence(room_survey, T, "truth"), tmp_path / "right.ply")
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "right.ply"))
    assert len(mesh.vertices) == right.vertices > 10_000 and mesh.has_vertex_colors()
    colours = np.asarray(mesh.vertex_colors)
    assert colours.std() > 0.05  # the room's textures, not one grey
    # The mesh lies on the room's surfaces: its vertices are within a voxel of the exact depth's points.
    lo, hi = room_survey.scene.bounds()
    vertices = np.asarray(mesh.vertices)
    assert np.all(vertices > lo - 0.1) and np.all(vertices < hi + 0.1)
    walls = right.thickness
    assert len(walls["planes"]) >= 4 and walls["thickness_m"] < 0.005, walls
    # The second half of the survey 6 cm along x: the walls across x are seen twice, 6 cm apart.
    bent_T = T.copy()
    bent_T[len(T) // 2:] = exp_se3(np.array([0.0, 0.0, 0.0, 0.06, 0.0, 0.0])) @ bent_T[len(T) // 2:]
    bent = fuse_mesh(PosedSequence(room_survey, bent_T, "bent"), tmp_path / "bent.ply", MeshSettings(every=1))
    x_walls = [p["spread_m"] for p in bent.thickness["planes"] if abs(p["normal"][0]) > 0.95]
    assert x_walls and abs(max(x_walls) - 0.06) < 0.01, bent.thickness
    assert bent.thickness["thickness_m"] > WALL_THICKNESS_BAD_M > walls["thickness_m"]


def test_a_survey_cut_into_submaps_is_fused_a_submap_at_a_time_into_one_mesh(room_survey, tmp_path):
    """The room's survey cut in two: each half fused alone keeps its core's triangles; the mesh
    is the whole survey's (every vertex on it), not doubled where the halves overlap, and the
    walls measure the same."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.fields.submaps import SubmapSettings
    from nap3d_graph.mapping.mesh import fuse_mesh
    from nap3d_graph.mapping.submaps import plan_submaps

    T = np.asarray(room_survey.T_world_cam_gt)
    posed = PosedSequence(room_survey, T, "truth")
    whole = fuse_mesh(posed, tmp_path / "whole.ply")
    plan = plan_submaps(T, SubmapSettings(max_frames=30))
    assert len(plan) == 2
    cut = fuse_mesh(posed, tmp_path / "cut.ply", submaps=plan)
    v_whole = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "whole.ply")).vertices)
    v_cut = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "cut.ply")).vertices)
    assert 0.85 * whole.vertices < cut.vertices < 1.05 * whole.vertices, (whole.vertices, cut.vertices)
    assert np.percentile(cKDTree(v_whole).query(v_cut)[0], 99) < 0.02
    # Around the cut (both halves fused it): as many vertices as the whole survey's, not twice.
    along_whole, along_cut = v_whole @ plan[0].axis, v_cut @ plan[0].axis
    cut_at = plan[0].core[1]
    band = [np.sum(np.abs(a - cut_at) < 0.3) for a in (along_whole, along_cut)]
    assert band[0] > 500 and band[1] < 1.15 * band[0], band
    assert cut.thickness["thickness_m"] == whole.thickness["thickness_m"]


def _desk_views(shift_m: float, rng) -> list[np.ndarray]:
    """Twenty views (points (P, 3), metres) of a 2 x 2 m desk top at z = 0 with books 4 cm tall on
    a quarter of it, each view a different 1 m window; the second half of the views put ``shift_m``
    higher (a survey bent between its halves). Sensor noise 3 mm."""
    views = []
    for k in range(20):
        x0, y0 = rng.uniform(-1.0, 0.0, size=2)
        xy = rng.uniform([x0, y0], [x0 + 1.0, y0 + 1.0], size=(6000, 2))
        z = np.where((xy[:, 0] > 0.3) & (xy[:, 1] > 0.3), 0.04, 0.0) + rng.normal(0, 0.003, len(xy))
        views.append(np.column_stack([xy, z + (shift_m if k >= 10 else 0.0)]))
    return views


def test_walls_are_measured_where_frames_see_the_same_cells_not_over_what_each_frame_sees():
    """Each view of a desk sees a different share of what stands on it: whole-view medians
    moved with that share (a consistent survey of fr1/desk read 4.9 cm thick at its
    ground-truth poses). Compared cell by cell between views, the consistent views are
    millimetres thick and a 3 cm bend reads 3 cm."""
    from nap3d_graph.mapping.mesh import WALL_THICKNESS_BAD_M, wall_thickness

    rng = np.random.default_rng(0)
    right = wall_thickness(_desk_views(0.0, rng))
    bent = wall_thickness(_desk_views(0.03, rng))
    desk = [p for p in right["planes"] if abs(p["normal"][2]) > 0.99]
    assert desk and right["thickness_m"] < 0.005 < WALL_THICKNESS_BAD_M, right
    assert abs(bent["thickness_m"] - 0.03) < 0.005, bent


def test_nothing_to_fuse_is_a_clear_error(room_survey, tmp_path):
    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.mapping.mesh import fuse_mesh

    nowhere = np.full((len(room_survey), 4, 4), np.nan)
    with pytest.raises(ValueError, match="no frame of the survey has a pose"):
        fuse_mesh(PosedSequence(room_survey, nowhere, "none"), tmp_path / "x.ply")
    assert not (tmp_path / "x.ply").exists()


def test_a_map_of_a_simulated_room_is_not_scored_against_the_simulators_world(room_survey):
    """The oracle renders in the simulator's world frame; a map's poses are in its first
    camera's: held-out depth of a self-posed simulated survey is scored against the sensor's
    depth, not against the oracle at the wrong place (it read 2.5 m of depth error)."""
    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.fields.evaluation import oracle_for

    assert oracle_for(room_survey) is not None
    assert oracle_for(PosedSequence(room_survey, np.asarray(room_survey.T_world_cam_gt), "map")) is None
