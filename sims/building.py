"""A floor of a building: furnished rooms in a row, joined by doors, some of them twins.

The rooms stand side by side along world +X, all ``size_y`` deep and ``size_z`` high (world
+Z up, metres, the first room's floor corner at the origin). Each shared wall has a door
(``door_width_m`` x ``door_height_m``, centred across the floor at ``door_y_m``) a camera
sees through into the next room; the end walls have none. Walls are thin: a room's face and
its neighbour's are the two sides of one plane.

Every room is built from a *design*: its length, its wall, floor and ceiling textures and its
furniture, all in the room's own frame. Rooms that share a design are twins, as the offices of
one floor are: the same desks and chairs in the same places, the same paint. Textures are
drawn in the room's own frame, so a twin looks the same from the same place in it; only what
is seen through its doors (and which of its walls has one) tells it from the other.
``twin_layout(n)`` gives the default floor: every third room is a twin of the one two before
it (``A B A``, ``A B A C D C``), so a walk through the middle of the floor passes a twin
between two different rooms.

:class:`Building` ray-casts as :class:`~nap3d_graph.sims.scene.Scene` does (and renders
through the same :class:`~nap3d_graph.sims.scene.RayCastRenderer`), so
:class:`~nap3d_graph.sims.scene.OracleField` and the sequence writer take either. A ray that
reaches a shared wall inside its door goes on into the next room.

Why hand-written: as for the single room (no maintained CPU ray-caster of textured analytic
scenes with exact z-depth); a floor is rooms and doorways on top of it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .scene import (
    SCENE_VERSION,
    Box,
    RayCastRenderer,
    Room,
    bounding_sphere,
    furnish,
    hits_sphere,
    object_from_dict,
)
from .textures import TextureSpec, shade_texture

__all__ = ["RoomDesign", "Building", "make_building", "twin_layout"]

#: Faces per room, in :class:`~nap3d_graph.sims.scene.Room`'s order (-x, +x, -y, +y, floor, ceiling).
_FACES = 6
#: A surface's owner id: ``room * _OWNERS + k``, k < 6 a face of the room, else its object k - 6.
_OWNERS = 1000


@dataclass(frozen=True)
class RoomDesign:
    """A furnished room in its own frame (floor corner at the origin): ``size_m`` (3,),
    ``textures`` one per face, ``objects`` (boxes, cylinders, spheres) in that frame."""

    size_m: tuple[float, float, float]
    textures: tuple[TextureSpec, ...]
    objects: tuple = ()
    seed: int = 0

    def to_dict(self) -> dict:
        return {"size_m": list(self.size_m), "textures": [t.to_dict() for t in self.textures],
                "objects": [o.to_dict() for o in self.objects], "seed": self.seed}

    @classmethod
    def from_dict(cls, d: dict) -> "RoomDesign":
        return cls(tuple(float(v) for v in d["size_m"]), tuple(TextureSpec.from_dict(t) for t in d["textures"]),
                   tuple(object_from_dict(o) for o in d["objects"]), int(d["seed"]))


def twin_layout(rooms: int) -> tuple[int, ...]:
    """Which design each of ``rooms`` rooms in a row uses: every third room is a twin of the
    one two before it (3 rooms: 0 1 0; 6 rooms: 0 1 0 3 4 3)."""
    if rooms < 1:
        raise ValueError(f"a floor needs at least one room, got {rooms}")
    return tuple(i - 2 if i % 3 == 2 else i for i in range(rooms))


class Building(RayCastRenderer):
    """Rooms in a row along +X, joined by doors (see the module's text).

    designs: the room designs; layout: the design of each room, first to last; door_y_m,
    door_width_m, door_height_m: where the doors in the shared walls are and their size.
    """

    def __init__(self, designs: tuple[RoomDesign, ...], layout: tuple[int, ...], door_y_m: float,
                 door_width_m: float = 1.0, door_height_m: float = 2.1, seed: int = 0, ambient: float = 0.45):
        if not layout:
            raise ValueError("a building needs at least one room")
        if any(not 0 <= d < len(designs) for d in layout):
            raise ValueError(f"layout {layout} names a design that is not among the {len(designs)} given")
        depths = {(d.size_m[1], d.size_m[2]) for d in designs}
        if len(depths) != 1:
            raise ValueError("every room of a floor must have one depth and height (the doors line up)")
        self.designs, self.layout = tuple(designs), tuple(int(d) for d in layout)
        self.door_y_m, self.door_width_m, self.door_height_m = float(door_y_m), float(door_width_m), float(door_height_m)
        self.seed, self.ambient = int(seed), float(ambient)
        self.size_y, self.size_z = designs[0].size_m[1], designs[0].size_m[2]
        lengths = [designs[d].size_m[0] for d in self.layout]
        #: (n + 1,) world x of the end walls and shared walls, first to last.
        self.walls_x = np.concatenate([[0.0], np.cumsum(lengths)])

    # --- the floor -----------------------------------------------------------------------------

    @property
    def rooms(self) -> int:
        return len(self.layout)

    def room_design(self, r: int) -> RoomDesign:
        return self.designs[self.layout[r]]

    def origin(self, r: int) -> np.ndarray:
        """(3,) world position of room ``r``'s floor corner (its own frame's origin)."""
        return np.array([self.walls_x[r], 0.0, 0.0])

    def room_of(self, p_world) -> int:
        """The room whose floor area holds ``p_world`` (3,) (the nearer one on a shared wall)."""
        x = float(np.asarray(p_world, dtype=float)[0])
        return int(np.clip(np.searchsorted(self.walls_x, x, side="right") - 1, 0, self.rooms - 1))

    def twins(self, r: int) -> list[int]:
        """The other rooms of ``r``'s design."""
        return [q for q in range(self.rooms) if q != r and self.layout[q] == self.layout[r]]

    def has_door(self, r: int, side: int) -> bool:
        """Whether room ``r``'s -x (``side`` -1) or +x (+1) wall has a door."""
        return 0 <= r + side < self.rooms

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned world bounds ``[min, max]`` of the floor in metres."""
        return np.array([[0.0, 0.0, 0.0], [float(self.walls_x[-1]), self.size_y, self.size_z]])

    # --- ray casting ---------------------------------------------------------------------------

    def _in_door(self, points: np.ndarray) -> np.ndarray:
        return (np.abs(points[:, 1] - self.door_y_m) < self.door_width_m / 2) & (points[:, 2] < self.door_height_m)

    def _walls(self, origin: np.ndarray, dirs: np.ndarray) -> tuple:
        """Each ray followed through the doors to the wall it stops at: ``t`` (N,), normals
        (N, 3), owner (N,) ``room * _OWNERS + face``, and for each room the rays that crossed it."""
        n = len(dirs)
        t, normal, owner = np.full(n, np.inf), np.zeros((n, 3)), np.zeros(n, dtype=int)
        crossed: list[list[np.ndarray]] = [[] for _ in range(self.rooms)]
        active, room = np.arange(n), np.full(n, self.room_of(origin))
        while active.size:
            passing = []
            for r in np.unique(room[active]):
                sel = active[room[active] == r]
                crossed[r].append(sel)
                size = np.asarray(self.room_design(r).size_m)
                local = origin - self.origin(r)
                with np.errstate(divide="ignore", invalid="ignore"):
                    # Each slab's far side along the ray: the ray starts inside the slab in y and z
                    # and inside or before it in x (it came through a door).
                    t_axis = np.where(dirs[sel] > 0, (size - local) / dirs[sel], -local / dirs[sel])
                t_axis = np.where(np.abs(dirs[sel]) < 1e-12, np.inf, t_axis)
                axis = np.argmin(t_axis, axis=1)
                t_hit = t_axis[np.arange(len(sel)), axis]
                positive = dirs[sel, axis] > 0
                face = axis * 2 + positive.astype(int)
                side = np.where(positive, 1, -1)
                door = ((axis == 0) & (0 <= r + side) & (r + side < self.rooms)
                        & self._in_door(origin + t_hit[:, None] * dirs[sel]))
                stop = ~door
                t[sel[stop]] = t_hit[stop]
                normal[sel[stop], axis[stop]] = np.where(positive[stop], -1.0, 1.0)
                owner[sel[stop]] = r * _OWNERS + face[stop]
                room[sel[door]] = r + side[door]
                passing.append(sel[door])
            active = np.concatenate(passing) if passing else np.arange(0)
        return t, normal, owner, [np.concatenate(c) if c else np.arange(0) for c in crossed]

    def cast(self, origin: np.ndarray, dirs: np.ndarray, shade: bool = True):
        """As :meth:`~nap3d_graph.sims.scene.Scene.cast`: ``t`` (N,) in units of |dirs|, world
        hit points (N, 3), unit normals (N, 3), albedo (N, 3) (zeros unless ``shade``)."""
        origin = np.asarray(origin, dtype=float)
        t, normal, owner, crossed = self._walls(origin, dirs)
        dirs_sq = np.einsum("ij,ij->i", dirs, dirs)
        for r, rays in enumerate(crossed):
            if rays.size == 0:
                continue
            local = origin - self.origin(r)
            for index, obj in enumerate(self.room_design(r).objects):
                # Only the rays that crossed this room can meet its furniture; cull by the bounding sphere.
                cand = rays[hits_sphere(local, dirs[rays], dirs_sq[rays], *bounding_sphere(obj))]
                if cand.size == 0:
                    continue
                t_obj, n_obj = obj.intersect(local, dirs[cand])
                closer = t_obj < t[cand]
                idx = cand[closer]
                t[idx], normal[idx], owner[idx] = t_obj[closer], n_obj[closer], r * _OWNERS + _FACES + index
        valid = np.isfinite(t)
        points = origin + np.where(valid, t, 0.0)[:, None] * dirs
        albedo = np.zeros_like(points)
        if shade:
            for owner_id in np.unique(owner[valid]):
                sel = valid & (owner == owner_id)
                r, k = divmod(int(owner_id), _OWNERS)
                # Drawn in the room's own frame: a twin's surfaces look the same from the same place in it.
                albedo[sel] = shade_texture(self._texture(r, k), points[sel] - self.origin(r))
        return t, points, normal, albedo

    def _texture(self, r: int, k: int) -> TextureSpec:
        """Room ``r``'s face ``k`` (k < 6) or its object ``k - 6``."""
        design = self.room_design(r)
        return design.textures[k] if k < _FACES else design.objects[k - _FACES].texture

    # --- description ---------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {"kind": "building", "version": SCENE_VERSION, "seed": self.seed, "ambient": self.ambient,
                "layout": list(self.layout), "door_y_m": self.door_y_m, "door_width_m": self.door_width_m,
                "door_height_m": self.door_height_m, "designs": [d.to_dict() for d in self.designs]}

    @classmethod
    def from_dict(cls, d: dict) -> "Building":
        if int(d.get("version", -1)) != SCENE_VERSION:
            raise ValueError(f"scene description version {d.get('version')} != {SCENE_VERSION}")
        return cls(tuple(RoomDesign.from_dict(x) for x in d["designs"]), tuple(d["layout"]), float(d["door_y_m"]),
                   float(d["door_width_m"]), float(d["door_height_m"]), int(d["seed"]), float(d["ambient"]))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))


