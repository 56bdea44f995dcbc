"""A run that starts in one of two twin rooms of a simulated floor: never placed in the twin,
placed once the camera sees what tells them apart; and the placement's rules one by one."""

import numpy as np
import pytest

from nap3d_graph.conventions import exp_se3, inv_T
from nap3d_graph.mapping.relocalise import Relocalisation, add_look_alike
from nap3d_graph.mapping.start import MapPlacement, PlacementSettings


@pytest.fixture(scope="module")
def twin_floor(tmp_path_factory):
    """A three-room floor (room 2 the twin of room 0), its survey indexed at its true poses
    (no survey error: relocalisation alone is under test), and a walk that starts in room 2
    looking back over its shoulder (120 deg) at a corner both twins have, then turns towards
    the door to room 1."""
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.mapping.build import MapSettings, index_posed_survey
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    root = tmp_path_factory.mktemp("floor")
    survey = open_sequence(simulate_sequence(root / "survey", SimConfig(
        frames=300, path="mapping", rooms=3, width=240, height=180, fps=1.875, seed=1)))
    walk = open_sequence(simulate_sequence(root / "walk", SimConfig(
        frames=60, path="traverse", rooms=3, start_room=2, end_room=1, look_aside_deg=120.0, width=240, height=180,
        fps=4.5, seed=2)))
    index = index_posed_survey(survey, root / "index", survey.T_world_cam_gt, MapSettings(matcher="sift",
                                                                                          keyframe_every=2))
    return index.root, walk


def test_a_start_in_a_twin_room_waits_for_what_tells_the_rooms_apart(twin_floor):
    from nap3d_graph.mapping.relocalise import Relocaliser
    from nap3d_graph.motion.odometry import RecordedOdometry
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline

    index, walk = twin_floor
    field = walk.oracle_field()
    floor = field.scene
    T_gt, T_odom = np.asarray(walk.T_world_cam_gt), np.asarray(walk.T_world_cam_odom)
    pipeline = Pipeline(walk, field, RecordedOdometry(inv_T(T_odom[0]) @ T_odom),
                        PipelineConfig(keyframe_every=3, align=AlignConfig(matcher="sift")))
    relocaliser = Relocaliser(index, field, AlignConfig(matcher="sift"))
    # The posed index met the twins as a map's survey does: loops a room from the given poses.
    twin_m = floor.walls_x[2] - floor.walls_x[0]
    assert relocaliser.look_alikes and relocaliser.look_alike_offsets
    assert all(abs(np.linalg.norm(T[:3, 3]) - twin_m) < 0.5 for T in relocaliser.look_alike_offsets)
    pipeline.start_in_map(relocaliser)
    run = pipeline.run()
    events = run.placement["events"]
    relocalised = [e for e in events if e["step"] == "relocalise" and "at_m" in e]
    ambiguous = [e for e in relocalised if e.get("reason", "").startswith("ambiguous")]
    # The first view that verifies (a corner both twins have) verifies in both rooms: refused,
    # not guessed.
    answered = [e for e in relocalised if e["success"] or e.get("reason", "").startswith("ambiguous")]
    assert ambiguous and answered[0] is ambiguous[0], relocalised
    assert all(abs(r["distance_m"] - twin_m) < 0.5 for e in ambiguous
               for r in e["rivals"])
    # No answer taken as a candidate is in the wrong room.
    for e in relocalised:
        if e["success"]:
            assert floor.room_of(e["at_m"]) == floor.room_of(T_gt[e["frame"], :3, 3]), e
    assert run.placement["placed"] and run.placement["placed_at_frame"] > ambiguous[-1]["frame"]
    errors = np.linalg.norm(run.T_world_cam_estimate[:, :3, 3] - T_gt[:, :3, 3], axis=1)
    assert errors.max() < 0.15 and np.sqrt(np.mean(errors**2)) < 0.08
    placed = run.placement["placed_at_frame"]
    assert errors[placed:].max() < 0.05  # once placed, in the right room to centimetres
    # The keyframes relocalised before the placement (ambiguous ones too: the answer or rival
    # where the placed graph puts the keyframe, through the gate) measure the poses before it:
    # 1.5 cm there, where the odometry from the placed keyframe alone left 5.6.
    earlier = [e for e in events if e["step"] == "earlier"]
    assert len(earlier) == 1 and earlier[0]["added_frames"] and max(earlier[0]["added_frames"]) < placed
    assert np.sqrt(np.mean(errors[:placed] ** 2)) < 0.03


