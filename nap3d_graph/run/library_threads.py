"""The thread pools of the libraries a run calls (OpenBLAS through numpy, OpenCV), held to a
fixed size while the run goes.

A run brings its own parallelism: the real frame's features detected beside the render
(inline), or the keyframe's whole measurement beside the odometry (``--overlap``). Each
library call would add its own pool on top, and OpenBLAS's threads spin while they wait for
work: on two cores numpy's matrix products (XFeat's matching, the alignment) then steal the
other thread's core. Measured on fr1/desk's second half with the grid field, three
interleaved runs each (ad hoc, then ``benchmarks/realtime_desk.py``): XFeat inline 28.3-28.8
frame/s with OpenBLAS on one thread against 25.5 with its pool; overlapped 32.5 with both
libraries on one thread, 30.9 with OpenBLAS alone, 25.3 with neither. OpenCV's pool is kept
inline: there SIFT's detection and matching have the machine to themselves (at 320x240 19
and 3 ms on two threads against 27 and 5 on one; the SIFT run 31.2 frame/s keeping it
against 28.6 without). The results do not change: the same trajectories to the last bit
(``tests/test_pipeline.py``).

torch's thread count is set per block where torch is called
(:mod:`nap3d_graph.torch_threads`); numba's kernels are single-threaded.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

__all__ = ["library_threads"]

log = logging.getLogger(__name__)


@contextlib.contextmanager
def library_threads(count: int | None, opencv: bool = True) -> Iterator[None]:
    """OpenBLAS's pool, and with ``opencv`` OpenCV's, at ``count`` threads inside the block
    (None: as they are), set back after it. Without ``threadpoolctl`` the BLAS pool stays as
    it is (logged)."""
    if count is None:
        yield
        return
    with contextlib.ExitStack() as stack:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:
            log.info("threadpoolctl is not installed: numpy's BLAS threads are left as they are "
                     "(pip install threadpoolctl; a run on two cores is slower with them)")
        else:
            stack.enter_context(threadpool_limits(limits=count, user_api="blas"))
        if opencv:
            import cv2

            stack.callback(cv2.setNumThreads, cv2.getNumThreads())
            cv2.setNumThreads(count)
        yield
