"""Where a result file came from: each benchmark writes its JSON through :func:`write_result`,
which records the commit, the command (the flags given are the settings that differ from the
script's defaults, the training budget among them) and every setting the run used, so the
results page can say how each figure was measured."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def provenance(args=None) -> dict:
    """``commit`` (HEAD, ``+dirty`` when the tree had changes), ``command`` as typed (script
    path relative to the repository), ``settings`` (the parsed arguments, defaults included)
    and ``written`` (UTC)."""
    commit = _git("rev-parse", "--short=12", "HEAD")
    if commit and _git("status", "--porcelain", "--untracked-files=no"):
        commit += "+dirty"
    script = Path(sys.argv[0]).resolve()
    try:
        script_text = str(script.relative_to(ROOT))
    except ValueError:
        script_text = sys.argv[0]
    settings = {k: (v if isinstance(v, (int, float, bool, type(None))) else str(v))
                for k, v in sorted(vars(args).items())} if args is not None else {}
    return {"commit": commit, "command": " ".join(["python", script_text, *sys.argv[1:]]), "settings": settings,
            "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def _json_value(value):
    """numpy scalars and arrays as numbers, anything else as its text."""
    if hasattr(value, "tolist"):
        return value.tolist()
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)


def write_result(path: str | Path, result: dict, args=None) -> None:
    """``result`` with its ``provenance`` to ``path`` (JSON, atomically)."""
    from nap3d_graph.textfiles import write_json_atomic

    write_json_atomic(Path(path), {"provenance": provenance(args), **result}, default=_json_value)