class _Answers:
    """A relocaliser that answers from a list, in turn."""

    def __init__(self, answers):
        self.answers = list(answers)

    def locate(self, frame, twist=None):
        return self.answers.pop(0)


def _found(x_m: float, rivals_x_m=(), inliers: int = 100) -> Relocalisation:
    T = exp_se3(np.array([0, 0, 0, x_m, 0, 0.0]))
    rivals = [{"T_map_cam": exp_se3(np.array([0, 0, 0, r, 0, 0.0])), "keyframe": 7, "inliers": inliers,
               "distance_m": abs(r - x_m)} for r in rivals_x_m]
    return Relocalisation(True, T, np.eye(6) * 1e-4, keyframe=3, inliers=inliers, sigma_m=0.01, sigma_deg=0.5,
                          agreeing=1, tried=4, rivals=rivals)


class _Correction:
    def __init__(self, T):
        self.success, self.T_world_cam_corrected, self.num_inliers, self.reason = True, T, 80, ""
        self.covariance = np.eye(6) * 1e-4


def test_an_ambiguous_answer_is_no_candidate_and_a_placed_run_takes_the_one_where_it_is():
    placement = MapPlacement(_Answers([_found(1.0, [12.0])]))
    assert placement.propose(0, 0, None, np.eye(4)) is None and placement.candidate is None
    assert placement.events[-1]["reason"].startswith("ambiguous: the frame verifies 11.0 m away")
    # Once placed, the odometry is the prior: the rival where the run is wins, a jump is refused.
    placed = MapPlacement(_Answers([_found(1.0, [12.0]), _found(5.0)]), placed=True)
    T_here = exp_se3(np.array([0, 0, 0, 11.9, 0, 0.0]))
    candidate = placed.propose(3, 3, None, T_here)
    assert candidate is not None and abs(candidate.found.T_map_cam[0, 3] - 12.0) < 1e-9
    assert placed.propose(4, 4, None, T_here) is None
    assert "jumps 6.90 m" in placed.events[-1]["reason"]


def test_a_placement_needs_the_travel_its_settings_ask_for():
    settings = PlacementSettings(confirmations=1, confirm_travel_m=0.5)
    placement = MapPlacement(_Answers([_found(0.0)]), settings)
    placement.propose(0, 0, None, np.eye(4))
    verdicts = []
    for k, x in enumerate((0.2, 0.4, 0.6)):
        T = exp_se3(np.array([0, 0, 0, x, 0, 0.0]))
        verdicts.append(placement.confirm(k + 1, k + 1, _Correction(T), T))
    assert verdicts == ["agrees", "agrees", "confirmed"]
    assert [e["travel_m"] for e in placement.events if e["step"] == "confirm"] == [0.2, 0.4, 0.6]
    # A map whose survey found no look-alike places, and no rival met: one confirming keyframe places it.
    plain = _Answers([_found(0.0)])
    plain.look_alikes = False
    placement = MapPlacement(plain, settings)
    placement.propose(0, 0, None, np.eye(4))
    T = exp_se3(np.array([0, 0, 0, 0.2, 0, 0.0]))
    assert placement.confirm(1, 1, _Correction(T), T) == "confirmed"
    with pytest.raises(ValueError, match="confirm_travel_m"):
        PlacementSettings(confirm_travel_m=-1.0)


class _Failed:
    success, num_inliers, reason = False, 0, "too few matches (4 < 8)"


def test_a_candidate_that_agreed_waits_through_a_keyframe_that_measured_nothing():
    """A door passage matches nothing: that says nothing against a candidate a keyframe already
    agreed with, which waits (``max_unmeasured`` in a row) and is placed by the next that agree;
    one more failure in a row, or a failure before any agreement, drops it."""
    settings = PlacementSettings(confirmations=1, confirm_travel_m=0.5, max_unmeasured=2)
    placement = MapPlacement(_Answers([_found(0.0)]), settings)
    placement.propose(0, 0, None, np.eye(4))
    T = [exp_se3(np.array([0, 0, 0, x, 0, 0.0])) for x in (0.2, 0.3, 0.4, 0.6)]
    verdicts = [placement.confirm(1, 1, _Correction(T[0]), T[0]), placement.confirm(2, 2, _Failed(), T[1]),
                placement.confirm(3, 3, _Failed(), T[2]), placement.confirm(4, 4, _Correction(T[3]), T[3])]
    assert verdicts == ["agrees", "unmeasured", "unmeasured", "confirmed"]
    assert [k for k, _, _ in placement.candidate.confirmed] == [1, 4]
    assert "waits: 2 of 2 in a row" in placement.events[-2]["reason"]
    # A third failure in a row drops it; so does a failure before any keyframe agreed.
    placement = MapPlacement(_Answers([_found(0.0)]), settings)
    placement.propose(0, 0, None, np.eye(4))
    placement.confirm(1, 1, _Correction(T[0]), T[0])
    assert [placement.confirm(k, k, _Failed(), T[1]) for k in (2, 3, 4)] == ["unmeasured", "unmeasured", "refuted"]
    assert placement.candidate is None
    placement = MapPlacement(_Answers([_found(0.0)]), settings)
    placement.propose(0, 0, None, np.eye(4))
    assert placement.confirm(1, 1, _Failed(), T[0]) == "refuted"
    with pytest.raises(ValueError, match="max_unmeasured"):
        PlacementSettings(max_unmeasured=-1)