def _design(seed: int, size_y: float, size_z: float, door_y_m: float, clear_m: float) -> RoomDesign:
    """A room design from ``seed``: its length, textures and furniture, the doorways of both
    end walls kept clear (``clear_m`` either side of ``door_y_m``), so any room can use it."""
    rng = np.random.default_rng([seed, 2024])
    kinds = np.random.default_rng([seed, 17])

    def texture() -> TextureSpec:
        return TextureSpec.random(rng).as_kind(str(kinds.choice(["standard", "plain", "fine"], p=[0.55, 0.2, 0.25])))

    size = (float(rng.uniform(5.0, 6.5)), size_y, size_z)
    textures = tuple(texture() for _ in range(_FACES))
    Room(size, textures)  # the same checks as a single room's

    def blocked(x: float, y: float, radius: float) -> bool:
        # The end walls' doorways (x = 0 and x = size_x) and the walk through them stay free.
        return abs(y - door_y_m) < clear_m + radius and (x < 1.2 + radius or x > size[0] - 1.2 - radius)

    objects = furnish(rng, size, texture, 1.0, blocked)
    return RoomDesign(size, textures, tuple(objects + _wall_items(seed, size, door_y_m, clear_m)), seed)


def _wall_items(seed: int, size: tuple[float, float, float], door_y_m: float, clear_m: float) -> list:
    """What hangs on an office's walls (pictures, pinboards, whiteboards): two or three panels a
    wall, 2 cm thick, between 0.8 and 2.2 m high, none across an end wall's doorway. A painted
    wall alone is a plane of one colour (nothing to track); a real room's walls rarely are.
    From a stream of their own, so a design's paint and furniture stay what they were."""
    rng = np.random.default_rng([seed, 31])
    items: list = []
    for wall in range(4):  # -y, +y (the long side walls), then the end walls -x, +x
        length = size[0] if wall < 2 else size[1]
        spans: list[tuple[float, float]] = []
        for _ in range(int(rng.integers(2, 4))):
            width, height = float(rng.uniform(0.5, 1.4)), float(rng.uniform(0.4, 1.0))
            for _ in range(50):
                along = float(rng.uniform(width / 2 + 0.2, length - width / 2 - 0.2))
                lo, hi = along - width / 2, along + width / 2
                in_door = wall >= 2 and hi > door_y_m - clear_m and lo < door_y_m + clear_m
                if not in_door and all(hi + 0.1 < a or lo - 0.1 > b for a, b in spans):
                    spans.append((lo, hi))
                    break
            else:
                continue
            z = float(rng.uniform(0.8 + height / 2, min(2.2, size[2] - 0.2) - height / 2))
            texture = TextureSpec.random(rng).as_kind("standard")
            if wall < 2:
                centre, half = (along, 0.01 if wall == 0 else size[1] - 0.01, z), (width / 2, 0.01, height / 2)
            else:
                centre, half = (0.01 if wall == 2 else size[0] - 0.01, along, z), (0.01, width / 2, height / 2)
            items.append(Box(centre, half, 0.0, texture))
    return items


def make_building(rooms: int = 3, seed: int = 0, layout: tuple[int, ...] | None = None) -> Building:
    """A floor of ``rooms`` rooms in a row, deterministic from ``seed``; ``layout``: which
    design each room uses (default :func:`twin_layout`: every third room a twin)."""
    layout = twin_layout(rooms) if layout is None else tuple(layout)
    if len(layout) != rooms:
        raise ValueError(f"layout {layout} has {len(layout)} rooms, not {rooms}")
    rng = np.random.default_rng([seed, 1])
    size_y, size_z = float(rng.uniform(4.6, 5.4)), float(rng.uniform(2.7, 2.9))
    door_y = size_y / 2
    designs = tuple(_design(seed * 100 + d, size_y, size_z, door_y, 0.9) for d in range(max(layout) + 1))
    return Building(designs, layout, door_y, seed=seed)
