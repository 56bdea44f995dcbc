"""The thread pools of the libraries a run calls (OpenBLAS through numpy, OpenCV), held to a
fixed size while the run goes.

An overlapped run (``--overlap``) brings its own parallelism: the odometry on one thread,
the keyframe's measurement on another. Each library call would add its own pool on top:
OpenCV's dense odometry spreads over every core and numpy's matrix products over OpenBLAS's
threads, which spin while they wait for work. On two cores that is four or five busy threads
for two: the overlapped fr1/desk run with XFeat went 0.85-0.88x as fast with the pools as
they come as with one thread each, in three pairs of runs
(``benchmarks/results/realtime_fr1_desk_xfeat.json``; with SIFT no difference beyond the
noise). An inline run's keyframe has the machine to itself and keeps the pools. The results
do not change: the same trajectories to the last bit (``tests/test_pipeline.py``).

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
    """OpenBLAS's and OpenCV's pools at ``count`` threads inside the block (None: as they
    are), set back after it. Without ``threadpoolctl`` the BLAS pool stays as it is (logged)."""
    if count is None:
        yield
        return
    import cv2

    with contextlib.ExitStack() as stack:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:
            log.info("threadpoolctl is not installed: numpy's BLAS threads are left as they are "
                     "(pip install threadpoolctl; a run on two cores is slower with them)")
        else:
            stack.enter_context(threadpool_limits(limits=count, user_api="blas"))
        before = cv2.getNumThreads()
        cv2.setNumThreads(count)
        stack.callback(cv2.setNumThreads, before)
        yield
