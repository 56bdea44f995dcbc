"""Field checkpoints: reading them safely (``torch.load(weights_only=True)``, one-line errors)
and storing their metadata as JSON."""

from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

from .base import FieldError

__all__ = ["load_state", "save_state", "check_state", "meta_json"]


def load_state(path: Path) -> dict:
    """The state dict of a checkpoint written by a field's ``save``: tensors and plain values
    only (never pickled code). Raises :class:`FieldError` on a missing, corrupt, truncated or
    foreign file, with the path and the cause on one line."""
    path = Path(path)
    if not path.is_file():
        raise FieldError(f"{path}: no such field checkpoint")
    if not zipfile.is_zipfile(path):
        raise FieldError(f"{path}: not a readable field checkpoint (not a torch zip archive: corrupt, truncated "
                         "or another format)")
    import torch

    try:
        # Mapped, not read: a checkpoint's tensors are its file's pages (shared with the page
        # cache, private if written to), so a field read again costs no copy and letting it go
        # returns its memory at once: a run across a floor reads its submaps' fields over and over.
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError:
        raise FieldError(f"{path}: not a readable field checkpoint (it holds pickled objects other than tensors "
                         "and plain values, which are refused)") from None
    except Exception as exc:  # torch raises many types for damaged files; all mean the same
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FieldError(f"{path}: not a readable field checkpoint ({detail[:200]})") from None
    if not isinstance(state, dict):
        raise FieldError(f"{path}: not a nap3d-graph field checkpoint")
    return state


def save_state(state: dict, path) -> Path:
    """Write a field's state dict with ``torch.save``, atomically (a temporary file renamed:
    never a half-written checkpoint under the real name); returns the path."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path


def check_state(state, source: str, kind: str, fmt: str, version: int, required: tuple[str, ...]) -> None:
    """Raise :class:`FieldError` (one line naming ``source``) unless ``state`` is a ``kind``
    checkpoint of format ``fmt``, version ``version``, holding every key of ``required``."""
    if not isinstance(state, dict) or state.get("format") != fmt:
        raise FieldError(f"{source}: not a nap3d-graph {kind} checkpoint")
    if state.get("version") != version:
        raise FieldError(f"{source}: {kind} checkpoint version {state.get('version')!r}, but this "
                         f"nap3d-graph reads version {version}; rebuild it with `nap3d-graph train-field`")
    missing = [k for k in required if k not in state]
    if missing:
        raise FieldError(f"{source}: checkpoint lacks {', '.join(missing)}")


def meta_json(meta: dict) -> str:
    """A field's metadata as JSON (numpy scalars and arrays, paths as plain values), as
    checkpoints store it."""
    return json.dumps(meta, default=_json_default)


def _json_default(value):
    import numpy as np

    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__} in checkpoint metadata")
