"""Procedural indoor rooms and the analytic ray-caster that renders them.

A room is an axis-aligned box ``[0, Lx] x [0, Ly] x [0, Lz]`` (world frame, +Z up, metres)
furnished with yaw-rotated boxes, vertical cylinders and spheres (the curved primitives),
each with a solid procedural texture. :class:`OracleField` renders RGB, z-depth and opacity
at any ``T_world_cam`` and satisfies the same ``render`` protocol as trained fields, so NAP3D
can be tested against exact geometry.

Why hand-written: no maintained Python package ray-casts textured analytic scenes on a CPU
with exact z-depth and no GPU/OpenGL context; the geometry here is a few quadrics and slabs.
"""

from __future__ import annotations

import abc
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics, RenderedView

from .textures import TextureSpec, shade_texture

__all__ = ["Box", "Cylinder", "Sphere", "Room", "Scene", "OracleField", "make_scene", "RayCastRenderer", "furnish",
           "bounding_sphere", "hits_sphere", "object_from_dict",
           "SCENE_VERSION"]

SCENE_VERSION = 1
_EPS = 1e-6
_LIGHT_DIR = np.array([0.35, 0.25, 0.90]) / np.linalg.norm([0.35, 0.25, 0.90])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Room:
    """Interior of an axis-aligned box; the camera must be inside."""

    size_m: tuple[float, float, float]
    textures: tuple[TextureSpec, ...]  # one per face: -x, +x, -y, +y, floor, ceiling

    def intersect(self, origin: np.ndarray, dirs: np.ndarray):
        hi = np.asarray(self.size_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_axis = np.where(dirs > 0, (hi - origin) / dirs, -origin / dirs)
        t_axis = np.where(np.abs(dirs) < 1e-12, np.inf, t_axis)
        axis = np.argmin(t_axis, axis=1)
        t = t_axis[np.arange(len(dirs)), axis]
        positive = dirs[np.arange(len(dirs)), axis] > 0
        face = axis * 2 + positive.astype(int)
        normal = np.zeros_like(dirs)
        normal[np.arange(len(dirs)), axis] = np.where(positive, -1.0, 1.0)
        return t, normal, face

    def to_dict(self) -> dict:
        return {"size_m": list(self.size_m), "textures": [t.to_dict() for t in self.textures]}


@dataclass(frozen=True)
class Box:
    """Box of half-extents ``half_m`` centred at ``center_m``, rotated by ``yaw`` about +Z."""

    center_m: tuple[float, float, float]
    half_m: tuple[float, float, float]
    yaw: float
    texture: TextureSpec

    def intersect(self, origin: np.ndarray, dirs: np.ndarray):
        R = _rot_z(self.yaw)
        o = R.T @ (origin - np.asarray(self.center_m))
        d = dirs @ R  # (R^T d) for each row
        h = np.asarray(self.half_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - o) / d
            t2 = (h - o) / d
        t1 = np.where(np.isnan(t1), -np.inf, t1)
        t2 = np.where(np.isnan(t2), np.inf, t2)
        t_near = np.minimum(t1, t2)
        t_far = np.maximum(t1, t2)
        axis = np.argmax(t_near, axis=1)
        t_enter = t_near[np.arange(len(d)), axis]
        t_exit = t_far.min(axis=1)
        hit = (t_enter <= t_exit) & (t_enter > _EPS)
        t = np.where(hit, t_enter, np.inf)
        normal_local = np.zeros_like(d)
        normal_local[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
        return t, normal_local @ R.T

    def to_dict(self) -> dict:
        return {"type": "box", "center_m": list(self.center_m), "half_m": list(self.half_m),
                "yaw": self.yaw, "texture": self.texture.to_dict()}


@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder standing on ``z0_m`` up to ``z1_m`` with a flat top cap."""

    center_xy_m: tuple[float, float]
    radius_m: float
    z0_m: float
    z1_m: float
    texture: TextureSpec

    def intersect(self, origin: np.ndarray, dirs: np.ndarray):
        c = np.asarray(self.center_xy_m)
        ox, oy = origin[0] - c[0], origin[1] - c[1]
        dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
        a = dx * dx + dy * dy
        b = 2 * (ox * dx + oy * dy)
        cc = ox * ox + oy * oy - self.radius_m**2
        disc = b * b - 4 * a * cc
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
            t_side = (-b - sq) / (2 * a)
        z_side = origin[2] + t_side * dz
        side_ok = np.isfinite(t_side) & (t_side > _EPS) & (z_side >= self.z0_m) & (z_side <= self.z1_m)
        t_side = np.where(side_ok, t_side, np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_cap = (self.z1_m - origin[2]) / dz
        px = ox + t_cap * dx
        py = oy + t_cap * dy
        cap_ok = np.isfinite(t_cap) & (t_cap > _EPS) & (px * px + py * py <= self.radius_m**2) & (dz < 0)
        t_cap = np.where(cap_ok, t_cap, np.inf)
        use_cap = t_cap < t_side
        t = np.minimum(t_side, t_cap)
        normal = np.zeros_like(dirs)
        hx = ox + t_side * dx
        hy = oy + t_side * dy
        with np.errstate(invalid="ignore"):
            normal[:, 0] = np.where(use_cap, 0.0, hx / self.radius_m)
            normal[:, 1] = np.where(use_cap, 0.0, hy / self.radius_m)
        normal[:, 2] = np.where(use_cap, 1.0, 0.0)
        return t, np.nan_to_num(normal)

    def to_dict(self) -> dict:
        return {"type": "cylinder", "center_xy_m": list(self.center_xy_m), "radius_m": self.radius_m,
                "z0_m": self.z0_m, "z1_m": self.z1_m, "texture": self.texture.to_dict()}


@dataclass(frozen=True)
class Sphere:
    center_m: tuple[float, float, float]
    radius_m: float
    texture: TextureSpec

    def intersect(self, origin: np.ndarray, dirs: np.ndarray):
        oc = origin - np.asarray(self.center_m)
        a = np.einsum("ij,ij->i", dirs, dirs)
        b = 2 * dirs @ oc
        c = oc @ oc - self.radius_m**2
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore"):
            t = (-b - np.sqrt(np.where(disc >= 0, disc, np.nan))) / (2 * a)
        t = np.where(np.isfinite(t) & (t > _EPS), t, np.inf)
        hit_points = origin + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
        normal = (hit_points - np.asarray(self.center_m)) / self.radius_m
        return t, normal

    def to_dict(self) -> dict:
        return {"type": "sphere", "center_m": list(self.center_m), "radius_m": self.radius_m,
                "texture": self.texture.to_dict()}


@dataclass(frozen=True)
class Poster:
    """A flat picture hung on a wall of the room: a ``2 half_m`` rectangle ``standoff_m`` in
    front of wall ``wall`` (0: x = 0, 1: x = size_x, 2: y = 0, 3: y = size_y, as the room's
    faces), centred at ``centre_m`` (along the wall, height). Its pattern is drawn in its own
    frame (right as seen facing it, up), so two posters with one texture look the same
    wherever they hang: the repeated texture a map's loop closure must not be fooled by."""

    wall: int
    wall_m: float
    centre_m: tuple[float, float]
    half_m: tuple[float, float]
    texture: TextureSpec
    standoff_m: float = 0.01

    def _axis(self) -> int:
        return 0 if self.wall < 2 else 1

    def _plane(self) -> float:
        return self.wall_m + (self.standoff_m if self.wall in (0, 2) else -self.standoff_m)

    def _right(self) -> np.ndarray:
        """The direction to the right of someone facing the poster (world +Z up)."""
        return np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]][self.wall])

    def centre3(self) -> np.ndarray:
        centre = np.zeros(3)
        axis = self._axis()
        centre[axis], centre[1 - axis], centre[2] = self._plane(), self.centre_m[0], self.centre_m[1]
        return centre

    def intersect(self, origin: np.ndarray, dirs: np.ndarray):
        axis = self._axis()
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self._plane() - origin[axis]) / dirs[:, axis]
        points = origin + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
        along, z = points[:, 1 - axis], points[:, 2]
        hit = (np.isfinite(t) & (t > _EPS) & (np.abs(along - self.centre_m[0]) <= self.half_m[0])
               & (np.abs(z - self.centre_m[1]) <= self.half_m[1]))
        normal = np.zeros_like(dirs)
        normal[:, axis] = 1.0 if self.wall in (0, 2) else -1.0
        return np.where(hit, t, np.inf), normal

    def local_points(self, points: np.ndarray) -> np.ndarray:
        """World points on the poster (N, 3) in its own frame (right, up, 0): what its texture
        is drawn in."""
        rel = points - self.centre3()
        return np.stack([rel @ self._right(), rel[:, 2], np.zeros(len(rel))], axis=1)

    def to_dict(self) -> dict:
        return {"type": "poster", "wall": self.wall, "wall_m": self.wall_m, "centre_m": list(self.centre_m),
                "half_m": list(self.half_m), "standoff_m": self.standoff_m, "texture": self.texture.to_dict()}


