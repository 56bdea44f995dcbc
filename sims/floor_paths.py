"""Camera paths across a floor of rooms (:class:`~nap3d_graph.sims.building.Building`).

* ``survey``: the floor mapped room by room, as a user walks it with a camera: in each room
  one and a half loops round its free middle, looking outward at the walls and furniture with a
  sweeping yaw and rising and falling between two heights, then straight through the door into
  the next room, looking ahead. It comes back to places within a room (loops a map can close)
  but never to an earlier room.
* ``traverse``: a walk through the middle of the rooms from ``start_room`` to ``end_room``
  (either way along the row), through every door between, never coming back; it looks ahead,
  10 deg down, with a gentle yaw sweep. ``look_aside_deg``: it starts looking this far to its left at the
  side wall and turns ahead over the first metre, so a start in a twin room first sees only
  what the twin has too.

Each path is sampled densely along its arc length, its corners smoothed (a Gaussian over
``_SMOOTH_M`` of path), and interpolated by cubic splines, so position and angles have smooth
first and second derivatives (the IMU simulator differentiates them). The camera moves at a
constant walking pace along the path, starting and stopping over ``_EASE_S``.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d

from .building import Building
from .trajectories import Trajectory, smooth_noise

__all__ = ["floor_survey", "floor_traverse"]

_STEP_M = 0.02  # path sampling
_SMOOTH_M = 0.35  # corners rounded over about this much path
_MARGIN_M = 1.5  # the free middle of a room keeps this far from its walls
_EASE_S = 1.5  # a walker starts and stops over this long


def _timed(samples: np.ndarray, duration_s: float, kind: str) -> Trajectory:
    """A trajectory through ``samples`` (M, 6): x, y, z, yaw, pitch, roll along the path at
    ``_STEP_M`` spacing, smoothed, at a constant walking pace between a start and a stop of
    ``_EASE_S`` each (a quarter of ``duration_s`` at most)."""
    sigma = _SMOOTH_M / _STEP_M
    smooth = gaussian_filter1d(samples, sigma, axis=0, mode="nearest")
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(smooth[:, :3], axis=0), axis=1))])
    keep = np.concatenate([[True], np.diff(arc) > 1e-9])
    spline = CubicSpline(arc[keep], smooth[keep], axis=0)
    s_of = _walking_pace(float(arc[-1]), float(duration_s))
    return Trajectory(lambda t: spline(s_of(t))[:3], lambda t: tuple(float(a) for a in spline(s_of(t))[3:]),
                      float(duration_s), kind)


def _walking_pace(length_m: float, duration_s: float):
    """``s_of(t)``: the distance along a path of ``length_m`` walked at time ``t`` (s) of
    ``duration_s``. The pace is constant but for a start and a stop of ``_EASE_S`` (speed
    ``(1 - cos)/2`` up and down, so velocity and acceleration are zero at both ends): a walker,
    not a sweep that is slowest at its ends and fastest in its middle (an easing over the whole
    duration surveyed a 6-room floor's middle rooms at twice its end rooms' pace, a third of
    their frames)."""
    ease = min(_EASE_S, duration_s / 4)
    speed = length_m / (duration_s - ease)  # each ramp covers half its time at full speed

    def ramp(t: float) -> float:  # the distance covered in the first t (<= ease) seconds
        return speed * (t / 2 - ease / (2 * np.pi) * np.sin(np.pi * t / ease))

    def s_of(t: float) -> float:
        t = float(np.clip(t, 0.0, duration_s))
        if t < ease:
            return ramp(t)
        if t > duration_s - ease:
            return length_m - ramp(duration_s - t)
        return speed * (t - ease / 2)

    return s_of


def _line(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, 3) points from ``a`` to ``b`` at the sampling step (``b`` excluded)."""
    n = max(int(np.ceil(np.linalg.norm(b - a) / _STEP_M)), 1)
    return a + (b - a) * (np.arange(n) / n)[:, None]


