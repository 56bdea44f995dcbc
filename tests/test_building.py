"""The simulated floor of rooms: doors a camera sees through, twin rooms that look the same
from the same place, a survey that visits every room and a traverse that never comes back."""

import numpy as np
import pytest

from nap3d_graph.sims.building import Building, make_building, twin_layout
from nap3d_graph.sims.floor_paths import floor_survey, floor_traverse
from nap3d_graph.sims.scene import OracleField
from nap3d_graph.sims.scene_file import load_scene, oracle_from_file
from nap3d_graph.sims.sequence import default_intrinsics
from nap3d_graph.sims.trajectories import R_world_cam_from_angles

K = default_intrinsics(160, 120)


def _pose(x: float, y: float, yaw: float, z: float = 1.4) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R_world_cam_from_angles(yaw, 0.0, 0.0)
    T[:3, 3] = [x, y, z]
    return T


@pytest.fixture(scope="module")
def floor():
    return make_building(3, seed=0)


def test_layout_makes_every_third_room_a_twin(floor):
    assert twin_layout(1) == (0,) and twin_layout(3) == (0, 1, 0) and twin_layout(6) == (0, 1, 0, 3, 4, 3)
    assert floor.twins(0) == [2] and floor.twins(1) == [] and make_building(6).twins(3) == [5]
    with pytest.raises(ValueError, match="at least one room"):
        twin_layout(0)


def test_a_door_is_seen_through_and_a_wall_without_one_is_not(floor):
    """From the middle of room 0 looking along +X the centre ray passes both doors and stops at
    the far end wall; room 2 (no door in its +X wall) stops at its own wall. Depth is exact."""
    x_mid = floor.room_design(0).size_m[0] / 2
    view = OracleField(floor).render(_pose(x_mid, floor.door_y_m, 0.0), K)
    far_end = floor.walls_x[-1] - x_mid
    centre = view.depth_m[int(K.cy), int(K.cx)]
    assert abs(centre - far_end) < 1e-4 or centre < far_end  # furniture may stand in the last room's view
    assert centre > floor.walls_x[1] - x_mid + 0.5  # beyond room 0's own wall: seen through the door
    x2 = floor.walls_x[2] + x_mid
    view2 = OracleField(floor).render(_pose(x2, floor.door_y_m, 0.0), K)
    np.testing.assert_allclose(view2.depth_m[int(K.cy), int(K.cx)], floor.walls_x[3] - x2, atol=1e-4)
    # Above the door (2.1 m) the shared wall stops every ray.
    up = _pose(x_mid, floor.door_y_m, 0.0, z=2.5)
    depth_up = OracleField(floor).render(up, K).depth_m
    assert np.all(depth_up[: int(K.cy) - 5][depth_up[: int(K.cy) - 5] > 0] < floor.walls_x[1] - x_mid + 1e-3)


def test_twin_rooms_look_the_same_from_the_same_place_but_not_towards_their_doors(floor):
    """Room 2 is room 0's twin: from the same place in each, a view of the side wall is the same
    image; a view along the row is not (room 0's +X wall has the door, room 2's has none)."""
    field = OracleField(floor)
    offset = floor.walls_x[2]
    for yaw in (np.pi / 2, -np.pi / 2):
        a, b = field.render(_pose(2.4, 2.2, yaw), K), field.render(_pose(offset + 2.4, 2.2, yaw), K)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_allclose(a.depth_m, b.depth_m, atol=1e-9)
    a, b = field.render(_pose(2.4, floor.door_y_m, 0.0), K), field.render(_pose(offset + 2.4, floor.door_y_m, 0.0), K)
    assert np.mean(np.abs(a.depth_m - b.depth_m) > 0.5) > 0.05  # the doorway: a deep hole in one view only
    # Room 1 is no twin: its side wall is another image.
    c = field.render(_pose(floor.walls_x[1] + 2.4, 2.2, np.pi / 2), K)
    assert np.mean(np.abs(c.rgb.astype(int) - a.rgb.astype(int))) > 10


def test_a_floor_round_trips_through_its_scene_file(floor, tmp_path):
    floor.save(tmp_path / "scene.json")
    again = load_scene(tmp_path / "scene.json")
    assert isinstance(again, Building) and again.to_dict() == floor.to_dict()
    T = _pose(floor.walls_x[1] + 1.0, 2.0, 0.4)
    np.testing.assert_array_equal(OracleField(again).render(T, K).rgb, OracleField(floor).render(T, K).rgb)
    np.testing.assert_allclose(oracle_from_file(tmp_path / "scene.json").bounds, floor.bounds())
    (tmp_path / "bad.json").write_text('{"kind": "building", "version": 1}')
    with pytest.raises(ValueError, match="bad.json"):
        load_scene(tmp_path / "bad.json")


def test_the_survey_maps_every_room_in_turn_and_the_traverse_never_comes_back(floor):
    survey = floor_survey(floor, np.random.default_rng(0), 216.0)
    stamps = np.arange(0.0, survey.duration_s, 0.25)
    p = np.stack([survey.position_fn(t) for t in stamps])
    rooms = [floor.room_of(x) for x in p]
    assert sorted(set(rooms)) == [0, 1, 2] and np.all(np.diff(rooms) >= 0)  # room by room, never back
    for r in range(3):  # clear of the furniture band along the walls, but for the way through the doors
        local = p[np.asarray(rooms) == r] - floor.origin(r)
        assert local[:, 1].min() > 1.0 and local[:, 1].max() < floor.size_y - 1.0
        off_doorway = np.abs(local[:, 1] - floor.door_y_m) > 0.5
        assert np.all(local[off_doorway, 0] > 1.0) and np.all(local[off_doorway, 0] < floor.room_design(r).size_m[0] - 1.0)
    for start, end in ((0, 2), (2, 0), (1, 0)):
        walk = floor_traverse(floor, np.random.default_rng(1), 30.0, start, end, look_aside_deg=80.0)
        x = np.array([walk.position_fn(t)[0] for t in np.arange(0.0, 30.0, 0.1)])
        assert floor.room_of([x[0], 0, 0]) == start and floor.room_of([x[-1], 0, 0]) == end
        assert np.all(np.sign(end - start) * np.diff(x) >= -1e-9)  # never comes back
        # It starts looking at the side wall and turns ahead.
        assert abs(walk.angles_fn(0.0)[0] - (0.0 if end > start else np.pi) - np.radians(80.0)) < np.radians(35.0)
        # It goes through every door square on: at each shared wall it is within the doorway.
        for wall in floor.walls_x[1:-1]:
            if min(start, end) < floor.room_of([wall + 0.01, 0, 0]) <= max(start, end):
                t_wall = np.arange(0.0, 30.0, 0.02)[np.argmin(np.abs(np.array(
                    [walk.position_fn(t)[0] for t in np.arange(0.0, 30.0, 0.02)]) - wall))]
                assert abs(walk.position_fn(t_wall)[1] - floor.door_y_m) < floor.door_width_m / 2 - 0.2
