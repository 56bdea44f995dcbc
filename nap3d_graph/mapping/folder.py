"""A map folder: where each of its files lives, its ``map.json`` and which stages finished.

``nap3d-graph map`` writes each stage's file when the stage finishes and records the stage in
``map.json``; a map interrupted anywhere resumes from its last finished stage. Every module
that reads or writes a map's file names it through :class:`MapFolder`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from nap3d_graph.pools import peak_memory_gb
from nap3d_graph.textfiles import write_json_atomic

__all__ = ["MapFolder", "MAP_INFO", "load_map_info"]

#: The file that marks a folder as a map.
MAP_INFO = "map.json"


def load_map_info(folder) -> dict:
    """``map.json`` of a map folder (``FileNotFoundError`` when it is not one)."""
    path = Path(folder) / MAP_INFO
    if not path.is_file():
        raise FileNotFoundError(f"{folder}: not a map folder (no {MAP_INFO}; make one with 'nap3d-graph map')")
    return json.loads(path.read_text())


@dataclass
class MapFolder:
    """The map in ``root``; ``info``: its ``map.json`` as read or being written."""

    root: Path
    info: dict = field(default_factory=dict)

    # Each stage's files (module docstring of :mod:`.build`), then the outputs.
    @property
    def info_path(self) -> Path:
        return self.root / MAP_INFO

    @property
    def odometry(self) -> Path:
        """Stage 1: the survey's frame-to-frame odometry (:class:`~.survey.SurveyOdometry`)."""
        return self.root / "odometry.npz"

    @property
    def keyframes(self) -> Path:
        """Stage 2: keyframe indices, global descriptors and the vocabulary."""
        return self.root / "keyframes.npz"

    @property
    def keyframe_frames(self) -> Path:
        """Stage 2: the keyframes' colour and depth at a small width, for relocalisation."""
        return self.root / "keyframe_frames.npz"

    @property
    def edges(self) -> Path:
        """Stage 3: the consecutive edges, the loops and their inlier matches."""
        return self.root / "edges.npz"

    @property
    def loops_table(self) -> Path:
        """Stage 4: every loop candidate, its verification and the graph's decision (CSV)."""
        return self.root / "loops.csv"

    @property
    def poses(self) -> Path:
        """Stage 4: every survey frame's pose in the map (TUM format)."""
        return self.root / "poses.txt"

    @property
    def odometry_poses(self) -> Path:
        """Stage 4: the odometry's poses alone over the kept segment (TUM format)."""
        return self.root / "odometry.txt"

    @property
    def keyframe_poses(self) -> Path:
        """Stage 4: the keyframes' poses in the map (K, 4, 4), ``.npy``."""
        return self.root / "keyframe_poses.npy"

    @property
    def field(self) -> Path:
        """Stage 5: the field's checkpoint."""
        return self.root / "field.pt"

    @property
    def field_report(self) -> Path:
        return self.root / "field.report.json"

    @property
    def mesh(self) -> Path:
        """Stage 6: the survey fused at the map's poses, a coloured triangle mesh (PLY)."""
        return self.root / "map.ply"

    @property
    def survey_ate(self) -> Path:
        """The survey's poses against the recording's ground truth, where it has one."""
        return self.root / "survey_ate.json"

    @property
    def plot(self) -> Path:
        return self.root / "map.png"

    @property
    def report(self) -> Path:
        return self.root / "report.md"

    @classmethod
    def read(cls, root) -> "MapFolder":
        """An existing map (``FileNotFoundError`` when ``root`` is not one)."""
        return cls(Path(root), load_map_info(root))

    @classmethod
    def open(cls, root, wanted: dict, compared: tuple[str, ...]) -> "MapFolder":
        """The map folder ``root`` for a map described by ``wanted`` (JSON-able): made when new,
        resumed when its ``map.json`` agrees with ``wanted`` on every key of ``compared``;
        ``FileExistsError`` when it holds a map of other data or settings (never mixed)."""
        folder = cls(Path(root))
        folder.root.mkdir(parents=True, exist_ok=True)
        info = json.loads(folder.info_path.read_text()) if folder.info_path.is_file() else {}
        expected = json.loads(json.dumps(wanted, default=float))
        if info and any(info.get(k) != expected.get(k) for k in compared):
            raise FileExistsError(f"{folder.root} holds a map of other data or settings; choose another folder or "
                                  "remove it")
        folder.info = {**wanted, "stages": info.get("stages", {}),
                       **{k: v for k, v in info.items() if k not in wanted and k != "stages"}}
        folder.save()
        return folder

    def save(self) -> None:
        """``map.json`` written (atomically)."""
        write_json_atomic(self.info_path, self.info, default=float)

    def done(self, stage: str, seconds: float, **extra) -> None:
        """``stage`` recorded as finished, with its seconds, ``extra`` figures and the most memory
        this process had held by its end (``peak_memory_gb``: the stage that raised it is where a
        map's memory went)."""
        self.info["stages"][stage] = {"seconds": round(seconds, 2), **extra, "peak_memory_gb": peak_memory_gb()}
        self.save()

    def finished(self, stage: str, path: Path) -> bool:
        """Whether ``stage`` finished before and left ``path``."""
        return stage in self.info["stages"] and path.is_file()
