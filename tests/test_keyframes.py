"""Keyframes worth measuring: a due keyframe waits (within a short window) for a sharp frame
instead of landing on a motion-blurred one, and the odometry's doubt makes one at once."""

import dataclasses

import cv2
import numpy as np
import pytest

from nap3d_graph.camera import sharpness
from nap3d_graph.datasets import SimSequence
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline


class _Blurred:
    """A sequence whose frames ``blurred`` are smeared as by fast motion (a 15-pixel streak)."""

    def __init__(self, sequence, blurred):
        self._sequence, self.blurred = sequence, set(blurred)

    def __len__(self):
        return len(self._sequence)

    def __getattr__(self, name):
        return getattr(self._sequence, name)

    def __getitem__(self, i):
        frame = self._sequence[i]
        if i not in self.blurred:
            return frame
        kernel = np.zeros((15, 15), np.float32)
        kernel[7, :] = 1.0 / 15
        return dataclasses.replace(frame, rgb=cv2.filter2D(frame.rgb, -1, kernel))


@pytest.fixture(scope="module")
def walk(sim_walk):
    return SimSequence(sim_walk(33, width=192, height=144))


def test_sharpness_ranks_a_blurred_frame_below_its_sharp_self(walk):
    frame = walk[5]
    blurred = _Blurred(walk, {5})[5]
    assert sharpness(blurred.rgb) < 0.3 * sharpness(frame.rgb)


def test_a_due_keyframe_waits_for_the_next_sharp_frame(walk):
    due = set(range(4, 33, 4))  # where every-4th keyframes fall
    seq = _Blurred(walk, due)
    config = PipelineConfig(keyframe_every=4, keyframe_window=3, render_width=None, render_height=None)
    result = Pipeline(seq, walk.oracle_field(), make_odometry("recorded", walk), config).run()
    chosen = result.keyframe_indices
    assert chosen[0] == 0
    # No keyframe on a blurred frame; none later than the window allows (4 + 2 frames).
    assert not set(chosen) & due and chosen[1] == 5 and result.keyframes[1].postponed == 1
    assert all(4 <= b - a <= 6 for a, b in zip(chosen, chosen[1:]))
    records = result.keyframes[1:]
    assert all(r.why == "every" and r.postponed == (b - a) - 4 and np.isfinite(r.sharpness)
               for r, a, b in zip(records, chosen, chosen[1:]))
    # Without the window the keyframes land on the blurred frames.
    plain = Pipeline(seq, walk.oracle_field(), make_odometry("recorded", walk),
                     dataclasses.replace(config, keyframe_window=0)).run()
    assert set(plain.keyframe_indices[1:]) <= due
    # What the wait buys: more inliers per correction.
    assert np.median([r.inliers for r in records]) > 1.3 * np.median([r.inliers for r in plain.keyframes[1:]])


def test_a_window_of_blurred_frames_takes_its_last(walk):
    seq = _Blurred(walk, range(4, 33))  # everything after frame 3 is blurred
    config = PipelineConfig(keyframe_every=4, keyframe_window=3, render_width=None, render_height=None)
    result = Pipeline(seq, walk.oracle_field(), make_odometry("recorded", walk), config).run()
    # The first due keyframe (4) waits out its window: frames 1-3 were sharp, 4-6 are not.
    assert result.keyframe_indices[:2] == [0, 6] and result.keyframes[1].postponed == 2
    # From then on the blur is the norm, judged against the frames since the last keyframe.
    assert all(4 <= b - a <= 6 for a, b in zip(result.keyframe_indices, result.keyframe_indices[1:]))


class _DoubtingOdometry:
    """The recorded odometry, but its step into frame 10 is a guess (as VO's after losing track)."""

    def __init__(self, odometry):
        self._odometry = odometry

    def __getattr__(self, name):
        return getattr(self._odometry, name)

    def increment(self, i, frame):
        inc = self._odometry.increment(i, frame)
        return dataclasses.replace(inc, ok=False, reason="lost track") if i == 10 else inc


def test_the_odometrys_doubt_makes_a_keyframe_at_once(walk):
    config = PipelineConfig(keyframe_every=8, keyframe_on_doubt=True, render_width=None, render_height=None)
    result = Pipeline(walk, walk.oracle_field(), _DoubtingOdometry(make_odometry("recorded", walk)), config).run()
    assert result.keyframe_indices[:4] == [0, 8, 10, 18]
    assert [r.why for r in result.keyframes[:3]] == ["first", "every", "doubt"]
    off = Pipeline(walk, walk.oracle_field(), _DoubtingOdometry(make_odometry("recorded", walk)),
                   dataclasses.replace(config, keyframe_on_doubt=False)).run()
    assert off.keyframe_indices[:3] == [0, 8, 16]
