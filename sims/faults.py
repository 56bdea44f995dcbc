"""Sensor faults injected into any sequence, for tests and benchmarks of a run's robustness."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["ScaledDepth", "CoveredFrames"]


class ScaledDepth:
    """``sequence`` with the depth of frames ``i`` multiplied by ``factors[i]`` (a depth
    sensor whose metre is off on those frames); everything else as the sequence has it."""

    def __init__(self, sequence, factors: dict[int, float]):
        self._sequence, self._factors = sequence, factors

    def __getattr__(self, name):
        return getattr(self._sequence, name)

    def __len__(self):
        return len(self._sequence)

    def __getitem__(self, i):
        frame = self._sequence[i]
        factor = self._factors.get(int(i), 1.0)
        return frame if factor == 1.0 else frame.with_depth(frame.depth_m * np.float32(factor))


class CoveredFrames:
    """``sequence`` with frames ``frames`` (a range of indices) covered: black colour and no
    depth, as a lens covered for a moment or a blank wall too near for the depth sensor
    (the odometry loses the camera there); everything else as the sequence has it."""

    def __init__(self, sequence, frames: range):
        self._sequence, self._frames = sequence, frames

    def __getattr__(self, name):
        return getattr(self._sequence, name)

    def __len__(self):
        return len(self._sequence)

    def __getitem__(self, i):
        frame = self._sequence[i]
        if i not in self._frames:
            return frame
        return replace(frame, rgb=np.zeros_like(frame.rgb), depth_m=np.zeros_like(frame.depth_m))