def with_twin_posters(scene: "Scene", seed: int = 0, identical: bool = True) -> "Scene":
    """``scene`` with one picture hung twice, on the two walls across the room from each other
    (x = 0 and x = size_x, same place along the wall, above the furniture): a survey sees the
    same 1.2 x 0.8 m pattern in two places 5-7 m apart. ``identical`` False hangs two
    different pictures there instead (the control: the same room without a repeated texture)."""
    textures = [TextureSpec.random(np.random.default_rng([seed, 99 + k])).as_kind("standard") for k in range(2)]
    if identical:
        textures[1] = textures[0]
    size = scene.room.size_m
    along, height = size[1] / 2, min(2.0, size[2] - 0.5)
    posters = tuple(Poster(wall, wall_m, (along, height), (0.6, 0.4), texture)
                    for (wall, wall_m), texture in zip(((0, 0.0), (1, float(size[0]))), textures))
    return Scene(room=scene.room, objects=scene.objects + posters, free_xy_m=scene.free_xy_m, seed=scene.seed,
                 ambient=scene.ambient)


def bounding_sphere(obj) -> tuple[np.ndarray, float]:
    if isinstance(obj, Poster):
        return obj.centre3(), float(np.hypot(*obj.half_m)) + obj.standoff_m
    if isinstance(obj, Box):
        return np.asarray(obj.center_m), float(np.linalg.norm(obj.half_m))
    if isinstance(obj, Cylinder):
        half_h = (obj.z1_m - obj.z0_m) / 2
        centre = np.array([*obj.center_xy_m, (obj.z0_m + obj.z1_m) / 2])
        return centre, float(np.hypot(half_h, obj.radius_m))
    return np.asarray(obj.center_m), float(obj.radius_m)


