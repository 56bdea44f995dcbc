"""A run as a rerun recording (``run --viz run.rrd`` or ``--viz spawn``; extra ``viz``: rerun-sdk).

On the ``frame`` timeline (and ``capture_time``, the frames' stamps), per keyframe:

- ``keyframes/real`` and ``keyframes/render``: the real image and the field's render the
  alignment compared (at the render's resolution);
- ``keyframes/matches``: both side by side with the inlier matches as lines;
- ``keyframes/status``: one text entry per keyframe, accepted (inliers, size of the
  correction) or refused with the reason;
- ``world/corrections/accepted/FRAME`` or ``refused/FRAME`` (a correction the gate refused):
  the measured pose's position covariance as a 3-sigma ellipsoid at the corrected position;
- ``world/camera``: the keyframe's corrected pose and pinhole (a frustum in the 3D view).

At the end of the run, ``world/trajectory/{odometry,causal,smoothed,truth}`` as lines
(static) and the causal camera ``world/camera_causal`` at every frame.
"""

from __future__ import annotations

import logging

import numpy as np

from nap3d_graph.rerun_sdk import import_rerun

__all__ = ["RunRecorder", "keyframe_entries"]

log = logging.getLogger(__name__)

COLOURS = {"odometry": (230, 159, 0), "causal": (0, 114, 178), "smoothed": (0, 158, 115), "truth": (90, 90, 90),
           "accepted": (0, 158, 115), "refused": (213, 94, 0)}
JPEG_QUALITY = 90
SIGMAS = 3.0  # ellipsoids drawn at 3 sigma: a 1-sigma centimetre is invisible beside a room


