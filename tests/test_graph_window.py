"""A bounded graph (PipelineConfig.graph_window): a long run's iSAM2 keeps a window of keyframes,
its results match the unbounded run's where nothing but the window differs, and corrections
still remove the drift."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from nap3d_graph.conventions import pose_error
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.trajectories import ImagelessWalk


def _graph_size(pipeline) -> tuple[int, int]:
    factors = pipeline.state.graph.isam.getFactorsUnsafe()
    live = sum(factors.at(i) is not None for i in range(factors.size()))
    return pipeline.state.graph.isam.calculateEstimate().size(), live


@pytest.mark.slow
def test_a_long_run_keeps_a_bounded_graph_and_the_same_trajectory():
    walk = ImagelessWalk(3000)
    base = PipelineConfig(keyframe_every=5, progress=False)
    sizes = []
    bounded = Pipeline(walk, None, make_odometry("noisy", walk, 1, 2e-3, 2e-3),
                       dataclasses.replace(base, graph_window=20))
    result = bounded.run(on_keyframe=lambda record: sizes.append(_graph_size(bounded)))
    assert len(result.keyframes) == 600
    variables, factors = np.max(sizes, axis=0)
    assert variables <= 31 and factors <= 40, (variables, factors)  # 1.5 x 20 keyframes at most
    assert sizes[-1][0] <= 31 and bounded.state.graph.first_live >= 570
    assert len(bounded.state.graph.factor_log) <= 40 and bounded.state.graph.graph_all.size() <= 40
    whole = Pipeline(walk, None, make_odometry("noisy", walk, 1, 2e-3, 2e-3), base).run()
    # Odometry alone: every keyframe's estimate is its odometry, windowed or not.
    np.testing.assert_allclose(result.T_world_cam_estimate, whole.T_world_cam_estimate, atol=1e-6)
    np.testing.assert_allclose(result.T_world_cam_online, whole.T_world_cam_online, atol=1e-6)


def test_a_bounded_run_still_removes_the_drift(tmp_path):
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.sims.sensors import DepthNoise
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    ideal = SimConfig(frames=48, seed=5, width=160, height=120, timing=None, exposure=None,
                      depth=DepthNoise(flying_fraction=0.0))
    walk = SimSequence(simulate_sequence(tmp_path / "w", ideal))
    config = PipelineConfig(keyframe_every=2, render_width=160, render_height=120, progress=False)

    def ate(result):
        return float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                      zip(result.T_world_cam_estimate, walk.T_world_cam_gt)])))

    runs = {window: Pipeline(walk, walk.oracle_field(), make_odometry("noisy", walk, 2, 6e-3, 6e-3),
                             dataclasses.replace(config, graph_window=window)).run() for window in (0, 4)}
    odometry = float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                      zip(runs[0].T_world_cam_odometry, walk.T_world_cam_gt)])))
    assert ate(runs[4]) < 0.5 * odometry, (ate(runs[4]), odometry)
    assert ate(runs[4]) < 1.5 * ate(runs[0]) + 0.002, (ate(runs[4]), ate(runs[0]))
    # The causal trajectory sees the window only through its relinearisation: the same drift.
    causal = {w: float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                        zip(r.T_world_cam_online, walk.T_world_cam_gt)]))) for w, r in runs.items()}
    assert causal[4] < 1.1 * causal[0] + 0.001, causal


def test_graph_window_is_refused_where_it_does_not_apply():
    with pytest.raises(ValueError, match="graph_window must be 0"):
        PipelineConfig(graph_window=2)
    walk = ImagelessWalk(10)
    with pytest.raises(ValueError, match="map anchor"):
        Pipeline(walk, None, make_odometry("noisy", walk, 1), PipelineConfig(graph_window=5, use_anchor=True))


def _kept(pipeline) -> int:
    """The most per-frame or per-keyframe items the run holds."""
    state = pipeline.state
    motion = state.motion
    return max(len(motion.T_world_cam_odom._items), len(motion.increments._items), len(state.online._items),
               len(state.keyframe_indices._items), len(state.records._items), len(state.graph.frozen))


@pytest.mark.slow
def test_a_long_run_that_retires_its_past_keeps_flat_memory_and_the_same_result(tmp_path):
    from nap3d_graph.run.history import join_segments
    from nap3d_graph.trajectory import read_tum_trajectory

    walk = ImagelessWalk(3000)
    config = PipelineConfig(keyframe_every=5, progress=False, graph_window=20)
    segments, kept = [], []
    written = open(tmp_path / "estimate.txt", "w")

    def retire(segment):
        segments.append(segment)
        segment.trajectories()["estimate"].append_tum(written)  # as a long run writes them out

    streamed = Pipeline(walk, None, make_odometry("noisy", walk, 1, 2e-3, 2e-3), config, on_retire=retire)
    result = streamed.run(on_keyframe=lambda record: kept.append(_kept(streamed)))
    result.trajectories()["estimate"].append_tum(written)
    written.close()
    # 600 keyframes; at most 1.5 windows of them (and their frames) are ever held.
    assert max(kept) <= 31 * 5 + 1, max(kept)
    assert len(segments) >= 50 and result.first_frame >= 3000 - 31 * 5
    whole = Pipeline(walk, None, make_odometry("noisy", walk, 1, 2e-3, 2e-3), config).run()
    joined = join_segments([*segments, result])
    assert joined.first_frame == 0 and len(joined.timestamps) == 3000 and len(joined.keyframes) == 600
    np.testing.assert_array_equal(joined.timestamps, whole.timestamps)
    np.testing.assert_allclose(joined.T_world_cam_estimate, whole.T_world_cam_estimate, atol=1e-9)
    np.testing.assert_allclose(joined.T_world_cam_online, whole.T_world_cam_online, atol=1e-12)
    np.testing.assert_allclose(joined.T_world_cam_odometry, whole.T_world_cam_odometry, atol=1e-12)
    np.testing.assert_allclose(joined.T_world_cam_gt, whole.T_world_cam_gt)
    assert joined.keyframe_indices == whole.keyframe_indices
    stamps, T_world_cam = read_tum_trajectory(tmp_path / "estimate.txt")
    np.testing.assert_allclose(stamps, whole.timestamps, atol=1e-6)
    np.testing.assert_allclose(T_world_cam, whole.T_world_cam_estimate, atol=1e-8)
    assert [k.frame_index for k in joined.keyframes] == [k.frame_index for k in whole.keyframes]
    with pytest.raises(ValueError, match="not consecutive"):
        join_segments([segments[0], segments[2]])


def test_a_live_corrector_that_retires_its_past_matches_the_one_that_keeps_it(tmp_path):
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.run.history import join_segments
    from nap3d_graph.run.live import DriftCorrector
    from nap3d_graph.sims.sensors import DepthNoise
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    ideal = SimConfig(frames=40, seed=7, width=160, height=120, timing=None, exposure=None,
                      depth=DepthNoise(flying_fraction=0.0))
    walk = SimSequence(simulate_sequence(tmp_path / "w", ideal))
    odometry = make_odometry("noisy", walk, 3, 6e-3, 6e-3)
    increments = [odometry.increment(i, None).T_prev_cur for i in range(1, len(walk))]
    config = PipelineConfig(keyframe_every=2, render_width=160, render_height=120, graph_window=4)
    field = walk.oracle_field()

    def corrector(segments=None):
        live = DriftCorrector(field, walk.T_world_cam_gt[0], config,
                              on_retire=None if segments is None else segments.append)
        for i in range(len(walk)):
            frame = walk[i]
            live.add_frame(frame.rgb, frame.depth_m, frame.intrinsics, frame.timestamp,
                           None if i == 0 else increments[i - 1])
        return live

    segments: list = []
    streamed, kept = corrector(segments), corrector()
    assert segments and len(streamed._frames.timestamps._items) < 20  # the stamps are let go too
    joined, whole = join_segments([*segments, streamed.finish()]), kept.finish()
    assert sum(k.accepted for k in joined.keyframes) == whole.num_accepted >= 10
    np.testing.assert_allclose(joined.T_world_cam_estimate, whole.T_world_cam_estimate, atol=1e-9)
    np.testing.assert_allclose(joined.T_world_cam_online, whole.T_world_cam_online, atol=1e-12)

    def ate(T_world_cam):
        return float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(T_world_cam, walk.T_world_cam_gt)])))

    assert ate(joined.T_world_cam_estimate) < 0.5 * ate(joined.T_world_cam_odometry), \
        (ate(joined.T_world_cam_estimate), ate(joined.T_world_cam_odometry))
