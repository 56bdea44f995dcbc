"""Progress bars that suit where they are written: tqdm's live bar on a terminal, and one
plain line every few seconds into a log file or a pipe (where tqdm's carriage-return
refreshes would pile up into one line of tens of kilobytes)."""

from __future__ import annotations

import sys
from typing import Any

#: Seconds between two lines when the output is not a terminal.
LOG_INTERVAL_S = 5.0


class _LineWriter:
    """A file-like that turns each of tqdm's ``\\r``-refreshes into one line of its own."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = text.replace("\r", "").rstrip()
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a closed or file-less stream
        return False


def progress_bar(iterable: Any = None, **kwargs: Any):
    """``tqdm(iterable, **kwargs)`` on a terminal; off a terminal the same bar as one line per
    ``LOG_INTERVAL_S`` seconds at most (and one at the end), on stderr unless ``file=`` says."""
    from tqdm import tqdm

    stream = kwargs.pop("file", None) or sys.stderr
    if _is_terminal(stream):
        return tqdm(iterable, file=stream, **kwargs)
    kwargs["mininterval"] = max(LOG_INTERVAL_S, kwargs.get("mininterval", 0.0))
    kwargs.setdefault("ncols", 100)
    return tqdm(iterable, file=_LineWriter(stream), dynamic_ncols=False, **kwargs)
