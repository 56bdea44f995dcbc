"""What a run keeps of its past, and how a long run lets go of it.

A run keeps, per frame, its odometry pose, its increment and its causal pose, and per
keyframe its record and its graph variable's frame. With a bounded graph
(``PipelineConfig.graph_window``) the oldest keyframes leave iSAM2 with their poses fixed:
from then on every frame up to the last fixed keyframe has its final smoothed pose, and a run
given somewhere to put them (``Pipeline(on_retire=...)``) hands them over as a
:class:`~nap3d_graph.run.records.RunResult` segment (its ``first_frame`` says where it starts)
and forgets them, so its memory stays flat however long it runs. :func:`join_segments` puts
the segments and the run's final result back together.

:class:`FrameLog` is the list that makes this possible: indexed by the absolute frame (or
keyframe) number however many of its oldest items were dropped.
"""

from __future__ import annotations

from typing import Generic, Iterator, TypeVar

import numpy as np

from nap3d_graph.run.records import RunResult

__all__ = ["FrameLog", "join_segments"]

T = TypeVar("T")


class FrameLog(Generic[T]):
    """A list indexed by absolute number whose oldest items can be dropped
    (:meth:`drop_before`). ``len`` counts every item ever appended; indexing a dropped item
    raises IndexError; negative indices count from the end; a slice ``[a:b]`` returns a list
    of the kept items in it (``a`` defaults to the oldest kept one)."""

    def __init__(self, items=()):
        self._items: list[T] = list(items)
        self.start = 0  # the absolute number of the oldest kept item

    def append(self, item: T) -> None:
        self._items.append(item)

    def mapped(self, fn) -> "FrameLog":
        """A FrameLog of ``fn(item)`` for each kept item, numbered as this one."""
        out: FrameLog = FrameLog(fn(item) for item in self._items)
        out.start = self.start
        return out

    def __len__(self) -> int:
        return self.start + len(self._items)

    def __getitem__(self, i):
        if isinstance(i, slice):
            if i.step not in (None, 1):
                raise ValueError("FrameLog slices take no step")
            first = self.start if i.start is None else i.start
            stop = len(self) if i.stop is None else min(i.stop, len(self))
            if first < self.start:
                raise IndexError(f"items before {self.start} were dropped (asked from {first})")
            return self._items[first - self.start:max(stop - self.start, first - self.start)]
        i = int(i)
        if i < 0:
            i += len(self)
        if not self.start <= i < len(self):
            raise IndexError(f"item {i} is not kept (kept: {self.start}..{len(self) - 1})")
        return self._items[i - self.start]

    def __iter__(self) -> Iterator[T]:
        return iter(self._items)

    def items(self) -> Iterator[tuple[int, T]]:
        """``(absolute number, item)`` of every kept item."""
        return enumerate(self._items, start=self.start)

    def first(self, condition) -> int:
        """The number of the oldest kept item for which ``condition(item)`` holds (``len``
        when none does)."""
        return next((k for k, item in self.items() if condition(item)), len(self))

    def drop_before(self, k: int) -> list[T]:
        """Forget the items numbered below ``k``; returns them."""
        cut = max(0, min(k, len(self)) - self.start)
        dropped, self._items = self._items[:cut], self._items[cut:]
        self.start += cut
        return dropped


def join_segments(segments: list[RunResult]) -> RunResult:
    """One :class:`RunResult` from consecutive pieces of a run (the segments a run handed to
    ``on_retire``, then its final result), as if nothing had been retired: trajectories,
    records and keyframes concatenated; the run-level fields (``wall_time_s``, the depth
    scale, the measurement stream, ``partial``...) from the last piece."""
    if not segments:
        raise ValueError("no segments to join")
    for before, after in zip(segments, segments[1:]):
        if before.first_frame + len(before.timestamps) != after.first_frame:
            raise ValueError(f"segments are not consecutive: frames from {before.first_frame} "
                             f"({len(before.timestamps)} of them), then from {after.first_frame}")
    last = segments[-1]

    def stacked(name: str):
        parts = [getattr(s, name) for s in segments]
        return None if any(p is None for p in parts) else np.concatenate([np.asarray(p) for p in parts])

    joined = RunResult(stacked("timestamps"), stacked("T_world_cam_estimate"), stacked("T_world_cam_odometry"),
                       stacked("T_world_cam_gt"), [k for s in segments for k in s.keyframes],
                       [i for s in segments for i in s.keyframe_indices], last.T_world_map, last.wall_time_s,
                       stacked("T_world_cam_online"), last.partial, list(last.gnc_outliers), list(last.gnc_recovered),
                       last.depth_scale, dict(last.interval_odometry), dict(last.corrections),
                       [inc for s in segments for inc in s.increments], first_frame=segments[0].first_frame)
    return joined
