"""Drift correction a frame at a time (``DriftCorrector``): the same trajectory as the batch
run for the same inputs, the correction and the factor at each keyframe, bad input refused
without touching the graph."""

import numpy as np
import pytest

from nap3d_graph.conventions import exp_se3, pose_error
from nap3d_graph.datasets import SimSequence
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.live import DriftCorrector
from nap3d_graph.run.pipeline import Pipeline

CONFIG = PipelineConfig(keyframe_every=4, render_width=None, render_height=None)


@pytest.fixture(scope="module")
def walk(sim_walk):
    return SimSequence(sim_walk(21))


def _feed(corrector, walk, odometry) -> list:
    """Every frame of ``walk`` given to ``corrector`` with the odometry's increment, as a
    caller's loop does; the updates."""
    updates = []
    for i in range(len(walk)):
        frame = walk[i]  # the caller's own images, camera and stamps
        inc = odometry.increment(i, None) if i > 0 else None
        updates.append(corrector.add_frame(frame.rgb, frame.depth_m, frame.intrinsics, frame.timestamp,
                                           None if inc is None else inc.T_prev_cur,
                                           None if inc is None else inc.covariance))
    return updates


def test_frame_at_a_time_equals_the_batch_run(walk):
    field = walk.oracle_field()
    batch = Pipeline(walk, field, make_odometry("recorded", walk), CONFIG).run()
    odometry = make_odometry("recorded", walk)
    corrector = DriftCorrector(field, odometry.initial_pose(), CONFIG)
    updates = _feed(corrector, walk, odometry)
    live = corrector.finish()
    np.testing.assert_allclose(live.T_world_cam_estimate, batch.T_world_cam_estimate, atol=1e-9)
    np.testing.assert_allclose(live.T_world_cam_online, batch.T_world_cam_online, atol=1e-9)
    np.testing.assert_allclose(np.stack([u.T_world_cam for u in updates]), batch.T_world_cam_online, atol=1e-9)
    keyframes = [i for i, u in enumerate(updates) if u.keyframe]
    assert keyframes == batch.keyframe_indices == [0, 4, 8, 12, 16, 20]
    accepted = [u for u in updates if u.keyframe and u.record.accepted]
    assert len(accepted) >= 5 and all(u.factor is not None and u.correction.success for u in accepted)
    # The correction is the keyframe's pose, millimetres from the truth on the exact field.
    for u, i in zip(accepted, [i for i in keyframes if updates[i].record.accepted]):
        assert pose_error(u.correction.T_world_cam_corrected, walk.T_world_cam_gt[i])[0] < 0.01
    # The drift is gone from the causal estimate too (the odometry alone drifts centimetres).
    assert pose_error(updates[-1].T_world_cam, walk.T_world_cam_gt[-1])[0] < 0.01


def test_an_overlapped_corrector_returns_at_once_and_lands_each_correction_later(walk):
    """With ``overlap`` each keyframe is measured on a worker thread: ``add_frame`` reports the
    keyframe, and the correction comes with the frame at which it landed (at the latest when
    the next keyframe arrives, or at ``finish``). Each keyframe is measured at the same
    prediction as inline, so the smoothed trajectory is the inline one."""
    import dataclasses

    field = walk.oracle_field()
    inline = Pipeline(walk, field, make_odometry("recorded", walk), CONFIG).run()
    odometry = make_odometry("recorded", walk)
    corrector = DriftCorrector(field, odometry.initial_pose(), dataclasses.replace(CONFIG, overlap=True))
    updates = _feed(corrector, walk, odometry)
    result = corrector.finish()
    assert [i for i, u in enumerate(updates) if u.keyframe] == inline.keyframe_indices
    landed = [(i, u.record.frame_index) for i, u in enumerate(updates) if u.record is not None]
    assert all(keyframe <= i for i, keyframe in landed)  # never before its keyframe
    # Every keyframe's correction met the graph once: during a later frame or at finish.
    assert [r.frame_index for r in result.keyframes] == inline.keyframe_indices
    assert {k for _, k in landed} <= set(inline.keyframe_indices)
    assert result.num_accepted == inline.num_accepted
    np.testing.assert_allclose(result.T_world_cam_estimate, inline.T_world_cam_estimate, atol=1e-6)


