"""Reading a ``scene.json``: one room or a floor of rooms, whichever it describes."""

from __future__ import annotations

import json
from pathlib import Path

from .building import Building
from .scene import OracleField, Scene

__all__ = ["load_scene", "oracle_from_file"]


def load_scene(path: str | Path):
    """The scene a ``scene.json`` describes: one room (:class:`Scene`) or a floor of rooms
    (:class:`~nap3d_graph.sims.building.Building`); ``ValueError`` when it is neither."""
    path = Path(path)
    try:
        description = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a valid scene description ({exc})") from None
    if isinstance(description, dict) and description.get("kind") == "building":
        try:
            return Building.from_dict(description)
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: not a valid building description ({exc})") from None
    return Scene.load(path)


def oracle_from_file(path: str | Path) -> OracleField:
    """The exact field of the scene a ``scene.json`` describes."""
    return OracleField(load_scene(path))
