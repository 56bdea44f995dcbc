"""Procedural solid textures for the simulated rooms.

Textures are functions of the 3D world point (solid textures), so any primitive, flat or
curved, is textured without a surface parameterisation. Multi-octave value noise gives
blob-like structure at several scales and thresholded noise gives sharp-edged patches:
together they give SIFT enough corners and blobs. Real rooms also have plain surfaces (a
painted wall gives SIFT next to nothing) and fine ones (printed paper, fabric: detail a
centimetre across, finer than a 3 cm grid holds); rooms mix all three kinds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TextureSpec", "value_noise", "shade_texture"]

_TABLE_SIZE = 1024


def _lattice_values(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.permutation(_TABLE_SIZE), rng.random(_TABLE_SIZE)


_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}
_ROTATIONS: dict[int, np.ndarray] = {}


def _rotation(seed: int) -> np.ndarray:
    if seed not in _ROTATIONS:
        q, r = np.linalg.qr(np.random.default_rng(seed + 7919).normal(size=(3, 3)))
        _ROTATIONS[seed] = q * np.sign(np.diag(r))
    return _ROTATIONS[seed]


def _tables(seed: int) -> tuple[np.ndarray, np.ndarray]:
    if seed not in _CACHE:
        _CACHE[seed] = _lattice_values(seed)
    return _CACHE[seed]


def value_noise(points: np.ndarray, scale_m: float, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at points (N, 3), with features ~``scale_m`` wide."""
    perm, values = _tables(seed)
    # A per-seed random rotation keeps the lattice from lining up with walls and edges.
    p = np.asarray(points, dtype=float) @ _rotation(seed).T / scale_m
    base = np.floor(p)
    frac = p - base
    # Cubic smoothstep: continuous slope, fewer flat plateaus than the quintic fade.
    w = frac * frac * (3.0 - 2.0 * frac)
    ix = base.astype(np.int64) & (_TABLE_SIZE - 1)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        hx = perm[(ix[:, 0] + dx) & (_TABLE_SIZE - 1)]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            hy = perm[(hx + ix[:, 1] + dy) & (_TABLE_SIZE - 1)]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                h = perm[(hy + ix[:, 2] + dz) & (_TABLE_SIZE - 1)]
                out += wx * wy * wz * values[h]
    return out


@dataclass(frozen=True)
class TextureSpec:
    """Palette and noise parameters of one primitive's surface.

    palette: (3, 3) RGB colours in [0, 1] blended by the multi-scale noise.
    spot_rgb: (3,) colour of sharp-edged patches; spot_fraction: share of area they cover.
    kind: "standard", "plain" (a painted wall: nearly one colour, no patches, little for
    SIFT) or "fine" (detail down to ~1 cm, finer than a 3 cm grid can hold: paper, fabric).
    """

    seed: int
    palette: tuple[tuple[float, float, float], ...]
    spot_rgb: tuple[float, float, float]
    spot_fraction: float = 0.3
    scales_m: tuple[float, float, float] = (0.45, 0.14, 0.05)
    kind: str = "standard"

    def to_dict(self) -> dict:
        return {
            "seed": self.seed,
            "palette": [list(c) for c in self.palette],
            "spot_rgb": list(self.spot_rgb),
            "spot_fraction": self.spot_fraction,
            "scales_m": list(self.scales_m),
            "kind": self.kind,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "TextureSpec":
        return cls(
            seed=int(d["seed"]),
            palette=tuple(tuple(float(x) for x in c) for c in d["palette"]),
            spot_rgb=tuple(float(x) for x in d["spot_rgb"]),
            spot_fraction=float(d["spot_fraction"]),
            scales_m=tuple(float(x) for x in d["scales_m"]),
            kind=str(d.get("kind", "standard")),
        )

    @classmethod
    def random(cls, rng: np.random.Generator) -> "TextureSpec":
        hue_base = rng.random()
        palette = []
        for k in range(3):
            hue = (hue_base + 0.18 * k + 0.1 * rng.random()) % 1.0
            palette.append(_hsv_to_rgb(hue, 0.3 + 0.6 * rng.random(), [0.2, 0.6, 0.95][k] * (0.8 + 0.2 * rng.random())))
        spot = _hsv_to_rgb((hue_base + 0.5) % 1.0, 0.6 + 0.4 * rng.random(), 0.5 + 0.5 * rng.random())
        return cls(
            seed=int(rng.integers(0, 2**31 - 1)),
            palette=tuple(palette),
            spot_rgb=spot,
            spot_fraction=float(0.2 + 0.2 * rng.random()),
        )


    def as_kind(self, kind: str) -> "TextureSpec":
        """This texture turned plain (its palette pulled to within 4% of its mean colour, no
        patches) or fine (features from 20 cm down to 1.2 cm); "standard" leaves it."""
        from dataclasses import replace

        if kind == "plain":
            mean = np.mean(np.asarray(self.palette), axis=0)
            palette = tuple(tuple(float(m * (1.0 + 0.04 * (k - 1))) for m in mean) for k in range(3))
            return replace(self, palette=palette, spot_fraction=0.0, kind="plain")
        if kind == "fine":
            return replace(self, scales_m=(0.2, 0.04, 0.012), kind="fine")
        return self


def _hsv_to_rgb(h: float, s: float, v: float) -> tuple[float, float, float]:
    import colorsys

    return tuple(float(c) for c in colorsys.hsv_to_rgb(h, s, v))


def shade_texture(spec: TextureSpec, points_world: np.ndarray) -> np.ndarray:
    """Albedo (N, 3) in [0, 1] of the texture at world points (N, 3)."""
    coarse, mid, fine = spec.scales_m
    n = (
        0.55 * value_noise(points_world, coarse, spec.seed)
        + 0.30 * value_noise(points_world, mid, spec.seed + 1)
        + 0.15 * value_noise(points_world, fine, spec.seed + 2)
    )
    # Stretch the noise (it concentrates around 0.5) before the palette lookup.
    n = np.clip((n - 0.5) * 2.2 + 0.5, 0.0, 1.0)
    palette = np.asarray(spec.palette)
    # Piecewise-linear palette: 0 -> c0, 0.5 -> c1, 1 -> c2.
    lo = np.clip(n * 2.0, 0.0, 1.0)[:, None]
    hi = np.clip(n * 2.0 - 1.0, 0.0, 1.0)[:, None]
    albedo = np.where(n[:, None] < 0.5, palette[0] * (1 - lo) + palette[1] * lo,
                      palette[1] * (1 - hi) + palette[2] * hi)
    if spec.spot_fraction <= 0:
        return albedo  # a plain surface: no patches
    # Sharp-edged patches at two scales: corners and blobs SIFT can lock on to.
    threshold = 0.5 + (0.5 - spec.spot_fraction) * 0.9  # covers ~spot_fraction/2 of the area
    spot_rgb = np.asarray(spec.spot_rgb)
    for k, scale in enumerate((mid * 1.2, fine * 1.4)):
        spots = value_noise(points_world, scale, spec.seed + 3 + k)
        edge = np.clip((spots - threshold - 0.04 * k) / 0.025, 0.0, 1.0)[:, None]
        colour = spot_rgb if k == 0 else 1.0 - albedo.mean(axis=1, keepdims=True) * np.ones(3)
        albedo = albedo * (1 - edge) + colour * edge
    return albedo
