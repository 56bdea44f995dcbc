"""Reading a recording's next frames while the run works on this one.

A recording's frame costs its decoding (fr1/desk: two PNGs and the undistortion, 11-12 ms on
one core), a third of a 30 Hz camera's frame period. A live camera's driver hands over frames
already in memory, decoded on its own thread; a replay does the same here: one background
thread reads the ``ahead`` frames after the one asked for (OpenCV's decoders release the GIL,
so the reading runs on the other core), and the run takes each frame when it gets to it. The
frames are the same; only where their decoding runs changes. An overlapped run whose
keyframes wait for its second thread reads on its own thread instead: there a third thread
on two cores only slows what the run waits for (fr1/desk, the grid field overlapped: 10%
slower reading ahead; the view field, whose second thread keeps up: 7-13% faster).

Only sequences that say their frames can be read from another thread
(``reads_concurrently = True``: the file-per-frame formats and the RealSense recording,
decoded up front) are read ahead; a ROS bag's reader stays on the run's thread.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

__all__ = ["FrameReadAhead", "reads_concurrently"]


def reads_concurrently(sequence) -> bool:
    """Whether ``sequence``'s frames may be read on a thread other than the run's."""
    return bool(getattr(sequence, "reads_concurrently", False))


class FrameReadAhead:
    """``reader[i]`` is ``sequence[i]``, with frames ``i+1 .. i+ahead`` (below ``stop``) being
    read on a background thread meanwhile. A frame that could not be read raises what
    ``sequence[i]`` raised, when it is asked for. Use as a context manager (``close``).

    ``wanted()``, when given, is asked before reading more ahead: False reads nothing more
    ahead for now (frames not read ahead are read when asked for, on the asking thread). An
    overlapped run says False while it waits for its second thread: a reader competing with
    that thread for two cores would only slow what the run waits for.
    """

    def __init__(self, sequence, ahead: int, stop: int, wanted: Callable[[], bool] | None = None):
        if ahead < 1:
            raise ValueError(f"ahead must be >= 1, got {ahead}")
        self.sequence = sequence
        self.ahead = int(ahead)
        self.stop = int(stop)
        self.wanted = wanted
        self.read_ahead_count = 0  # frames handed over that were read ahead
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="nap3d-read-ahead")
        self._pending: dict[int, Future] = {}

    def __getitem__(self, i: int):
        i = int(i)
        future = self._pending.pop(i, None)
        # Frames before i (asked for out of order, or skipped) will not be asked for again.
        for j in [j for j in self._pending if j < i]:
            self._pending.pop(j).cancel()
        if self.wanted is None or self.wanted():
            for j in range(i + 1, min(i + 1 + self.ahead, self.stop)):
                if j not in self._pending:
                    self._pending[j] = self._pool.submit(self.sequence.__getitem__, j)
        if future is None:
            return self.sequence[i]
        self.read_ahead_count += 1
        return future.result()

    def close(self) -> None:
        """Drop the frames not asked for and stop the thread (waits for a read under way)."""
        for future in self._pending.values():
            future.cancel()
        self._pending.clear()
        self._pool.shutdown(wait=True)

    def __enter__(self) -> "FrameReadAhead":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
