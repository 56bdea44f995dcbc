"""Radiance fields behind one protocol, and :func:`load_field` to open any of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nap3d_graph.sims.scene_file import oracle_from_file

from .base import FieldError, RadianceField
from .checkpoint import load_state
from .nerfstudio import load_nerfstudio_field
from .submaps import SUBMAPS_INDEX, load_submap_field

__all__ = ["RadianceField", "FieldError", "load_field", "resolve_field", "frames_seen_in_training"]


def load_field(path: str | Path, scanned: bool = False):
    """Open a field by what ``path`` is.

    * a simulated sequence folder or its ``scene.json``: the exact oracle field of that room;
    * a ``.pt`` checkpoint written by ``nap3d-graph train-field``: the grid, splat or view field it holds;
    * a nerfstudio ``config.yml``: the trained nerfstudio model (needs the optional extra).

    ``scanned``: this process has read the same file before and found its grid's weights finite
    (a submap read again, :func:`~.submaps.load_submap_field`): they are not scanned again.
    """
    path = Path(path)
    if path.is_dir() and (path / "scene.json").exists():
        path = path / "scene.json"
    if not path.exists():
        raise FieldError(f"{path}: no such field checkpoint, config or scene")
    if path.name == "scene.json":
        try:
            return oracle_from_file(path)
        except ValueError as exc:
            raise FieldError(str(exc)) from None
    if path.suffix == ".pt":
        from .grid import CHECKPOINT_FORMAT, GridField
        from .splat import SPLAT_FORMAT, SplatField
        from .views import VIEW_FORMAT, ViewField

        state = load_state(path)
        kind = state.get("format")
        if kind == CHECKPOINT_FORMAT:
            return GridField.from_state_dict(state, source=str(path), scan=not scanned)
        if kind == SPLAT_FORMAT:
            return SplatField.from_state_dict(state, source=str(path))
        if kind == VIEW_FORMAT:
            return ViewField.from_state_dict(state, source=str(path))
        raise FieldError(f"{path}: not a nap3d-graph field checkpoint (format {kind!r})")
    if path.suffix in (".yml", ".yaml"):
        return load_nerfstudio_field(path)
    raise FieldError(f"{path}: not a field (expected a .pt checkpoint, a nerfstudio config.yml or a scene.json)")


def resolve_field(field_arg: str, sequence=None):
    """What a ``--field`` argument names: ``oracle`` (the exact simulated room ``sequence``
    came from), ``none`` (no field: None), a map folder (``nap3d-graph map``: its field, with
    ``meta["map"]`` naming the folder), or a path for :func:`load_field`."""
    if field_arg == "none":
        return None
    if field_arg == "oracle":
        oracle = getattr(sequence, "oracle_field", None)
        if oracle is None:
            where = getattr(sequence, "path", "the data")
            raise FieldError(f"`field='oracle'` needs a simulated sequence (with scene.json); {where} is not one")
        return oracle()
    from pathlib import Path

    folder = Path(field_arg)
    if folder.is_dir() and (folder / "map.json").is_file():  # a map from 'nap3d-graph map'

        if (folder / SUBMAPS_INDEX).is_file():  # a map cut into submaps: their fields, one protocol
            try:
                field = load_submap_field(folder, load_field)
            except (FileNotFoundError, ValueError, KeyError) as exc:
                raise FieldError(str(exc)) from None
            field.meta["map"] = str(folder.resolve())
            return field
        checkpoint = folder / "field.pt"
        if not checkpoint.is_file():
            raise FieldError(f"{folder}: the map has no field (its 'nap3d-graph map' stopped before the field stage, "
                             "or ran with `no_field`); run the same map command again to finish it")
        field = load_field(checkpoint)
        field.meta["map"] = str(folder.resolve())
        return field
    return load_field(field_arg)


def frames_seen_in_training(field, sequence, tolerance_s: float = 1e-3) -> np.ndarray:
    """Which frames of ``sequence`` the field was trained on, (N,) bool: a correction there
    measures the field's memory of that very image, not how it generalises.

    A frame is recognised by its recording and its stamp: when the field records the
    recording it was built from (``meta["train_recording"]``) and the sequence has a
    ``recording_id``, another recording's frames are never reported, whatever their stamps
    (two simulated walks share stamps). ``sequence`` may also be a bare array of stamps (N,),
    matched by stamp alone. Fields that do not record their training frames (the oracle,
    nerfstudio models) give all False."""
    stamps = np.asarray(getattr(sequence, "timestamps", sequence), dtype=float).reshape(-1)
    meta = getattr(field, "meta", None) or {}
    trained = np.asarray(meta.get("train_timestamps") or [], dtype=float)
    if trained.size == 0 or stamps.size == 0 or not same_recording(meta, sequence):
        return np.zeros(stamps.shape, dtype=bool)
    trained = np.sort(trained)
    j = np.clip(np.searchsorted(trained, stamps), 1, max(trained.size - 1, 1))
    nearest = np.minimum(np.abs(stamps - trained[j - 1]), np.abs(stamps - trained[np.minimum(j, trained.size - 1)]))
    return nearest <= tolerance_s


def same_recording(meta: dict, sequence) -> bool:
    """Whether a field built with ``meta`` could have seen ``sequence``'s frames: False only
    when both name their recording and the names differ (old checkpoints name none)."""
    built_from = meta.get("train_recording")
    recording = getattr(sequence, "recording_id", None)
    return built_from is None or recording is None or built_from == recording