class RunRecorder:
    """Logs a run to rerun as it goes: :meth:`keyframe` from the run's ``on_keyframe``,
    :meth:`finish` with its result. ``target``: an ``.rrd`` path or ``"spawn"``."""

    def __init__(self, target: str, name: str = "run", intrinsics=None):
        rr = import_rerun()
        self.rr = rr
        self.stream = rr.RecordingStream("nap3d-graph", recording_id=None)
        if target == "spawn":
            self.stream.spawn()
        else:
            self.stream.save(target)
        self.target, self.intrinsics = target, intrinsics
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.stream.log("run", rr.TextDocument(f"nap3d-graph run: {name}"), static=True)

    def _at(self, frame_index: int, timestamp: float) -> None:
        self.stream.set_time("frame", sequence=int(frame_index))
        self.stream.set_time("capture_time", timestamp=float(timestamp))

    def keyframe(self, record, correction=None, T_field_cam_render=None) -> None:
        """One keyframe: its images, matches, status, covariance and camera (``correction``:
        its :class:`~nap3d_graph.results.Correction`, or None when none was measured)."""
        self._at(record.frame_index, record.timestamp)
        views = getattr(correction, "views", None) or {}
        real, render = views.get("real_rgb"), views.get("render_rgb")
        if real is not None:
            self.stream.log("keyframes/real", self._image(real))
        if render is not None:
            self.stream.log("keyframes/render", self._image(render))
        if real is not None and render is not None and real.shape == render.shape:
            self._matches(real, render, views)
        self.stream.log("keyframes/status", self._status(record))
        if correction is not None and correction.success:
            self._ellipsoid(record, correction)
            self._camera(correction.T_world_cam_corrected, real)

    def _image(self, rgb: np.ndarray):
        """JPEG-compressed: raw images would make a long run's recording a gigabyte."""
        return self.rr.Image(np.ascontiguousarray(rgb)).compress(jpeg_quality=JPEG_QUALITY)

    def _status(self, record):
        rr = self.rr
        if record.accepted:
            text = (f"frame {record.frame_index}: accepted, {record.inliers} inliers, correction "
                    f"{record.correction_m * 100:.1f} cm / {record.correction_deg:.2f} deg")
            return rr.TextLog(text, level=rr.TextLogLevel.INFO)
        return rr.TextLog(f"frame {record.frame_index}: refused: {record.reason or 'unknown'}",
                          level=rr.TextLogLevel.WARN)

    def _matches(self, real: np.ndarray, render: np.ndarray, views: dict) -> None:
        rr = self.rr
        width = real.shape[1]
        self.stream.log("keyframes/matches", self._image(np.concatenate([real, render], axis=1)))
        uv_real, uv_render = views.get("inlier_uv_real"), views.get("inlier_uv_render")
        if uv_real is None or uv_render is None or not len(uv_real):
            self.stream.log("keyframes/matches/inliers", rr.Clear(recursive=False))
            return
        ends = np.asarray(uv_render, dtype=float) + np.array([width, 0.0])
        strips = np.stack([np.asarray(uv_real, dtype=float), ends], axis=1)
        self.stream.log("keyframes/matches/inliers", rr.LineStrips2D(strips, colors=COLOURS["accepted"], radii=0.5))

    def _ellipsoid(self, record, correction) -> None:
        rr = self.rr
        T = np.asarray(correction.T_world_cam_corrected)
        R = T[:3, :3]
        # GTSAM order [rotation, translation], body frame: the translation block, in the world.
        cov_world = R @ np.asarray(correction.covariance)[3:, 3:] @ R.T
        values, vectors = np.linalg.eigh(0.5 * (cov_world + cov_world.T))
        if np.linalg.det(vectors) < 0:
            vectors[:, 0] *= -1
        from scipy.spatial.transform import Rotation

        kind = "accepted" if record.accepted else "refused"
        # One entity per keyframe: the viewer keeps every ellipsoid on screen, not only the latest.
        self.stream.log(f"world/corrections/{kind}/{record.frame_index}", rr.Ellipsoids3D(
            centers=[T[:3, 3]], half_sizes=[SIGMAS * np.sqrt(np.maximum(values, 0.0))],
            quaternions=[rr.Quaternion(xyzw=Rotation.from_matrix(vectors).as_quat())], colors=[COLOURS[kind]],
            labels=[f"{record.frame_index}"]))

    def _camera(self, T_world_cam: np.ndarray, image) -> None:
        rr = self.rr
        T = np.asarray(T_world_cam)
        self.stream.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        if self.intrinsics is not None:
            K = self.intrinsics
            h, w = image.shape[:2] if image is not None else (K.height, K.width)
            scale = w / K.width
            self.stream.log("world/camera", rr.Pinhole(focal_length=[K.fx * scale, K.fy * scale],
                                                       principal_point=[(K.cx + 0.5) * scale - 0.5,
                                                                        (K.cy + 0.5) * scale - 0.5],
                                                       resolution=[w, h], camera_xyz=rr.ViewCoordinates.RDF,
                                                       image_plane_distance=0.1))

    def finish(self, result) -> None:
        """The trajectories (static lines) and the causal camera along the timeline."""
        rr = self.rr
        tracks = {"odometry": result.T_world_cam_odometry, "smoothed": result.T_world_cam_estimate,
                  "causal": result.T_world_cam_online if result.T_world_cam_online is not None else None,
                  "truth": result.T_world_cam_gt}
        for name, T in tracks.items():
            if T is None:
                continue
            positions = np.asarray(T)[:, :3, 3]
            finite = np.all(np.isfinite(positions), axis=1)
            if finite.sum() >= 2:
                self.stream.log(f"world/trajectory/{name}", rr.LineStrips3D([positions[finite]], colors=COLOURS[name],
                                                                            radii=0.003), static=True)
        causal = tracks["causal"] if tracks["causal"] is not None else tracks["smoothed"]
        for i, (t, T) in enumerate(zip(result.timestamps, causal)):
            self._at(i, t)
            self.stream.log("world/camera_causal", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        self.stream.flush()

    def close(self) -> None:
        self.stream.flush()
        if self.target != "spawn":
            self.stream.disconnect()


def keyframe_entries(path) -> dict[str, int]:
    """Rows per entity path of an ``.rrd`` file, read back with rerun's own reader."""
    import_rerun()
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        counts[chunk.entity_path] = counts.get(chunk.entity_path, 0) + int(chunk.num_rows)
    return counts