def test_an_overlapped_corrector_given_time_returns_each_correction_with_its_keyframe(walk):
    """``land_within_s``: ``add_frame`` waits up to that long for the correction in flight
    (while a live loop would idle for the next frame). Given time enough, each keyframe's
    update carries its own correction, and every update's pose is the inline corrector's."""
    import dataclasses

    field = walk.oracle_field()
    inline = Pipeline(walk, field, make_odometry("recorded", walk), CONFIG).run()
    odometry = make_odometry("recorded", walk)
    corrector = DriftCorrector(field, odometry.initial_pose(),
                               dataclasses.replace(CONFIG, overlap=True, land_within_s=30.0))
    updates = _feed(corrector, walk, odometry)
    corrector.finish()
    assert [(i, u.record.frame_index) for i, u in enumerate(updates) if u.record is not None] == \
        [(i, i) for i in inline.keyframe_indices]
    np.testing.assert_allclose(np.stack([u.T_world_cam for u in updates]), inline.T_world_cam_online, atol=1e-6)


def test_bad_input_is_refused_and_the_graph_goes_on(walk):
    import gtsam

    field = walk.oracle_field()
    corrector = DriftCorrector(field, gtsam.Pose3(walk.T_world_cam_gt[0]), CONFIG)
    f0, f1 = walk[0], walk[1]
    corrector.add_frame(f0.rgb, f0.depth_m, f0.intrinsics, f0.timestamp)
    step = np.linalg.inv(walk.T_world_cam_gt[0]) @ walk.T_world_cam_gt[1]
    with pytest.raises(ValueError, match="needs the odometry"):
        corrector.add_frame(f1.rgb, f1.depth_m, f1.intrinsics, f1.timestamp)
    with pytest.raises(ValueError, match="not a rigid transform"):
        corrector.add_frame(f1.rgb, f1.depth_m, f1.intrinsics, f1.timestamp, step * 1.1)
    with pytest.raises(ValueError, match="stamps must increase"):
        corrector.add_frame(f1.rgb, f1.depth_m, f1.intrinsics, f0.timestamp, step)
    update = corrector.add_frame(f1.rgb, f1.depth_m, f1.intrinsics, f1.timestamp, gtsam.Pose3(step))
    assert not update.keyframe and pose_error(update.T_world_cam, walk.T_world_cam_gt[1])[0] < 0.002
    assert len(corrector.finish().timestamps) == 2
    with pytest.raises(ValueError, match="not a rigid transform"):
        DriftCorrector(field, exp_se3(np.zeros(6)) * 2.0)


def test_camera_pace_hands_each_frame_over_at_its_time_and_records_lateness(monkeypatch):
    """``run --pace``: frame i is taken no earlier than its stamp's offset from the first
    (divided by the speed); when the run is slower it is taken at once and the lateness is
    recorded. A fake clock: frames due at 0, 0.1, 0.2, 0.3 s (2x: 0, 0.05, 0.1, 0.15); the run
    spends 0.02 s on each frame except 0.12 s on frame 1."""
    import nap3d_graph.run.pacing as pacing
    from nap3d_graph.run.pacing import CameraPace

    clock = {"now": 100.0}
    monkeypatch.setattr(pacing.time, "perf_counter", lambda: clock["now"])
    monkeypatch.setattr(pacing.time, "sleep", lambda s: clock.__setitem__("now", clock["now"] + s))
    stops = iter([False, False, True, False])
    pace = CameraPace([5.0, 5.1, 5.2, 5.3], speed=2.0, then=lambda: next(stops))
    taken, answers = [], []
    for work_s in (0.02, 0.12, 0.02, 0.02):
        answers.append(pace())
        taken.append(clock["now"] - 100.0)
        clock["now"] += work_s
    np.testing.assert_allclose(taken, [0.0, 0.05, 0.17, 0.19])  # frames 2 and 3 late behind frame 1's work
    np.testing.assert_allclose(pace.behind_s, [0.0, 0.0, 0.07, 0.04], atol=1e-9)
    assert answers == [False, False, True, False]  # the wrapped hook (Ctrl-C) still speaks
    summary = pace.summary()
    assert summary["speed"] == 2.0 and summary["frames"] == 4
    assert summary["behind_camera_s"]["max"] == pytest.approx(0.07) and summary["frames_over_a_period_late"] == 1
    with pytest.raises(ValueError, match="speed"):
        CameraPace([0.0, 1.0], speed=0)
