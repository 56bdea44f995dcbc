"""A bounded graph (PipelineConfig.graph_window): a long run's iSAM2 keeps a window of keyframes,
its results match the unbounded run's where nothing but the window differs, and corrections
still remove the drift."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from nap3d_graph.conventions import pose_error
from nap3d_graph.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.trajectories import ImagelessWalk


def _graph_size(pipeline) -> tuple[int, int]:
    factors = pipeline.graph.isam.getFactorsUnsafe()
    live = sum(factors.at(i) is not None for i in range(factors.size()))
    return pipeline.graph.isam.calculateEstimate().size(), live


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
    assert sizes[-1][0] <= 31 and bounded.graph.first_live >= 570
    assert len(bounded.graph.factor_log) <= 40 and bounded.graph.graph_all.size() <= 40
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
