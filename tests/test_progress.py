"""Progress bars written into a log or a pipe are one line every few seconds, not a line of
carriage-return refreshes."""

from __future__ import annotations

import io

from nap3d_graph import progress
from nap3d_graph.progress import progress_bar


def test_off_a_terminal_each_refresh_is_its_own_line_and_few_are_written(monkeypatch):
    clock = iter(range(0, 10_000))  # tqdm's clock: one second per call, so refreshes are due often
    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 5.0)
    log = io.StringIO()
    bar = progress_bar(range(200), desc="frames", file=log)
    bar._time = lambda: float(next(clock))  # noqa: SLF001 - tqdm reads its clock through this attribute
    for _ in bar:
        pass
    text = log.getvalue()
    lines = text.splitlines()
    assert "\r" not in text and lines[-1].startswith("frames: 100%") and "200/200" in lines[-1]
    # Hundreds of seconds of simulated time, one line per 5 s at most (tqdm may skip some).
    assert 2 <= len(lines) <= 200 // 5 + 2, len(lines)


def test_a_terminal_keeps_tqdms_live_bar():
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    out = Terminal()
    for _ in progress_bar(range(3), desc="live", file=out, mininterval=0):
        pass
    assert "\r" in out.getvalue()
