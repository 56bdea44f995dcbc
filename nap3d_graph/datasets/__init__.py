"""Data sources: one module per format, each giving sequences of ``RGBDFrame``.

``SOURCES`` maps a source name (as the CLI's ``--traj`` uses it) to its sequence class:
``"tum"`` any TUM RGB-D folder, ``"sim"`` a folder written by ``nap3d-graph simulate``.
"""

from __future__ import annotations

from .sim import SimSequence
from .tum import DatasetError, TumSequence, read_tum_trajectory, write_tum_trajectory

__all__ = [
    "SOURCES",
    "open_sequence",
    "DatasetError",
    "TumSequence",
    "SimSequence",
    "read_tum_trajectory",
    "write_tum_trajectory",
]

SOURCES: dict[str, type] = {"tum": TumSequence, "sim": SimSequence}


def open_sequence(path, **kwargs):
    """A sequence folder as the right class: :class:`SimSequence` when the folder holds a
    simulator's ``scene.json``, :class:`TumSequence` otherwise."""
    from pathlib import Path

    cls = SimSequence if (Path(path) / "scene.json").exists() else TumSequence
    return cls(path, **kwargs)
