"""Shared fixtures: a small simulated room and the real TUM frames."""

from pathlib import Path

import numpy as np
import pytest

TUM_FR1_XYZ = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum" / "rgbd_dataset_freiburg1_xyz"


@pytest.fixture(scope="session")
def tum_path() -> Path:
    if not (TUM_FR1_XYZ / "rgb.txt").exists():
        pytest.skip(f"real TUM frames not found at {TUM_FR1_XYZ}")
    return TUM_FR1_XYZ


@pytest.fixture(scope="session")
def room():
    """A hold-out procedural room (not the default one) and its oracle field."""
    from nap3d_graph.sims.scene import OracleField, make_scene

    scene = make_scene(11)
    return scene, OracleField(scene)