def floor_survey(building: Building, rng: np.random.Generator, duration_s: float) -> Trajectory:
    """The room-by-room survey of the module's text, first room to last, in ``duration_s``."""
    sweep = smooth_noise(rng)
    parts = []
    for r in range(building.rooms):
        size_x = building.room_design(r).size_m[0]
        centre = building.origin(r)[:2] + np.array([size_x / 2, building.door_y_m])
        rx = 0.45 * (size_x - 2 * _MARGIN_M)
        ry = 0.45 * (building.size_y - 2 * _MARGIN_M)
        heights = (float(rng.uniform(1.0, 1.2)), float(rng.uniform(1.5, 1.7)))
        # 1.5 loops from the side it entered by (-x) to the side it leaves by (+x).
        n = int(np.ceil(1.5 * 2 * np.pi * np.hypot(rx, ry) / np.sqrt(2) / _STEP_M))
        a = np.pi + np.linspace(0.0, 3 * np.pi, n, endpoint=False)
        u = np.linspace(0.0, 1.0, n)
        loop = np.column_stack([centre[0] + rx * np.cos(a), centre[1] + ry * np.sin(a),
                                heights[0] + (heights[1] - heights[0]) * 0.5 * (1 - np.cos(2 * np.pi * u)),
                                # Outward, swinging +-80 deg; down 2 to 34 deg (positive pitch is down)
                                # so the floor and the furniture are seen, not the blank upper walls.
                                a + np.radians(80.0) * np.array([sweep(3.0 * v) for v in a]),
                                np.radians(18.0) + np.radians(16.0) * np.sin(1.7 * a), np.zeros(n)])
        parts.append(loop)
        if r + 1 < building.rooms:  # through the door into the next room, looking ahead
            nxt = building.room_design(r + 1).size_m[0]
            start = np.array([centre[0] + rx, centre[1], 1.35])
            end = np.array([building.walls_x[r + 1] + nxt / 2 - 0.45 * (nxt - 2 * _MARGIN_M), centre[1], 1.35])
            line = _line(start, end)
            yaw_end = loop[-1, 3]
            # Ahead (+x) on the branch of the angle nearest to where the loop left it.
            ahead = 2 * np.pi * np.round(yaw_end / (2 * np.pi))
            parts.append(np.column_stack([line, np.full(len(line), ahead), np.full(len(line), np.radians(8.0)),
                                          np.zeros(len(line))]))
    samples = np.concatenate(parts)
    samples[:, 3] = np.unwrap(samples[:, 3])
    return _timed(samples, duration_s, "mapping")


def floor_traverse(building: Building, rng: np.random.Generator, duration_s: float, start_room: int = 0,
                   end_room: int | None = None, look_aside_deg: float = 0.0) -> Trajectory:
    """The walk of the module's text from ``start_room`` to ``end_room`` (default the last
    room; the first when it starts in the last) in ``duration_s``."""
    n = building.rooms
    if end_room is None:
        end_room = n - 1 if start_room != n - 1 or n == 1 else 0
    for r in (start_room, end_room):
        if not 0 <= r < n:
            raise ValueError(f"room {r} is not on this floor of {n} room(s)")
    step = 1 if end_room >= start_room else -1
    rooms = list(range(start_room, end_room + step, step))
    x_start = building.origin(start_room)[0] + (1.2 if step > 0 else building.room_design(start_room).size_m[0] - 1.2)
    x_end = building.origin(end_room)[0] + (building.room_design(end_room).size_m[0] - 1.2 if step > 0 else 1.2)
    xs = np.arange(x_start, x_end, step * _STEP_M)
    # Within each room a sideways bump that is zero at its walls: the walk meets every door square.
    amplitude = {r: float(rng.uniform(-0.45, 0.45)) for r in rooms}
    room_of = np.array([building.room_of([x, 0.0, 0.0]) for x in xs])
    x0 = building.walls_x[room_of]
    lengths = building.walls_x[room_of + 1] - x0
    y = building.door_y_m + np.array([amplitude.get(r, 0.0) for r in room_of]) * np.sin(np.pi * (xs - x0) / lengths)
    travelled = np.abs(xs - x_start)
    yaw_sweep, bob = smooth_noise(rng), smooth_noise(rng)
    heading = 0.0 if step > 0 else np.pi
    aside = np.radians(look_aside_deg) * np.clip(1.0 - travelled / 1.0, 0.0, 1.0) ** 2
    height = float(rng.uniform(1.2, 1.5))
    samples = np.column_stack([xs, y, height + 0.05 * np.array([bob(s) for s in travelled]),
                               heading + aside + np.radians(30.0) * np.array([yaw_sweep(0.8 * s) for s in travelled]),
                               # 10 deg down (positive pitch is down), as a hand-held or robot camera is
                               # held to see the floor ahead, bobbing 6 deg.
                               np.radians(10.0) + np.radians(6.0) * np.array([bob(0.9 * s + 1.0) for s in travelled]),
                               np.radians(3.0) * np.array([bob(0.5 * s + 2.0) for s in travelled])])
    return _timed(samples, duration_s, "traverse")
