"""nap3d-graph: odometry drift removal with NAP3D alignments in a GTSAM factor graph.

The heavy parts (alignment, fields, torch) are imported lazily so ``import nap3d_graph``
stays fast and a missing optional dependency only matters where it is used.
"""

from __future__ import annotations

import importlib

from .camera import Intrinsics, RenderedView, RGBDFrame
from .results import Alignment, Correction

__version__ = "0.1.0"

_LAZY = {
    "align_views": ("nap3d_graph.nap3d", "align_views"),
    "correct_pose": ("nap3d_graph.nap3d", "correct_pose"),
    "AlignConfig": ("nap3d_graph.nap3d", "AlignConfig"),
    "load_field": ("nap3d_graph.fields", "load_field"),
    "DriftCorrector": ("nap3d_graph.run.live", "DriftCorrector"),
}

__all__ = ["Intrinsics", "RGBDFrame", "RenderedView", "Alignment", "Correction", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        module_name, attr = _LAZY[name]
        return getattr(importlib.import_module(module_name), attr)
    raise AttributeError(f"module 'nap3d_graph' has no attribute {name!r}")
