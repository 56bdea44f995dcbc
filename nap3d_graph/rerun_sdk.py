"""rerun-sdk for the recordings ``run --viz`` and ``map --viz`` write: the import, with a one-line
error when the extra ``viz`` is missing, and the check of a ``--viz`` target before any work."""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["VizError", "import_rerun", "check_viz_target"]


class VizError(RuntimeError):
    """The visualisation cannot be made (no rerun-sdk, no display); one line."""


def import_rerun():
    try:
        import rerun as rr
    except ImportError:
        raise VizError("`viz` needs rerun-sdk: pip install 'nap3d-graph[viz]' (or pip install rerun-sdk)") from None
    return rr


def check_viz_target(target: str) -> str:
    """'spawn' (a display is needed) or a path ending in .rrd whose folder exists; checked
    before the run, so a bad target costs nothing."""
    import_rerun()
    if target == "spawn":
        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise VizError("`viz=spawn`: no display here ($DISPLAY unset); write `viz=run.rrd` and open it where "
                           "there is one with: rerun run.rrd")
        return target
    path = Path(target)
    if path.suffix != ".rrd":
        raise VizError(f"`viz={target}`: a recording file ends in .rrd (or give 'spawn')")
    if not path.parent.is_dir():
        raise VizError(f"`viz={target}`: its folder {path.parent} does not exist")
    return target
