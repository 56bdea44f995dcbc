"""The run's parts take the run's state for the length of a call and return what they found:
no code outside ``Pipeline`` reads or writes a ``Pipeline``'s own attributes (its state and
parts), on the inline, overlapped, bounded, anchored, placed-in-a-map, recovering and live paths."""

import dataclasses
import sys
from collections import Counter

import numpy as np
import pytest

from nap3d_graph.conventions import exp_se3, inv_T
from nap3d_graph.datasets import SimSequence
from nap3d_graph.mapping.relocalise import Relocalisation
from nap3d_graph.motion.odometry import RecordedOdometry, make_odometry
from nap3d_graph.run import pipeline as pipeline_module
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.live import DriftCorrector
from nap3d_graph.run.pipeline import Pipeline


class _Watch:
    """Counts each read or write of a ``Pipeline`` instance's own attribute (one in its
    ``__dict__``; methods and properties are its interface) by code outside the class."""

    def __init__(self):
        self.outside: Counter = Counter()

    def _outside(self, name: str) -> None:
        code = sys._getframe(2).f_code
        if not (code.co_filename == pipeline_module.__file__ and code.co_qualname.startswith("Pipeline.")):
            self.outside[name, code.co_qualname] += 1

    def install(self, monkeypatch) -> None:
        watch = self

        def getattribute(obj, name):
            if name in object.__getattribute__(obj, "__dict__"):
                watch._outside(name)
            return object.__getattribute__(obj, name)

        def setattr_(obj, name, value):
            watch._outside(name)
            object.__setattr__(obj, name, value)

        monkeypatch.setattr(Pipeline, "__getattribute__", getattribute)
        monkeypatch.setattr(Pipeline, "__setattr__", setattr_)


class _GroundTruthMap:
    """A map's relocaliser that finds each frame where the ground truth puts it."""

    look_alike_offsets: list = []

    def __init__(self, walk):
        self.stamps, self.T_gt = list(walk.timestamps), np.asarray(walk.T_world_cam_gt)

    def locate(self, frame, twist=None):
        i = self.stamps.index(frame.timestamp)
        return Relocalisation(True, self.T_gt[i], np.eye(6) * 1e-4, keyframe=0, inliers=100, sigma_m=0.01,
                              sigma_deg=0.5, agreeing=1, tried=1)


class _Jump:
    """An odometry that jumps once (35 cm, 14 deg) at frame ``at``: the run is lost there."""

    def __init__(self, inner, at: int):
        self.inner, self.at = inner, at

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def increment(self, i, frame):
        step = self.inner.increment(i, frame)
        jump = exp_se3(np.array([0.0, 0.25, 0.0, 0.35, 0.0, 0.0]))
        return dataclasses.replace(step, T_prev_cur=step.T_prev_cur @ jump) if i == self.at else step


@pytest.fixture(scope="module")
def walk(sim_walk):
    return SimSequence(sim_walk(24))


def test_no_code_outside_the_pipeline_reaches_into_it(walk, monkeypatch):
    watch = _Watch()
    watch.install(monkeypatch)
    field, config = walk.oracle_field(), PipelineConfig(keyframe_every=3)
    recorded = lambda: make_odometry("recorded", walk)  # noqa: E731
    for changes in ({}, {"overlap": True, "render_ahead": True, "land_within_s": 0.05, "keyframe_when_idle": 1},
                    {"graph_window": 3}, {"use_anchor": True}):
        Pipeline(walk, field, recorded(), dataclasses.replace(config, **changes), on_retire=lambda s: None).run()
    T_odom = np.asarray(walk.T_world_cam_odom)
    placed = Pipeline(walk, field, RecordedOdometry(inv_T(T_odom[0]) @ T_odom), config)
    placed.start_in_map(_GroundTruthMap(walk))
    assert placed.run().placement["placed"]
    lost = Pipeline(walk, field, _Jump(recorded(), at=10), config)
    lost.recover_in_map(_GroundTruthMap(walk))
    lost.run()
    assert [r for r in lost.recoveries if r["step"] == "recovered"]
    live = DriftCorrector(field, walk.T_world_cam_gt[0], config)
    for i in range(len(walk)):
        frame = walk[i]
        live.add_frame(frame.rgb, frame.depth_m, frame.intrinsics, frame.timestamp,
                       None if i == 0 else inv_T(T_odom[i - 1]) @ T_odom[i])
    assert live.finish().keyframes
    assert watch.outside == Counter()
    # The watch sees a reach when there is one.
    assert live.pipeline.sequence is not None and watch.outside
