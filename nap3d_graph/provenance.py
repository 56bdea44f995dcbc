"""Where a result came from, written into each result file: the commit of the code (with
``+dirty`` when the tree had changes; outside a git checkout, the commit named by
``NAP3D_GRAPH_COMMIT`` for a copy of a checkout made without its ``.git``, else None), the
command as the process was started, the settings it ran with, and when (UTC). The results page
(``benchmarks/tables.py``) shows them beside each figure."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["provenance"]

#: The checkout the package runs from (an installed package is no checkout: no commit).
ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True,
                              timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def _command() -> str:
    """The command line, the script's path relative to the checkout where it lies in it."""
    script = Path(sys.argv[0]).resolve() if sys.argv and sys.argv[0] else None
    try:
        head = ["python", str(script.relative_to(ROOT))] if script is not None else []
    except ValueError:
        head = [Path(sys.argv[0]).name]
    return " ".join([*head, *sys.argv[1:]])


def _plain(value):
    """A setting as JSON keeps it: numbers, text, lists and mappings of them."""
    if isinstance(value, (bool, int, float, str, type(None))):
        return value
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return str(value)


def provenance(settings: dict | None = None) -> dict:
    """``{"commit", "command", "settings", "written"}`` for a result file."""
    commit = _git("rev-parse", "--short=12", "HEAD")
    if commit and _git("status", "--porcelain", "--untracked-files=no"):
        commit += "+dirty"
    elif commit is None:
        commit = os.environ.get("NAP3D_GRAPH_COMMIT") or None
    return {"commit": commit, "command": _command(), "settings": _plain(dict(settings or {})),
            "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
