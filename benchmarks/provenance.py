"""Each benchmark writes its JSON through :func:`write_result`, which puts the library's
:func:`nap3d_graph.provenance.provenance` (commit, command, every setting the run used, when)
at its head, so the results page can say how each figure was measured."""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.provenance import provenance
from nap3d_graph.textfiles import write_json_atomic


def _json_value(value):
    """numpy scalars and arrays as numbers, anything else as its text."""
    if hasattr(value, "tolist"):
        return value.tolist()
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)


def write_result(path: str | Path, result: dict, args=None) -> None:
    """``result`` with its ``provenance`` (``args``: the parsed arguments) to ``path`` (JSON,
    atomically; its folder made when missing), and a line saying so: every benchmark's
    closing block."""
    settings = vars(args) if args is not None else None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, {"provenance": provenance(settings), **result}, default=_json_value)
    print(f"wrote {path}")
