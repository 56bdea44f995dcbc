"""Sections of ``docs/results.md``, each a table generated from result files in
``benchmarks/results/`` (``python benchmarks/tables.py --write`` writes them; a test fails
when the committed page differs). A figure is read from its file, never typed.

Each module here exports ``SECTIONS``, a list of :class:`Section`.
"""

from __future__ import annotations

import json
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
