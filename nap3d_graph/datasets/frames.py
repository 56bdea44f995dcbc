"""Frame ranges: ``START:STOP`` by index or by fraction of the sequence.

Train a field on one part of a recording and correct another: ``0:0.5`` is the first half,
``0.5:1`` the second, ``10:200`` frames 10 to 199, ``:-20`` all but the last twenty. When either bound has a
decimal point both are fractions of the sequence's length (rounded down), so ``0.5:1`` is
the second half; otherwise they are indices (negative counts from the end, as in Python).
"""

from __future__ import annotations

import logging

from nap3d_graph.errors import DatasetError

log = logging.getLogger(__name__)

__all__ = ["parse_frame_range", "frame_index"]


def _bound(text: str, n: int, default: int, spec: str, fractions: bool) -> int:
    text = text.strip()
    if not text:
        return default
    try:
        if fractions:
            fraction = float(text)
            if not 0.0 <= fraction <= 1.0:
                raise DatasetError(f"frame range {spec!r}: a fraction must be in [0, 1], got {text}")
            return int(fraction * n)
        index = int(text)
    except ValueError:
        raise DatasetError(f"frame range {spec!r}: {text!r} is neither an index nor a fraction") from None
    return max(0, n + index) if index < 0 else min(index, n)


def parse_frame_range(spec: str | None, n: int) -> tuple[int, int]:
    """``(start, stop)`` frame indices, ``0 <= start < stop <= n``, from ``START:STOP``.

    ``None`` or ``":"`` selects all ``n`` frames. Raises :class:`DatasetError` (one line) on
    a malformed or empty range.
    """
    if spec is None:
        return 0, n
    if ":" not in spec:
        raise DatasetError(f"frame range {spec!r}: expected START:STOP (indices or fractions, e.g. 0:0.5)")
    start_text, stop_text = spec.split(":", 1)
    fractions = "." in spec
    start, stop = _bound(start_text, n, 0, spec, fractions), _bound(stop_text, n, n, spec, fractions)
    if not 0 <= start < stop <= n:
        raise DatasetError(f"frame range {spec!r} selects no frames of {n} (start {start}, stop {stop})")
    if not fractions and _past_end(stop_text, n):
        log.warning("frame range %r ends past the sequence's %d frames: using %d:%d", spec, n, start, stop)
    return start, stop


def _past_end(text: str, n: int) -> bool:
    try:
        return int(text.strip()) > n
    except ValueError:
        return False


def frame_index(index, n: int, name: str) -> int:
    """``seq[index]``'s position among ``n`` frames (negative counts from the end, as in
    Python); IndexError naming the sequence when it is out of range."""
    import operator

    i = operator.index(index)
    if i < 0:
        i += n
    if not 0 <= i < n:
        raise IndexError(f"frame index {index} out of range for {n} frames of {name}")
    return i
