"""A map as a rerun recording (``map --viz map.rrd``; extra ``viz``: rerun-sdk).

Read from the finished map folder, all static (a map has no time):

- ``world/survey``: the survey's path at the map's poses;
- ``world/keyframes/SUBMAP``: the keyframes' positions, one colour per submap (one entity for
  a map of one field);
- ``world/loops/{accepted,admitted,rejected}``: each loop as a segment between its keyframes;
- ``world/mesh``: ``map.ply``, the survey fused at the map's poses, with its colours;
- ``map/report``: the map's ``report.md``.

The map's frame is the first camera's (OpenCV axes: y down), logged as such.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from nap3d_graph.fields.submaps import SUBMAPS_INDEX, Submap
from nap3d_graph.rerun_sdk import import_rerun
from nap3d_graph.trajectory import read_tum_trajectory

from .folder import MapFolder
from .mesh import import_open3d

__all__ = ["write_map_recording"]

log = logging.getLogger(__name__)

_LOOP_COLOURS = {"accepted": (0, 158, 115), "admitted": (86, 180, 233), "rejected": (213, 94, 0)}
_SUBMAP_COLOURS = [(0, 114, 178), (230, 159, 0), (0, 158, 115), (204, 121, 167), (213, 94, 0), (86, 180, 233),
                   (240, 228, 66), (90, 90, 90)]


def write_map_recording(map_dir, target: str) -> Path:
    """Log the map in ``map_dir`` to ``target`` (an ``.rrd`` path) and return it."""
    rr = import_rerun()
    folder = MapFolder.read(map_dir)
    stream = rr.RecordingStream("nap3d-graph-map", recording_id=None)
    stream.save(target)
    # The map's frame is its first camera's: x right, y down, z forward.
    stream.log("world", rr.ViewCoordinates.RDF, static=True)
    _, T_map_cam = read_tum_trajectory(folder.poses)
    stream.log("world/survey", rr.LineStrips3D([T_map_cam[:, :3, 3]], colors=[(120, 120, 120)], radii=0.005),
               static=True)
    T_map_key = np.load(folder.keyframe_poses)
    for name, positions, colour in _keyframe_groups(folder, T_map_cam, T_map_key):
        stream.log(f"world/keyframes/{name}", rr.Points3D(positions, colors=[colour], radii=0.02), static=True)
    for status, segments in _loops(folder, T_map_key).items():
        stream.log(f"world/loops/{status}", rr.LineStrips3D(segments, colors=[_LOOP_COLOURS[status]], radii=0.003),
                   static=True)
    if folder.mesh.is_file():
        _log_mesh(stream, rr, folder.mesh)
    if folder.report.is_file():
        stream.log("map/report", rr.TextDocument(folder.report.read_text(), media_type=rr.MediaType.MARKDOWN),
                   static=True)
    stream.flush()
    stream.disconnect()
    return Path(target)


def _keyframe_groups(folder: MapFolder, T_map_cam: np.ndarray, T_map_key: np.ndarray):
    """``(name, positions (P, 3), colour)`` per submap (by its core), or one group of all."""
    index = folder.root / SUBMAPS_INDEX
    if not index.is_file():
        yield "all", T_map_key[:, :3, 3], _SUBMAP_COLOURS[0]
        return
    submaps = [Submap.from_dict(d) for d in json.loads(index.read_text())["submaps"]]
    positions = T_map_key[:, :3, 3]
    owner = np.array([int(np.argmin([s.distance_m(p) for s in submaps])) for p in positions])
    for k, submap in enumerate(submaps):
        if np.any(owner == k):
            yield f"submap_{k:02d}", positions[owner == k], _SUBMAP_COLOURS[k % len(_SUBMAP_COLOURS)]


def _loops(folder: MapFolder, T_map_key: np.ndarray) -> dict[str, list]:
    """Segments (2, 3) between the keyframes of each loop the graph kept, admitted or rejected."""
    out: dict[str, list] = {}
    if not folder.loops_table.is_file():
        return out
    with open(folder.loops_table) as f:
        for row in csv.DictReader(f):
            if row["status"] in _LOOP_COLOURS:
                a, b = int(row["keyframe_a"]), int(row["keyframe_b"])
                out.setdefault(row["status"], []).append(np.stack([T_map_key[a, :3, 3], T_map_key[b, :3, 3]]))
    return out


def _log_mesh(stream, rr, path: Path) -> None:
    """``map.ply`` as a coloured triangle mesh (Open3D reads it; without Open3D it is left out)."""
    try:
        o3d = import_open3d()
    except ImportError as exc:
        log.warning("map.ply not in the recording: %s", exc)
        return
    mesh = o3d.io.read_triangle_mesh(str(path))
    colours = (np.asarray(mesh.vertex_colors) * 255).astype(np.uint8) if mesh.has_vertex_colors() else None
    stream.log("world/mesh", rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
                                       triangle_indices=np.asarray(mesh.triangles, dtype=np.uint32),
                                       vertex_colors=colours), static=True)
