"""numpy's BLAS thread pool (OpenBLAS), held to a fixed size while a run goes.

A run brings its own parallelism: the real frame's features detected beside the render
(inline), or the keyframe's whole measurement beside the odometry (``--overlap``). OpenBLAS
adds a pool of its own to every matrix product, and its idle threads spin while they wait for
work: on two cores numpy's products (XFeat's matching, the alignment) then take the core the
run's other thread needs. Measured on fr1/desk's second half, runs interleaved three at a
time (ad hoc, then ``benchmarks/realtime_desk.py``): XFeat with the grid field went 28.3-28.8
frame/s inline with OpenBLAS on one thread against 25.5 with its pool, and 30.9 overlapped
against 25.3. OpenCV's pool is left as it is: holding it too gave XFeat nothing (29.0
overlapped), SIFT's dense runs nothing (32.2 either way), and slowed SIFT's feature
odometry at 320 px, whose detections then ran on one thread (16.3 against 18.4 frame/s
overlapped; SIFT at 320x240 detects in 19 ms on two threads, 27 on one). The results do not
change: the same trajectories to the last bit (``tests/test_pipeline.py``).

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
def library_threads(count: int | None) -> Iterator[None]:
    """numpy's BLAS pool at ``count`` threads inside the block (None: as it is), set back
    after it. Without ``threadpoolctl`` the pool stays as it is (logged)."""
    if count is None:
        yield
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        log.info("threadpoolctl is not installed: numpy's BLAS threads are left as they are "
                 "(pip install threadpoolctl; a run on two cores is slower with them)")
        yield
        return
    with threadpool_limits(limits=count, user_api="blas"):
        yield
