"""Sections of ``docs/results.md``, each a table generated from result files in
``benchmarks/results/`` (``python benchmarks/tables.py --write`` writes them; a test fails
when the committed page differs). A figure is read from its file, never typed.

Each module here exports ``SECTIONS``, a list of :class:`Section`, by topic: ``mapping`` (the
map), ``real`` (the real recordings), ``drift``, ``estimation``, ``speed`` and ``faults`` (the
simulated rooms, the estimators, timings, faults) and ``checks``. The formatters below are
the one set they share (a missing figure reads ``n/a`` in every one).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

RESULTS = Path(__file__).resolve().parents[1] / "results"


@dataclass(frozen=True)
class Section:
    """One table of the results page.

    title: the heading (what was measured, where).
    files: the result paths it reads, relative to ``benchmarks/results`` (a file, or a
        folder's file such as ``study_fr1_desk/summary.json``).
    command: the command that wrote them (as a user would type it).
    make: returns the table (markdown, header row included) from the files; it reads
        every figure from them and rounds, nothing else.
    note: one or two sentences on how to read the table (no figures in it).
    """

    title: str
    files: tuple[str, ...]
    command: str
    make: Callable[[], str]
    note: str = ""


def load(name: str):
    """The parsed JSON of ``benchmarks/results/<name>``."""
    return json.loads((RESULTS / name).read_text())


def get(data, *keys):
    """``data[k0][k1]...``, or None where a key, an index or the container itself is missing
    (a file written before a figure was recorded reads ``n/a``, not a crash)."""
    for key in keys:
        if isinstance(data, dict) and key in data:
            data = data[key]
        elif isinstance(data, list) and isinstance(key, int) and -len(data) <= key < len(data):
            data = data[key]
        else:
            return None
    return data


def cm(value_m, digits: int = 2) -> str:
    """Metres as centimetres, ``n/a`` for a missing value."""
    return "n/a" if value_m is None else f"{value_m * 100:.{digits}f}"


def mm(value_m, digits: int = 1) -> str:
    return "n/a" if value_m is None else f"{value_m * 1000:.{digits}f}"


def num(value, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


# --- the cells every section formats its figures with -------------------------------------


def read(name: str) -> dict:
    """The parsed JSON of ``benchmarks/results/<name>``, or an empty dict where it is missing."""
    try:
        return load(name)
    except FileNotFoundError:
        return {}


def number(data, *keys) -> float | None:
    """A number at ``keys`` (booleans excepted), or None where it is missing or not finite."""
    value = get(data, *keys)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return value


def ms(seconds, digits: int = 1) -> str:
    """Seconds as milliseconds."""
    return "n/a" if seconds is None else f"{seconds * 1000:.{digits}f}"


def count(value) -> str:
    """A count, ``n/a`` where missing."""
    return "n/a" if value is None else f"{value:.0f}"


def pct(fraction) -> str:
    """A fraction as a whole percentage."""
    return "n/a" if fraction is None else f"{fraction * 100:.0f}%"


def frac(part, whole) -> str:
    """``part/whole``, ``n/a`` where either is missing."""
    return "n/a" if part is None or whole is None else f"{part:.0f}/{whole:.0f}"


def span(low, high, fmt=num) -> str:
    """``low-high`` through ``fmt``; one value where both read the same; ``n/a`` where either is missing."""
    if low is None or high is None:
        return "n/a"
    a, b = fmt(low), fmt(high)
    return a if a == b else f"{a}-{b}"


def list_span(values, fmt=num) -> str:
    """The range of the numbers in ``values`` (a list), ``n/a`` where there is none."""
    numbers = [v for v in (values or []) if number([v], 0) is not None]
    return span(min(numbers), max(numbers), fmt) if numbers else "n/a"


def pair(a: str, b: str) -> str:
    """Two formatted figures of one cell."""
    return f"{a} / {b}"


def signed_pct(fraction, digits: int = 3) -> str:
    """A signed fraction as a percentage."""
    return "n/a" if fraction is None else f"{fraction * 100:+.{digits}f}%"


def yes(flag) -> str:
    """A flag in words."""
    return "n/a" if flag is None else ("yes" if flag else "no")
