"""A tf tree from a bag's ``/tf`` and ``/tf_static``: a frame's pose in another at any time.

Each edge ``parent -> child`` is a time series of ``T_parent_child``; an edge from
``/tf_static``, or one whose transform never changes, is constant. A lookup walks the tree
from the lowest common ancestor of the two frames and interpolates every moving edge at the
query times (linear in translation, SLERP in rotation, NaN outside the edge's samples or in
a gap longer than ``max(0.1 s, 2.5 x its median interval)``), as tf's own buffer does.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from nap3d_graph.conventions import inv_T
from nap3d_graph.errors import DatasetError

from ..trajectory import GT_MAX_GAP_S, interpolate_poses

__all__ = ["TfTree"]


def _strip(frame: str) -> str:
    """ROS 1 allowed a leading slash in frame ids ('/world'); tf2 does not: compare without."""
    return frame.lstrip("/")


class TfTree:
    """Transforms collected from tf messages; :meth:`lookup` gives ``T_target_source`` poses."""

    def __init__(self):
        self._samples: dict[tuple[str, str], list[tuple[float, np.ndarray]]] = defaultdict(list)
        self._static: dict[tuple[str, str], np.ndarray] = {}
        self._edges: dict[tuple[str, str], tuple[np.ndarray, np.ndarray] | np.ndarray] | None = None

    def add(self, t_s: float, parent: str, child: str, T_parent_child: np.ndarray, static: bool = False) -> None:
        """One transform (from ``/tf`` at ``t_s``, or ``/tf_static``)."""
        key = (_strip(parent), _strip(child))
        if static:
            self._static[key] = np.asarray(T_parent_child, dtype=float)
        else:
            self._samples[key].append((float(t_s), np.asarray(T_parent_child, dtype=float)))
        self._edges = None

    def __bool__(self) -> bool:
        return bool(self._samples or self._static)

    @property
    def frames(self) -> set[str]:
        return {f for key in (*self._samples, *self._static) for f in key}

    def _built(self) -> dict:
        """child -> (parent, constant T or (stamps, T series)), built once."""
        if self._edges is not None:
            return self._edges
        edges = {}
        for (parent, child), T in self._static.items():
            edges[child] = (parent, T)
        for (parent, child), samples in self._samples.items():
            samples.sort(key=lambda s: s[0])
            stamps = np.array([s[0] for s in samples])
            T = np.stack([s[1] for s in samples])
            if np.allclose(T, T[0], atol=1e-9):
                edges[child] = (parent, T[0])  # published on /tf but never moves: a mount
            else:
                edges[child] = (parent, (stamps, T))
        self._edges = edges
        return edges

    def parent(self, frame: str) -> str | None:
        entry = self._built().get(_strip(frame))
        return entry[0] if entry else None

    def ancestors(self, frame: str) -> list[str]:
        """The frame and its ancestors up to the root."""
        chain, frame = [_strip(frame)], _strip(frame)
        while (parent := self.parent(frame)) is not None:
            if parent in chain:
                raise DatasetError(f"the bag's tf tree has a cycle through {parent!r}")
            chain.append(parent)
            frame = parent
        return chain

    def root(self, frame: str) -> str:
        return self.ancestors(frame)[-1]

    def moving_stamps(self, target: str, source: str) -> np.ndarray:
        """The stamps of the most densely sampled moving edge between the two frames (empty
        when every edge on the way is constant)."""
        best = np.zeros(0)
        for child in self._path_children(target, source):
            value = self._built()[child][1]
            if isinstance(value, tuple) and len(value[0]) > len(best):
                best = value[0]
        return best

    def _common(self, target: str, source: str) -> tuple[list[str], list[str], str]:
        """Both frames' ancestor chains and their lowest common ancestor."""
        up_t, up_s = self.ancestors(target), self.ancestors(source)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            raise DatasetError(f"the bag's tf tree does not connect {target!r} and {source!r} (roots "
                               f"{up_t[-1]!r} and {up_s[-1]!r})")
        return up_t, up_s, common

    def _path_children(self, target: str, source: str) -> list[str]:
        up_t, up_s, common = self._common(target, source)
        return up_t[: up_t.index(common)] + up_s[: up_s.index(common)]

    def _to_ancestor(self, frame: str, ancestor: str, stamps: np.ndarray) -> np.ndarray:
        """(M, 4, 4) T_ancestor_frame at the stamps."""
        T = np.broadcast_to(np.eye(4), (len(stamps), 4, 4)).copy()
        for child in self.ancestors(frame):
            if child == ancestor:
                return T
            _, value = self._built()[child]
            T = self._edge_at(value, stamps) @ T
        raise DatasetError(f"{ancestor!r} is not above {frame!r} in the bag's tf tree")

    @staticmethod
    def _edge_at(value, stamps: np.ndarray) -> np.ndarray:
        if not isinstance(value, tuple):
            return np.broadcast_to(value, (len(stamps), 4, 4))
        edge_stamps, T = value
        gap = max(GT_MAX_GAP_S, 2.5 * float(np.median(np.diff(edge_stamps)))) if len(edge_stamps) > 1 else 0.0
        return interpolate_poses(edge_stamps, T, stamps, max_gap=gap)

    def lookup(self, target: str, source: str, stamps) -> np.ndarray:
        """(M, 4, 4) ``T_target_source`` (the source frame's pose in the target frame) at the
        stamps (M,) seconds; NaN where a moving edge has no sample near."""
        stamps = np.asarray(stamps, dtype=float).reshape(-1)
        _, _, common = self._common(target, source)

        T_common_target = self._to_ancestor(target, common, stamps)
        T_common_source = self._to_ancestor(source, common, stamps)
        return inv_T(T_common_target) @ T_common_source
