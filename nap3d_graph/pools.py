"""Where independent jobs run: processes on this machine, or Ray tasks on this machine or a
cluster. A sweep's cells and a map's submap fields are such jobs; both take either pool.

Each job runs in a process of its own with one thread for OpenMP, MKL and OpenBLAS
(``THREAD_ENV``): two jobs on two cores then use both, where each job's own threads would spin
against the other's. Why Ray and not a scheduler of our own: it already places tasks on a
cluster's nodes, retries a lost one and returns results; a ``--ray-address`` joins a cluster
started with ``ray start --head``.
"""

from __future__ import annotations

import os
import resource
import sys

__all__ = ["THREAD_ENV", "LocalPool", "RayPool", "SerialPool", "make_pool", "peak_memory_gb"]

#: Each job's threads: one (see the module's text).
THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def peak_memory_gb() -> float:
    """The most memory (resident, GB of 1024^3 bytes, as the benchmarks count) this process has
    held so far: read where a stage or a job ends, how much of the machine it needed. Linux's
    ``VmHWM`` (this program's own high-water mark); not ``ru_maxrss``, which a process started by
    another keeps from its parent (a submap worker spawned by a 1.1 GB map read 1.1 GB before it
    did anything)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024**2, 3)  # kB
    except OSError:
        pass
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1024 if sys.platform == "darwin" else 1)
    return round(peak_kib / 1024**2, 3)  # macOS counts bytes, Linux KiB


class SerialPool:
    """Jobs run one after another in this process, as they are submitted: the result of a
    pool of one, with nothing to start."""

    name = "serial"
    workers = 1

    class Done:
        """A job run at once: its value (a handle as the other pools' futures are)."""

        def __init__(self, value):
            self.value = value

    def submit(self, fn, *args):
        return self.Done(fn(*args))

    def wait_any(self, pending: list) -> tuple[list, list]:
        return pending[:1], pending[1:]

    @staticmethod
    def result(done):
        return done.value

    def close(self) -> None:
        pass


class LocalPool:
    """``workers`` processes on this machine (spawned: no state shared with the parent)."""

    name = "local"

    def __init__(self, workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers = workers
        self.executor = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))

    def submit(self, fn, *args):
        # The workers start within submit and inherit THREAD_ENV before numpy loads; this
        # process keeps its own threads (a map's field after its loops trains on all cores).
        saved = {k: os.environ.get(k) for k in THREAD_ENV}
        os.environ.update(THREAD_ENV)
        try:
            return self.executor.submit(fn, *args)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v

    def wait_any(self, pending: list) -> tuple[list, list]:
        from concurrent.futures import FIRST_COMPLETED, wait

        done, rest = wait(pending, return_when=FIRST_COMPLETED)
        return list(done), list(rest)

    @staticmethod
    def result(future):
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)


class RayPool:
    """Ray tasks of one CPU each: ``address`` "auto" starts a local Ray instance with
    ``workers`` CPUs; any other address joins that cluster (``ray start --head`` on it)."""

    name = "ray"

    def __init__(self, address: str, workers: int):
        try:
            import ray
        except ImportError:
            raise RuntimeError("`ray` needs Ray: pip install 'nap3d-graph[ray]'") from None
        self.ray = ray
        self.started = not ray.is_initialized()
        if self.started:
            env = {"env_vars": dict(THREAD_ENV)}
            if address == "auto":
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, runtime_env=env,
                         configure_logging=False)
            else:
                ray.init(address=address, log_to_driver=False, runtime_env=env, configure_logging=False)
        self.workers = int(ray.cluster_resources().get("CPU", workers))
        self._remote = {}

    def submit(self, fn, *args):
        if fn not in self._remote:
            self._remote[fn] = self.ray.remote(num_cpus=1, max_retries=1)(fn)
        return self._remote[fn].remote(*args)

    def wait_any(self, pending: list) -> tuple[list, list]:
        done, rest = self.ray.wait(pending, num_returns=1)
        return list(done), list(rest)

    def result(self, ref):
        return self.ray.get(ref)

    def close(self) -> None:
        if self.started:
            self.ray.shutdown()


def make_pool(workers: int, ray_address: str | None = None):
    """A pool for ``workers`` jobs at once: Ray tasks when ``ray_address`` is given ("auto": a
    local Ray instance of ``workers`` CPUs; otherwise that cluster's address), else processes on
    this machine, or this process alone for one worker."""
    if ray_address:
        return RayPool(ray_address, workers)
    if workers <= 1:
        return SerialPool()
    return LocalPool(workers)
