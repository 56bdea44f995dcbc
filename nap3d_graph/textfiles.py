"""Reading the datasets' text files: data lines and numbers, each error one line with its
file and line number; and writing a JSON file atomically."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Iterator

from nap3d_graph.errors import DatasetError

__all__ = ["data_lines", "parse_float", "write_json_atomic"]


def data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of every non-empty, non-comment line; fields split on blanks/commas."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read ({exc})") from None
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        yield number, line.replace(",", " ").split()


def parse_float(path: Path, number: int, token: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise DatasetError(f"{path}:{number}: {token!r} is not a number") from None
    if not math.isfinite(value):
        raise DatasetError(f"{path}:{number}: non-finite value {token!r}")
    return value


def write_json_atomic(path: Path, data: dict, default=str) -> None:
    """``data`` as JSON in ``path``, atomically: a reader never sees half a file, a killed
    writer leaves none. ``default``: how values JSON does not know are written."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=default))
    os.replace(tmp, path)
