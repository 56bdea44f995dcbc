"""Where a run's frames come from: its sequence, or a reader thread ahead of it.

:class:`FrameReader` is the one place a :class:`~nap3d_graph.run.pipeline.Pipeline` reads a
frame: an unreadable frame is logged and its reason kept (the keyframe record says it), and
the first frame primes the motion model.
"""

from __future__ import annotations

import logging

from nap3d_graph.camera import Intrinsics
from nap3d_graph.datasets import DatasetError
from nap3d_graph.datasets.protocol import FrameSource
from nap3d_graph.run.motion import MotionModel
from nap3d_graph.run.read_ahead import FrameReadAhead, reads_concurrently
from nap3d_graph.run.selection import KeyframeSelector

__all__ = ["FrameReader"]

log = logging.getLogger(__name__)


class FrameReader:
    """Frames of ``sequence`` for one run.

    motion: the run's motion model: primed with frame 0 when it is read, and asked at each
        frame whether it reads every frame now (else a run on recorded or IMU odometry reads
        its keyframes alone; an IMU run falling back on visual odometry reads every frame
        while it does).
    selector: the run's keyframe selection (a sharpness window reads every frame).
    """

    def __init__(self, sequence: FrameSource, motion: MotionModel, selector: KeyframeSelector):
        self.sequence = sequence
        self.source: FrameSource | FrameReadAhead = sequence
        self.motion, self.selector = motion, selector
        self.intrinsics: Intrinsics | None = None  # the last frame read's camera (a render made ahead uses it)
        self.error = "unknown error"  # why the last unreadable frame could not be read
        # The latest keyframe waits for the one in flight: a reader thread would only slow the
        # run down then (FrameReadAhead's ``wanted``).
        self.hold_back = False

    def reads_every_frame(self) -> bool:
        """Whether the motion model or the keyframe selection reads every frame now."""
        return self.motion.needs_frames or self.selector.reads_every_frame

    def read_ahead(self, depth: int, n: int) -> None:
        """Read up to ``depth`` frames of the first ``n`` ahead on a thread of their own, when
        the run reads every frame and the sequence allows it."""
        if depth and self.reads_every_frame() and reads_concurrently(self.sequence):
            self.source = FrameReadAhead(self.sequence, depth, n, wanted=lambda: not self.hold_back)

    def close(self) -> None:
        """Stop reading ahead (the run is over)."""
        if isinstance(self.source, FrameReadAhead):
            self.source.close()
        self.source = self.sequence

    def read(self, i: int):
        """Frame i, or None when it cannot be read (the reason logged and kept in ``error``)."""
        try:
            frame = self.source[i]
        except (DatasetError, OSError) as exc:
            log.warning("frame %d unreadable: %s", i, exc)
            self.error = str(exc)
            return None
        if i == 0:
            self.motion.prime(frame)
        self.intrinsics = frame.intrinsics
        return frame

    def for_odometry(self, i: int):
        """Frame i when the run reads every frame, else None."""
        return self.read(i) if self.reads_every_frame() else None

    def for_keyframe(self, i: int, frame, needed: bool):
        """The keyframe's image: ``frame`` when the odometry read it, else read now when
        ``needed`` (without a field a keyframe needs none)."""
        return self.read(i) if frame is None and needed else frame
