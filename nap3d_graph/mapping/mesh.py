"""A map to look at: a coloured mesh fused at the map's poses, and how thick its walls are.

``map.ply`` is the survey's depth fused by TSDF integration at the map's poses (Open3D's
``VoxelBlockGrid``, a sparse voxel hash that grows with the surfaces seen, not with the floor's
bounding box; an optional extra, ``pip install 'nap3d-graph[mesh]'``), a triangle mesh with
vertex colours that MeshLab, CloudCompare, Blender and rerun open. (Open3D 0.20's legacy
``ScalableTSDFVolume`` extracts nothing on this project's CPU build: checked, not used.)

A survey that is wrong shows as doubled surfaces: a wall seen from one part of the survey sits
a few centimetres from where another part saw it. The wall thickness measures that without
ground truth: the largest planes of the fused cloud (walls, floor, large furniture faces) are
found by RANSAC, each is cut into 10 cm cells, and every frame that sees enough of a cell
gives the median signed distance of its points there. Two frames that see the same cells are
compared there only: the median of their differences over the shared cells is how far apart
they put the surface (within a frame the sensor's noise averages out; comparing cell by cell,
what part of a not quite flat surface each frame sees does not enter, which moved whole-frame
medians by several centimetres on fr1/desk at its ground-truth poses). The 90th percentile of
those pairwise distances is the plane's thickness: a few millimetres on a consistent map, the
doubling itself on a bent one (a part of the survey seen by one frame in twenty is enough).

Why Open3D: TSDF integration, marching cubes and plane RANSAC are well kept there; writing
them again here would only add bugs. The distance bookkeeping is the method's own.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import inv_T
from nap3d_graph.progress import progress_bar

__all__ = ["MeshSettings", "MeshResult", "fuse_mesh", "wall_thickness", "surface_points", "import_open3d",
           "WALL_THICKNESS_BAD_M"]

log = logging.getLogger(__name__)

#: Walls thicker than this (metres, the worst of the largest planes): the survey put the same surface
#: in two places (a doubled wall).
WALL_THICKNESS_BAD_M = 0.03


def import_open3d():
    """Open3D, or ``ImportError`` with the install line."""
    try:
        import open3d
    except ImportError as exc:
        raise ImportError(f"the map's mesh needs Open3D ({exc}): pip install 'nap3d-graph[mesh]'") from None
    return open3d


@dataclass(frozen=True)
class MeshSettings:
    """voxel_m: the TSDF's voxel (its truncation 4 voxels; 3 cm: a floor to look at, ~10 KB per
    20 cm block of surface); max_depth_m: depth beyond this is not fused (a structured-light
    sensor's far depth is its noisiest); every: fuse every so many frames; min_weight: a surface
    is kept where at least this many fused frames saw it; planes: the largest planes the wall
    thickness looks at; plane_inlier_m: a point within this of a plane belongs to it;
    min_points: a frame that sees fewer of a plane's points gives it nothing; cell_m: the side of
    the cells a plane is cut into; cell_points: a frame's cell with fewer points gives no median;
    shared_cells: two frames are compared where they share at least this many cells; columns:
    the thickness back-projects about so many columns of each frame (every ``width // columns``-th
    pixel), so a cell holds as many points at 160 pixels across as at 640."""

    voxel_m: float = 0.03
    max_depth_m: float = 4.0
    every: int = 2
    min_weight: float = 2.0
    planes: int = 6
    plane_inlier_m: float = 0.06
    min_points: int = 150
    cell_m: float = 0.10
    cell_points: int = 8
    shared_cells: int = 5
    columns: int = 160


@dataclass
class MeshResult:
    """``vertices`` / ``triangles`` of the written mesh, ``frames`` fused, and the wall thickness
    (:func:`wall_thickness`'s dict)."""

    path: Path
    vertices: int
    triangles: int
    frames: int
    thickness: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"file": self.path.name, "vertices": self.vertices, "triangles": self.triangles, "frames": self.frames,
                "wall_thickness": self.thickness}


def _posed_frames(T_map_cam: np.ndarray, every: int) -> list[int]:
    """Frames with a finite pose, every ``every``-th."""
    ok = np.flatnonzero(np.all(np.isfinite(np.asarray(T_map_cam).reshape(len(T_map_cam), -1)), axis=1))
    return [int(i) for i in ok[::max(int(every), 1)]]


def _depth_poses(posed, frames: list[int], timing) -> np.ndarray:
    """(F, 4, 4) where the camera was when each frame's depth was captured: the posed sequence's
    pose at its depth stamp moved by the capture timing (``depth_offset_s``), as the field is
    built; at the colour's pose without a timing."""
    T = np.asarray(posed.T_world_cam_gt, dtype=float)[frames]
    if timing is None or not hasattr(posed, "ground_truth_at") or getattr(posed, "depth_timestamps", None) is None:
        return T
    T_depth = np.asarray(posed.ground_truth_at(np.asarray(posed.depth_timestamps)[frames] + timing.depth_offset_s))
    ok = np.all(np.isfinite(T_depth.reshape(len(frames), -1)), axis=1)
    return np.where(ok[:, None, None], T_depth, T)


def fuse_mesh(posed, out: Path, settings: MeshSettings | None = None, timing=None,
              progress: bool = False, submaps: list | None = None) -> MeshResult:
    """Fuse the depth and colour of ``posed`` (a sequence whose ``T_world_cam_gt`` (N, 4, 4) are
    the map's poses, NaN where a frame has none: a :class:`~nap3d_graph.datasets.posed.PosedSequence`)
    into a coloured triangle mesh written to ``out`` (``.ply``), each depth at its capture instant
    by ``timing`` (a :class:`~nap3d_graph.datasets.depth_timing.CaptureTiming`, or None: at the
    colour's pose); its wall thickness measured on the same frames. ``submaps``: the map's
    :class:`~nap3d_graph.fields.submaps.Submap` list; with more than one, each is fused from its
    own frames alone and keeps the triangles in its core (the voxel grid of one room at a time,
    not of the floor: 0.7 GB for the 6-room floor's, 0.4 for a room's). ``ImportError`` without
    Open3D."""
    o3d = import_open3d()

    s = settings or MeshSettings()
    frames = _posed_frames(np.asarray(posed.T_world_cam_gt), s.every)
    if not frames:
        raise ValueError("no frame of the survey has a pose: nothing to fuse")
    T_map_depth = dict(zip(frames, _depth_poses(posed, frames, timing)))
    parts = [(frames, None)]
    if submaps is not None and len(submaps) > 1:
        parts = [(np.asarray(frames)[np.isin(frames, sm.frames)].tolist(), sm) for sm in submaps]
    mesh, clouds = o3d.geometry.TriangleMesh(), {}
    with progress_bar(total=sum(len(f) for f, _ in parts), desc="mesh", unit="frame", disable=not progress,
                      mininterval=2.0) as bar:
        for part_frames, submap in parts:
            part = _fuse(o3d, posed, part_frames, T_map_depth, s, clouds, bar)
            mesh += part if submap is None else _in_core(part, submap)
    if len(mesh.vertices) == 0:
        raise ValueError("the fused survey has no surface seen by enough frames: no mesh")
    mesh.compute_vertex_normals()
    out = Path(out)
    tmp = out.with_name(out.stem + ".tmp.ply")
    if not o3d.io.write_triangle_mesh(str(tmp), mesh):
        raise OSError(f"could not write {tmp}")
    tmp.replace(out)
    thickness = wall_thickness([clouds[i] for i in sorted(clouds)], s)
    log.info("mesh: %d frames fused into %d vertices (%s)", len(frames), len(mesh.vertices), out)
    return MeshResult(out, len(mesh.vertices), len(mesh.triangles), len(frames), thickness)


def _fuse(o3d, posed, frames: list[int], T_map_depth: dict, s: MeshSettings, clouds: dict, bar):
    """The legacy triangle mesh of ``frames`` of ``posed`` fused at ``T_map_depth[i]`` (4, 4);
    each frame's surface points (float32: the thickness needs millimetres, not more) added to
    ``clouds`` the first time it is read."""
    o3c = o3d.core
    grid = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                         attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
                                         attr_channels=((1), (1), (3)), voxel_size=s.voxel_m, block_resolution=8,
                                         block_count=20000, device=o3c.Device("CPU:0"))
    for i in frames:
        frame, T_map_cam = posed[i], T_map_depth[i]
        K = frame.intrinsics
        depth_m = np.nan_to_num(np.asarray(frame.depth_m, dtype=np.float32), nan=0.0)
        # The voxel grid takes depth as uint16 (here millimetres) with uint8 colour.
        depth_mm = o3d.t.geometry.Image(o3c.Tensor(np.rint(np.clip(depth_m, 0, 65.0) * 1000).astype(np.uint16)))
        colour = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(frame.rgb)))
        intrinsic = o3c.Tensor(np.array([[K.fx, 0, K.cx], [0, K.fy, K.cy], [0, 0, 1]]), o3c.float64)
        # Open3D's extrinsic maps world to camera (OpenCV axes, as ours).
        extrinsic = o3c.Tensor(inv_T(T_map_cam), o3c.float64)
        blocks = grid.compute_unique_block_coordinates(depth_mm, intrinsic, extrinsic, 1000.0, s.max_depth_m)
        grid.integrate(blocks, depth_mm, colour, intrinsic, intrinsic, extrinsic, 1000.0, s.max_depth_m)
        if i not in clouds:
            clouds[i] = surface_points(depth_m, K, T_map_cam, max(1, K.width // s.columns),
                                       s.max_depth_m).astype(np.float32)
        bar.update(1)
    return grid.extract_triangle_mesh(weight_threshold=s.min_weight).to_legacy()


def _in_core(mesh, submap):
    """``mesh`` (legacy) without the triangles whose centre lies outside ``submap``'s core (metres
    along its axis, the map's frame): neighbouring submaps' meshes meet there without overlapping."""
    triangles = np.asarray(mesh.triangles)
    if len(triangles) == 0:
        return mesh
    along = np.asarray(mesh.vertices)[triangles].mean(axis=1) @ np.asarray(submap.axis, dtype=float)
    mesh.remove_triangles_by_mask((along < submap.core[0]) | (along >= submap.core[1]))
    mesh.remove_unreferenced_vertices()
    return mesh


def surface_points(depth_m: np.ndarray, intrinsics, T_map_cam: np.ndarray, stride: int = 4,
                   max_depth_m: float = 4.0) -> np.ndarray:
    """(P, 3) points of one depth image (H, W, metres; 0 or NaN missing) in the map's frame,
    every ``stride``-th pixel, nearer than ``max_depth_m``."""
    K = intrinsics
    depth = np.asarray(depth_m, dtype=float)[::stride, ::stride]
    v, u = np.mgrid[0:K.height:stride, 0:K.width:stride]
    ok = np.isfinite(depth) & (depth > 0) & (depth < max_depth_m)
    z = depth[ok]
    p_cam = np.stack([(u[ok] - K.cx) / K.fx * z, (v[ok] - K.cy) / K.fy * z, z], axis=1)
    T = np.asarray(T_map_cam, dtype=float)
    return p_cam @ T[:3, :3].T + T[:3, 3]


def wall_thickness(clouds: list[np.ndarray], settings: MeshSettings | None = None, seed: int = 0) -> dict:
    """How thick the largest planes are (see the module's text) from per-frame point sets
    ``clouds`` (each (P, 3), the map's frame): per plane its normal, the frames that saw it and
    the 90th percentile of the distances between frames that see the same cells of it (metres);
    ``thickness_m`` the largest, ``reason`` when none could be measured."""
    o3d = import_open3d()
    s = settings or MeshSettings()
    usable = [c for c in clouds if len(c)]
    if len(usable) < 5:
        return {"thickness_m": None, "planes": [], "reason": "fewer than 5 frames with depth"}
    everything = np.concatenate(usable)
    rng = np.random.default_rng(seed)
    sample = everything[rng.choice(len(everything), min(len(everything), 200_000), replace=False)].astype(float)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    o3d.utility.random.seed(seed)  # plane RANSAC repeatable
    planes = []
    for _ in range(s.planes):
        if len(cloud.points) < 1000:
            break
        model, inliers = cloud.segment_plane(distance_threshold=s.plane_inlier_m / 2, ransac_n=3, num_iterations=500)
        if len(inliers) < 0.03 * len(sample):
            break
        normal, offset = _refit(np.asarray(cloud.points)[inliers])
        plane = _plane_spread(usable, normal, offset, s)
        if plane is not None:
            planes.append(plane)
        cloud = cloud.select_by_index(inliers, invert=True)
    spreads = [p["spread_m"] for p in planes]
    if not spreads:
        return {"thickness_m": None, "planes": planes, "reason": "no plane seen by enough frames"}
    return {"thickness_m": round(float(max(spreads)), 4), "median_plane_m": round(float(np.median(spreads)), 4),
            "planes": planes}


def _refit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The least-squares plane ``(normal, offset)`` of ``points`` (P, 3): RANSAC's plane is
    only one of many within its threshold, and a wall tilted by 1 deg is 9 cm off at 5 m."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    return normal, float(-normal @ centre)


def _plane_spread(clouds: list[np.ndarray], normal: np.ndarray, offset: float, s: MeshSettings) -> dict | None:
    """One plane ``normal . p + offset = 0``: each frame's offsets of the plane's cells
    (:func:`_cell_offsets`), each pair of frames' distance over the cells both see, and the 90th
    percentile of those distances (None when fewer than 5 frames or 10 pairs see it)."""
    seen = [cells for cells in (_cell_offsets(points, normal, offset, s) for points in clouds) if cells]
    if len(seen) < 5:
        return None
    distances = _pair_distances(seen, s.shared_cells)
    if len(distances) < 10:
        return None
    return {"normal": np.round(normal, 3).tolist(), "frames": len(seen), "pairs": len(distances),
            "spread_m": round(float(np.percentile(distances, 90)), 4)}


def _pair_distances(seen: list[dict[int, float]], shared_cells: int) -> np.ndarray:
    """For each pair of frames (their cell -> offset) sharing at least ``shared_cells`` cells,
    the absolute median of their offset differences over those cells. One frame against all
    later ones at a time, over the cells it sees (a table frames x cells, NaN where unseen):
    800 frames of a floor's wall are 300 000 pairs."""
    columns = {k: c for c, k in enumerate(sorted(set().union(*seen)))}
    table = np.full((len(seen), len(columns)), np.nan)
    for row, cells in enumerate(seen):
        table[row, [columns[k] for k in cells]] = list(cells.values())
    out = []
    for i in range(len(seen) - 1):
        mine = np.flatnonzero(np.isfinite(table[i]))
        later = table[i + 1:, mine]
        enough = np.isfinite(later).sum(axis=1) >= shared_cells
        if enough.any():
            out.append(np.abs(np.nanmedian(table[i, mine] - later[enough], axis=1)))
    return np.concatenate(out) if out else np.zeros(0)


def _cell_offsets(points: np.ndarray, normal: np.ndarray, offset: float, s: MeshSettings) -> dict[int, float]:
    """One frame's points (P, 3) near the plane: cell key -> the median signed distance of its
    points in that ``s.cell_m`` cell of the plane; empty when the frame sees too little of it."""
    d = points @ normal + offset
    near = np.abs(d) < s.plane_inlier_m
    if near.sum() < s.min_points:
        return {}
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    cell = np.floor(np.stack([points[near] @ u, points[near] @ v], axis=1) / s.cell_m).astype(np.int64)
    keys = cell[:, 0] * 1_000_003 + cell[:, 1]
    order = np.argsort(keys, kind="stable")
    keys, d = keys[order], d[near][order]
    unique, first, count = np.unique(keys, return_index=True, return_counts=True)
    return {int(k): float(np.median(d[a:a + n])) for k, a, n in zip(unique, first, count) if n >= s.cell_points}