def hits_sphere(origin, dirs, dirs_sq, centre, radius) -> np.ndarray:
    """Rays (not unit) that pass within ``radius`` of ``centre`` in front of the origin."""
    oc = centre - origin
    along = dirs @ oc
    dist_sq = oc @ oc - along * along / dirs_sq
    return (dist_sq <= radius * radius) & ((along > 0) | (oc @ oc <= radius * radius))


def object_from_dict(d: dict):
    kind = d["type"]
    texture = TextureSpec.from_dict(d["texture"])
    if kind == "box":
        return Box(tuple(d["center_m"]), tuple(d["half_m"]), float(d["yaw"]), texture)
    if kind == "cylinder":
        return Cylinder(tuple(d["center_xy_m"]), float(d["radius_m"]), float(d["z0_m"]),
                        float(d["z1_m"]), texture)
    if kind == "sphere":
        return Sphere(tuple(d["center_m"]), float(d["radius_m"]), texture)
    if kind == "poster":
        return Poster(int(d["wall"]), float(d["wall_m"]), tuple(d["centre_m"]), tuple(d["half_m"]), texture,
                      float(d["standoff_m"]))
    raise ValueError(f"unknown scene object type {kind!r}")


def _pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H*W, 3) each pixel's ray in the camera (OpenCV), unit z: a ray's parameter is its z-depth."""
    h, w = intrinsics.height, intrinsics.width
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([(u.ravel() - intrinsics.cx) / intrinsics.fx, (v.ravel() - intrinsics.cy) / intrinsics.fy,
                     np.ones(h * w)], axis=1)


class RayCastRenderer(abc.ABC):
    """RGB, z-depth and hit mask of anything that ray-casts (``cast(origin, dirs, shade)``) and
    has an ``ambient`` light level: one room (:class:`Scene`) or a floor of rooms
    (:class:`~nap3d_graph.sims.building.Building`)."""

    ambient: float

    @abc.abstractmethod
    def cast(self, origin: np.ndarray, dirs: np.ndarray, shade: bool = True):
        """``(t, points, normals, albedo)`` of rays ``origin + t * dirs`` (see :meth:`Scene.cast`)."""

    def render_depth(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """Noise-free z-depth (H, W) metres only (0 where nothing is hit): no shading, cheaper."""
        T_world_cam = np.asarray(T_world_cam, dtype=float)
        t = self.cast(T_world_cam[:3, 3], _pixel_rays(intrinsics) @ T_world_cam[:3, :3].T, shade=False)[0]
        return np.where(np.isfinite(t), t, 0.0).reshape(intrinsics.height, intrinsics.width)

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics):
        """Noise-free RGB (H, W, 3) float in [0, 1], z-depth (H, W) metres, hit mask (H, W).

        Camera: OpenCV frame, pixel centres at integer coordinates.
        """
        T_world_cam = np.asarray(T_world_cam, dtype=float)
        h, w = intrinsics.height, intrinsics.width
        rays_cam = _pixel_rays(intrinsics)
        # Direction with unit camera-z: the ray parameter t is the z-depth directly.
        dirs = rays_cam @ T_world_cam[:3, :3].T
        t, _, normal, albedo = self.cast(T_world_cam[:3, 3], dirs)
        unit_dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        # Two-sided Lambertian + ambient: view-independent, as a radiance field assumes.
        facing = np.abs(normal @ _LIGHT_DIR)
        shade = self.ambient + (1 - self.ambient) * facing
        # A little darkening at grazing view angles gives depth cues at object edges.
        shade *= 0.85 + 0.15 * np.abs(np.einsum("ij,ij->i", normal, unit_dirs))
        rgb = np.clip(albedo * shade[:, None], 0.0, 1.0)
        hit = np.isfinite(t)
        depth = np.where(hit, t, 0.0)
        return rgb.reshape(h, w, 3), depth.reshape(h, w), hit.reshape(h, w)



@dataclass(frozen=True)
class Scene(RayCastRenderer):
    """A furnished room and the free region where cameras may move.

    free_xy_m: ((x_min, x_max), (y_min, y_max)) of the floor area with no furniture.
    """

    room: Room
    objects: tuple = ()
    free_xy_m: tuple[tuple[float, float], tuple[float, float]] = ((1.0, 4.0), (1.0, 3.0))
    seed: int = 0
    ambient: float = 0.45

    def to_dict(self) -> dict:
        return {
            "version": SCENE_VERSION,
            "seed": self.seed,
            "ambient": self.ambient,
            "free_xy_m": [list(r) for r in self.free_xy_m],
            "room": self.room.to_dict(),
            "objects": [o.to_dict() for o in self.objects],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Scene":
        if int(d.get("version", -1)) != SCENE_VERSION:
            raise ValueError(f"scene description version {d.get('version')} != {SCENE_VERSION}")
        room = Room(tuple(d["room"]["size_m"]), tuple(TextureSpec.from_dict(t) for t in d["room"]["textures"]))
        return cls(
            room=room,
            objects=tuple(object_from_dict(o) for o in d["objects"]),
            free_xy_m=tuple(tuple(r) for r in d["free_xy_m"]),
            seed=int(d["seed"]),
            ambient=float(d["ambient"]),
        )

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned world bounds ``[min, max]`` of the room in metres."""
        return np.array([[0.0, 0.0, 0.0], list(self.room.size_m)])

    @classmethod
    def load(cls, path: str | Path) -> "Scene":
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: not a valid scene description ({exc})") from None

    # --- ray casting ---------------------------------------------------------------

    def cast(self, origin: np.ndarray, dirs: np.ndarray, shade: bool = True):
        """Cast rays ``origin + t * dirs`` (dirs (N, 3), not necessarily unit).

        Returns ``t`` (N,) in units of |dirs|, world hit points (N, 3), unit normals (N, 3)
        and the albedo (N, 3) of the surface hit (zeros unless ``shade``). Rays leaving the room
        get ``t = inf``.
        """
        origin = np.asarray(origin, dtype=float)
        t, normal, face = self.room.intersect(origin, dirs)
        owner = face  # 0..5 room faces; objects are 6 + index
        dirs_sq = np.einsum("ij,ij->i", dirs, dirs)
        for index, obj in enumerate(self.objects):
            # Cull with the bounding sphere first: most objects cover a small part of a view.
            cand = np.flatnonzero(hits_sphere(origin, dirs, dirs_sq, *bounding_sphere(obj)))
            if cand.size == 0:
                continue
            t_obj, n_obj = obj.intersect(origin, dirs[cand])
            closer = t_obj < t[cand]
            idx = cand[closer]
            t[idx] = t_obj[closer]
            normal[idx] = n_obj[closer]
            owner[idx] = 6 + index
        valid = np.isfinite(t)
        points = origin + np.where(valid, t, 0.0)[:, None] * dirs
        albedo = np.zeros_like(points)
        if not shade:
            return t, points, normal, albedo
        textures = list(self.room.textures) + [o.texture for o in self.objects]
        for owner_id in np.unique(owner[valid]):
            sel = valid & (owner == owner_id)
            obj = self.objects[owner_id - 6] if owner_id >= 6 else None
            # A poster's pattern is drawn in its own frame (the same picture wherever it hangs).
            local = obj.local_points(points[sel]) if isinstance(obj, Poster) else points[sel]
            albedo[sel] = shade_texture(textures[owner_id], local)
        return t, points, normal, albedo

    def inside_free_space(self, p_world: np.ndarray, margin_m: float = 0.3) -> bool:
        (x0, x1), (y0, y1) = self.free_xy_m
        x, y, z = np.asarray(p_world, dtype=float)
        return x0 <= x <= x1 and y0 <= y <= y1 and margin_m < z < self.room.size_m[2] - margin_m


