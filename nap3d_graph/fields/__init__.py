"""Radiance fields behind one protocol, and :func:`load_field` to open any of them."""

from __future__ import annotations

from pathlib import Path

from .base import FieldError, RadianceField

__all__ = ["RadianceField", "FieldError", "load_field"]


def load_field(path: str | Path):
    """Open a field by what ``path`` is.

    * a simulated sequence folder or its ``scene.json``: the exact oracle field of that room;
    * a ``.pt`` checkpoint written by ``nap3d-graph train-field``: the torch grid field;
    * a nerfstudio ``config.yml``: the trained nerfstudio model (needs the optional extra).
    """
    path = Path(path)
    if path.is_dir() and (path / "scene.json").exists():
        path = path / "scene.json"
    if not path.exists():
        raise FieldError(f"{path}: no such field checkpoint, config or scene")
    if path.name == "scene.json":
        from nap3d_graph.sims.scene import OracleField

        try:
            return OracleField.from_file(path)
        except ValueError as exc:
            raise FieldError(str(exc)) from None
    if path.suffix == ".pt":
        from .grid import GridField

        return GridField.load(path)
    if path.suffix in (".yml", ".yaml"):
        from .nerfstudio import load_nerfstudio_field

        return load_nerfstudio_field(path)
    raise FieldError(f"{path}: not a field (expected a .pt checkpoint, a nerfstudio config.yml or a scene.json)")
