"""Where nap3d-graph caches what it builds once (the embedded default's data and field, a
recording's depth-colour registration)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["default_cache_dir"]


def default_cache_dir() -> Path:
    """``$NAP3D_GRAPH_CACHE`` or ``~/.cache/nap3d-graph``."""
    return Path(os.environ.get("NAP3D_GRAPH_CACHE", Path.home() / ".cache" / "nap3d-graph"))