class OracleField:
    """The simulated room as a radiance field: exact RGB, z-depth and opacity.

    Satisfies the field protocol ``render(T_world_cam, intrinsics) -> RenderedView``.
    """

    name = "oracle"

    def __init__(self, scene: Scene):
        self.scene = scene

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned world bounds ``[min, max]`` in metres."""
        return self.scene.bounds()

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        rgb, depth, hit = self.scene.render(T_world_cam, intrinsics.without_distortion())
        return RenderedView(
            rgb=np.round(rgb * 255).astype(np.uint8),
            depth_m=depth.astype(np.float32),
            opacity=hit.astype(np.float32),
            intrinsics=intrinsics,
        )


# --- procedural generation ---------------------------------------------------------------


def make_scene(seed: int = 0) -> Scene:
    """A furnished room, deterministic from ``seed``.

    Furniture stands in a band along the walls; the middle of the floor is kept free for
    camera paths (``scene.free_xy_m``).
    """
    rng = np.random.default_rng(seed)
    # Which surfaces are plain or finely textured comes from its own stream, so the layout and
    # palettes of a room do not depend on it.
    kinds = np.random.default_rng([seed, 17])

    def texture() -> TextureSpec:
        return TextureSpec.random(rng).as_kind(str(kinds.choice(["standard", "plain", "fine"], p=[0.55, 0.2, 0.25])))

    size = (float(rng.uniform(5.5, 7.0)), float(rng.uniform(4.5, 5.8)), float(rng.uniform(2.6, 3.0)))
    room = Room(size, tuple(texture() for _ in range(6)))
    band = 1.0  # furniture stands within this distance of the walls
    # Cameras keep half a metre from the furniture band, so no view is a close-up of one object.
    free = ((band + 0.5, size[0] - band - 0.5), (band + 0.5, size[1] - band - 0.5))
    objects = furnish(rng, size, texture, band)
    return Scene(room=room, objects=tuple(objects), free_xy_m=free, seed=seed)


def furnish(rng: np.random.Generator, size: tuple[float, float, float], texture, band: float = 1.0,
            blocked=None) -> list:
    """Boxes, cylinders and spheres standing in a ``band`` (metres) along the walls of a room of
    ``size`` (its own frame, floor corner at the origin), deterministic from ``rng``;
    ``texture()`` gives each its surface; ``blocked(x, y, radius)``: footprints it refuses (a
    doorway kept clear), None for none."""
    objects: list = []
    occupied: list[tuple[float, float, float]] = []  # (x, y, radius) footprints

    def place(radius: float) -> tuple[float, float] | None:
        for _ in range(200):
            wall = rng.integers(4)
            along = rng.uniform(radius + 0.1, (size[0] if wall < 2 else size[1]) - radius - 0.1)
            # The whole footprint stays inside the band along the wall.
            off = rng.uniform(radius + 0.05, max(band - radius, radius + 0.05))
            if wall == 0:
                x, y = along, off
            elif wall == 1:
                x, y = along, size[1] - off
            elif wall == 2:
                x, y = off, along
            else:
                x, y = size[0] - off, along
            if blocked is not None and blocked(x, y, radius):
                continue
            if all(np.hypot(x - ox, y - oy) > radius + orad + 0.05 for ox, oy, orad in occupied):
                occupied.append((x, y, radius))
                return x, y
        return None

    for _ in range(int(rng.integers(6, 10))):
        half = (rng.uniform(0.15, 0.32), rng.uniform(0.15, 0.32), rng.uniform(0.2, 0.9))
        xy = place(float(np.hypot(half[0], half[1])))
        if xy is not None:
            objects.append(Box((xy[0], xy[1], half[2]), half, float(rng.uniform(0, np.pi)), texture()))
    for _ in range(int(rng.integers(2, 5))):
        radius = float(rng.uniform(0.12, 0.35))
        xy = place(radius)
        if xy is not None:
            objects.append(Cylinder(xy, radius, 0.0, float(rng.uniform(0.5, 1.9)), texture()))
    for _ in range(int(rng.integers(1, 4))):
        radius = float(rng.uniform(0.15, 0.35))
        xy = place(radius)
        if xy is not None:
            z = radius + float(rng.uniform(0.0, 0.8))
            objects.append(Sphere((xy[0], xy[1], z), radius, texture()))
    return objects
