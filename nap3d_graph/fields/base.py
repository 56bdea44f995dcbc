"""The radiance-field protocol every field satisfies (oracle, torch grid, nerfstudio)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from nap3d_graph.camera import Intrinsics, RenderedView

__all__ = ["RadianceField", "FieldError", "field_sigmas"]


class FieldError(ValueError):
    """A field that cannot be loaded or used (bad checkpoint, missing optional package)."""


@runtime_checkable
class RadianceField(Protocol):
    """``render(T_world_cam, intrinsics)`` gives RGB, z-depth (m) and opacity in [0, 1] seen
    by an OpenCV camera at ``T_world_cam`` (world <- camera); ``bounds`` is the (2, 3)
    world box ``[min, max]`` it covers; ``name`` says what it is."""

    name: str

    @property
    def bounds(self) -> np.ndarray: ...

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView: ...


def field_sigmas(field) -> tuple[float, float]:
    """``(sigma_m, sigma_rad)`` the field records (:func:`measure_field_error`), or zeros for a
    field that records none (the exact oracle, nerfstudio models, older checkpoints)."""
    error = (getattr(field, "meta", None) or {}).get("field_error") or {}
    return float(error.get("sigma_m", 0.0) or 0.0), float(error.get("sigma_rad", 0.0) or 0.0)
