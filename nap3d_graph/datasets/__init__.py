"""Data sources: one module per format, each giving sequences of ``RGBDFrame``.

``SOURCES`` maps a source name (as the CLI's ``--traj`` uses it) to its sequence class.
"""

from __future__ import annotations

from .tum import DatasetError, TumSequence, read_tum_trajectory, write_tum_trajectory

__all__ = ["SOURCES", "DatasetError", "TumSequence", "read_tum_trajectory", "write_tum_trajectory"]

SOURCES: dict[str, type] = {"tum": TumSequence}