class _TwinRooms:
    """A map along x from 0 to 20 m whose field shows a wall 2 m ahead everywhere but a
    doorway (5 m of depth) seen from x in [1, 5): the place at x and its look-alike 11 m on
    look the same until the doorway is in view."""

    def render(self, T_map_cam, intrinsics):
        from types import SimpleNamespace

        x = T_map_cam[0, 3]
        shape = (intrinsics.height, intrinsics.width)
        depth = np.full(shape, 5.0 if 1.0 <= x < 5.0 else 2.0, np.float32)
        return SimpleNamespace(depth_m=depth, opacity=np.full(shape, float(0.0 <= x < 20.0), np.float32))


def _walk_to_the_doorway(placement: MapPlacement, first_key: int) -> list[str]:
    """Confirm the pending candidate with keyframes at x 0.2, 0.6 and 1.2 m of :class:`_TwinRooms`
    (keys from ``first_key``), each corrected where it stands: the doorway comes into view at
    x 1 m. Returns the verdicts."""
    from nap3d_graph.camera import Intrinsics, RGBDFrame

    K = Intrinsics(80.0, 80.0, 80.0, 60.0, 160, 120)
    verdicts = []
    for k, x in enumerate((0.2, 0.6, 1.2), start=first_key):
        T = exp_se3(np.array([0, 0, 0, x, 0, 0.0]))
        frame = RGBDFrame(np.zeros((120, 160, 3), np.uint8), _TwinRooms().render(T, K).depth_m, K)
        verdicts.append(placement.confirm(k, k, _Correction(T), T, frame))
    return verdicts


def test_after_a_rival_a_start_is_placed_only_once_the_camera_tells_the_look_alikes_apart():
    relocaliser = _Answers([_found(1.0, [12.0]), _found(0.0)])
    relocaliser.field = _TwinRooms()
    placement = MapPlacement(relocaliser, PlacementSettings(confirmations=1, confirm_travel_m=0.5))
    assert placement.propose(0, 0, None, np.eye(4)) is None  # ambiguous: 11 m apart
    assert [round(T[0, 3], 6) for T in placement.look_alike_offsets] == [11.0, -11.0]
    assert placement.propose(1, 1, None, np.eye(4)) is not None  # no rival this time: a candidate
    verdicts = _walk_to_the_doorway(placement, first_key=2)
    # 0.6 m of travel is enough, but both places explain the wall; the doorway tells them apart.
    assert verdicts == ["agrees", "agrees", "confirmed"]
    confirms = [e for e in placement.events if e["step"] == "confirm"]
    assert [e["look_alikes_ruled_out"] for e in confirms] == ["1 of 2", "1 of 2", "2 of 2"]


