"""torch's intra-op thread count for a block of code, shared safely between Python threads.

``torch.set_num_threads`` is process-wide. An overlapped run has several threads that call
torch at once (the keyframe worker renders and detects the render's features while the
odometry's thread detects the next keyframe's): a plain set-and-restore per block let one
thread restore the old count while another was still inside its block, so that block ran
with another thread count than it asked for (and torch's results need not be bit-identical
across thread counts); a lock around each block made the blocks wait for each other, and the
two detections of an overlapped run then took turns instead of using both cores.

Here blocks that ask for the same count run at once; a block that asks for another waits
until the current ones are done. The count set before the first block is restored after the
last. A block nested in another on the same thread does not wait (it would wait for itself):
with another count it sets it for its duration, as a plain set-and-restore does.
"""

from __future__ import annotations

import contextlib
import threading

__all__ = ["torch_threads"]

_CONDITION = threading.Condition()
_state = {"users": 0, "count": None, "before": None}
_local = threading.local()  # depth: this thread's open blocks


@contextlib.contextmanager
def torch_threads(count: int | None):
    """Run a block with ``torch.set_num_threads(count)``; ``None`` leaves torch's setting
    alone (and takes no part in the sharing).

    Why one thread by default in this project's callers: on a small CPU, and on any CPU other
    processes also use, torch's OpenMP threads spin while they wait for each other; one thread
    measured 15x faster than two per training step on this project's 2-core machine under
    load, and no slower when it was idle.
    """
    if count is None:
        yield
        return
    import torch

    count = int(count)
    if getattr(_local, "depth", 0):
        with _nested(torch, count):
            yield
        return
    with _CONDITION:
        while _state["users"] and _state["count"] != count:
            _CONDITION.wait()
        if not _state["users"]:
            _state["before"] = torch.get_num_threads()
            _state["count"] = count
            if count != _state["before"]:
                torch.set_num_threads(count)
        _state["users"] += 1
    _local.depth = 1
    try:
        yield
    finally:
        _local.depth = 0
        with _CONDITION:
            _state["users"] -= 1
            if not _state["users"]:
                if torch.get_num_threads() != _state["before"]:
                    torch.set_num_threads(_state["before"])
                _state["count"] = None
                _CONDITION.notify_all()


@contextlib.contextmanager
def _nested(torch, count: int):
    """A block inside this thread's open block: ``count`` for its duration, then the outer's."""
    outer = torch.get_num_threads()
    _local.depth += 1
    if count != outer:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        if count != outer:
            torch.set_num_threads(outer)
        _local.depth -= 1