def test_the_look_alikes_a_survey_met_are_ruled_out_before_a_start_with_no_rival_is_placed(tmp_path):
    """The survey of a map along x refused a loop between keyframes 11 m apart as a look-alike
    place (its odometry could not have drifted so far): the map keeps that pair, and a start
    whose first answer met no rival (the twin alone verified, or the right room alone) is still
    placed only once the camera tells the two places apart, as after a rival."""
    from nap3d_graph.mapping.folder import MapFolder
    from nap3d_graph.mapping.loops import Loop, LoopSettings, refuse_look_alikes, save_edges
    from nap3d_graph.mapping.relocalise import look_alike_offsets

    T_map_key = np.stack([exp_se3(np.array([0, 0, 0, x, 0, 0.0])) for x in (0.5, 1.5, 11.5, 12.5)])
    # Keyframe 2 (x 11.5) matched keyframe 0's view as if it stood 2 cm from keyframe 0 (x 0.52).
    look_alike = Loop(0, 2, 0, 20, "appearance", 90, 80, 0.005, 0.004, 0.1,
                      T_a_b=exp_se3(np.array([0, 0, 0, 0.02, 0, 0.0])), covariance=np.eye(6) * 1e-6, status="verified")
    revisit = Loop(1, 3, 5, 25, "proximity", 90, 80, 0.005, 0.004, 0.1, T_a_b=inv_T(T_map_key[1]) @ T_map_key[3],
                   covariance=np.eye(6) * 1e-6, status="verified")
    assert refuse_look_alikes([look_alike, revisit], T_map_key, LoopSettings(drift_per_m=0.0)) == 1
    folder = MapFolder(tmp_path)
    save_edges(folder.edges, [], [look_alike, revisit], [])
    offsets = look_alike_offsets(folder, T_map_key)
    assert [round(T[0, 3], 6) for T in offsets] == [-10.98, 10.98]
    assert look_alike_offsets(MapFolder(tmp_path / "no map"), T_map_key) == []

    relocaliser = _Answers([_found(0.0)])  # no rival met
    relocaliser.field, relocaliser.look_alike_offsets = _TwinRooms(), offsets
    placement = MapPlacement(relocaliser, PlacementSettings(confirmations=1, confirm_travel_m=0.5))
    assert placement.propose(0, 0, None, np.eye(4)) is not None
    verdicts = _walk_to_the_doorway(placement, first_key=1)
    # The travel is there at 0.6 m, but only the doorway (x >= 1) rules out the place 11 m on.
    assert verdicts == ["agrees", "agrees", "confirmed"]


def test_a_survey_loop_between_twin_rooms_is_refused_and_a_revisit_kept():
    """Keyframes every 0.1 m along a 12 m walk. A revisit after 6 m of walking that the
    odometry put 20 cm off (it drifted) is kept; a loop between twin rooms 5.7 m apart, which
    says the two keyframes are in one place, is refused against the odometry."""
    from nap3d_graph.mapping.loops import Loop, LoopSettings, refuse_look_alikes

    T = np.tile(np.eye(4), (121, 1, 1))
    T[:, 0, 3] = np.linspace(0.0, 12.0, 121)
    revisit = Loop(10, 70, 10, 70, "appearance", T_a_b=exp_se3(np.array([0, 0, 0, 6.2, 0.0, 0])), status="verified")
    twins = Loop(20, 77, 20, 77, "appearance", T_a_b=np.eye(4), status="verified")
    refused = refuse_look_alikes([revisit, twins], T, LoopSettings())
    assert refused == 1 and revisit.status == "verified"
    assert twins.status == "refused" and twins.reason.startswith("look-alike place: the loop moves keyframe b 5.70 m")


def test_what_a_start_measured_before_its_candidate_is_kept_with_every_place_it_may_be():
    answers = _Answers([_found(1.0, [12.0]), _found(2.0)])
    answers.look_alikes = False
    placement = MapPlacement(answers, PlacementSettings(confirmations=1, confirm_travel_m=0.0))
    assert placement.propose(0, 10, None, np.eye(4)) is None  # ambiguous: no candidate, but measured
    cand = placement.propose(1, 11, None, np.eye(4))
    T = exp_se3(np.array([0, 0, 0, 2.2, 0, 0.0]))
    # It agrees (placed as if the camera had told the look-alikes apart: no field here to show it).
    assert placement.confirm(2, 12, _Correction(T), T) == "agrees"
    earlier = placement.earlier(placement.accept(2))
    # The candidate's own keyframes (11, 12) are the placement's; keyframe 10 is earlier, at
    # either of the places its answer and its rival put it.
    assert cand is not None and [m.key for m in earlier] == [10]
    assert sorted(T[0, 3] for T in earlier[0].T_map_cams) == [1.0, 12.0]
    # A placed run measures nothing for later: a recovery's relocalisation is no earlier pose.
    answers.answers.append(_found(3.0))
    placement.propose(3, 13, None, exp_se3(np.array([0, 0, 0, 3.0, 0, 0.0])))
    assert [m.key for m in placement.measured] == [10, 11, 12]


def test_two_twin_pairs_a_room_apart_keep_their_own_look_alike_moves():
    """Twin pairs 10.4 and 11.3 m apart are two moves (merged, a start in the second pair was
    checked against the first pair's move, 0.9 m off, and placed in its twin); one pair's
    answers a few centimetres apart are one move."""
    offsets: list = []
    for x_m in (10.42, 10.45, 11.29, 11.31):
        add_look_alike(offsets, exp_se3(np.array([0, 0, 0, x_m, 0, 0.0])))
    np.testing.assert_allclose(sorted(T[0, 3] for T in offsets), [-11.29, -10.42, 10.42, 11.29])
