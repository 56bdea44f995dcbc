"""The depth-unit mistakes, told from the depth alone (no poses) before any work, on real
recordings: each as it is (no warning wanted) and read in the wrong unit (a warning wanted).

Recordings: TUM fr1/desk and fr1/xyz (Kinect v1, 5000 per metre), 7-Scenes redkitchen
(Kinect v1, millimetres), a D435's recording (librealsense's own file, millimetres). Mistakes:
TUM's PNGs read as millimetres (``depth_scale`` 1000), a Kinect's millimetres read at TUM's
5000 (TUM's frames converted to millimetres, as a Kinect driver writes them), 7-Scenes read
at 5000, and the D435's frames written by a recording script into a TUM-layout folder
(millimetres) read at 5000. The check: :func:`nap3d_graph.datasets.depth_unit.inspect_depth_unit`,
what every command runs first.

    python benchmarks/depth_unit_without_poses.py --tum ../shared/data/tum \\
        --sevenscenes ../shared/data/7scenes/redkitchen \\
        --bag ../shared/data/realsense/single_depth_color_640x480.bag \\
        --out benchmarks/results/depth_unit_without_poses.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
from provenance import write_result


def _millimetre_copy(folder: Path, out: Path) -> Path:
    """TUM frames with their depth PNGs in millimetres (TUM's values / 5)."""
    shutil.copytree(folder, out, ignore=shutil.ignore_patterns("rgb"))
    (out / "rgb").symlink_to((folder / "rgb").resolve())
    for png in (out / "depth").glob("*.png"):
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(png), np.rint(raw / 5.0).astype(np.uint16))
    return out


def _bag_as_folder(bag: Path, out: Path) -> Path:
    """The recording's frames as a recording script writes them: TUM layout, millimetres."""
    from nap3d_graph.datasets import open_sequence

    sequence = open_sequence(bag)
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for k in range(len(sequence)):
        frame = sequence[k]
        cv2.imwrite(str(out / f"rgb/{k}.png"), frame.rgb[..., ::-1])
        cv2.imwrite(str(out / f"depth/{k}.png"), np.rint(frame.depth_m * 1000).astype(np.uint16))
        rgb_lines.append(f"{k * 0.1:.6f} rgb/{k}.png")
        depth_lines.append(f"{k * 0.1:.6f} depth/{k}.png")
    (out / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (out / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    K = sequence.intrinsics
    (out / "intrinsics.json").write_text(json.dumps({"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy,
                                                     "width": K.width, "height": K.height}))
    return out


def _look(path: Path, **kwargs) -> dict:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.datasets.depth_unit import inspect_depth_unit

    look = inspect_depth_unit(open_sequence(path, **kwargs))
    return {"median_m": look.median_m, "near_m": look.near_m, "units_per_m": look.units_per_m,
            "kinect_units_per_m": [u for u in look.kinect_units_per_m if u is not None],
            "warnings": list(look.warnings), "refused": look.mixed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tum", type=Path, required=True, help="folder with the TUM fr1/desk and fr1/xyz folders")
    parser.add_argument("--sevenscenes", type=Path, required=True)
    parser.add_argument("--bag", type=Path, required=True, help="a D435's RealSense recording (.bag)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    desk, xyz = args.tum / "rgbd_dataset_freiburg1_desk", args.tum / "rgbd_dataset_freiburg1_xyz"
    work = Path(tempfile.mkdtemp(prefix="depth_unit_"))
    cases = {
        "fr1/desk as it is": (desk, {}, False),
        "fr1/xyz as it is": (xyz, {}, False),
        "7-Scenes redkitchen as it is": (args.sevenscenes, {}, False),
        "D435 recording as it is": (args.bag, {}, False),
        "D435 frames in a TUM-layout folder, depth_scale 1000 declared": (None, {"depth_scale": 1000}, False),
        "fr1/desk read as millimetres": (desk, {"depth_scale": 1000}, True),
        "fr1/xyz read as millimetres": (xyz, {"depth_scale": 1000}, True),
        "fr1/desk in millimetres read at 5000": (_millimetre_copy(desk, work / "rgbd_freiburg1_desk_mm"), {}, True),
        "7-Scenes redkitchen read at 5000": (args.sevenscenes, {"depth_scale": 5000}, True),
        "D435 frames in a TUM-layout folder read at 5000": (None, {}, True),
    }
    bag_folder = _bag_as_folder(args.bag, work / "d435_frames")
    result: dict = {"cases": {}}
    for name, (path, kwargs, mistaken) in cases.items():
        look = _look(path or bag_folder, **kwargs)
        told = bool(look["warnings"] or look["refused"])
        look.update({"mistake": mistaken, "told": told, "right": told == mistaken})
        result["cases"][name] = look
        print(f"{name}: {'warned' if told else 'no warning'} ({'right' if told == mistaken else 'WRONG'})"
              + (f": {look['warnings'][0][:120]}" if look["warnings"] else ""))
    result["mistakes_told"] = sum(c["told"] for c in result["cases"].values() if c["mistake"])
    result["mistakes"] = sum(c["mistake"] for c in result["cases"].values())
    result["false_alarms"] = sum(c["told"] for c in result["cases"].values() if not c["mistake"])
    shutil.rmtree(work, ignore_errors=True)
    write_result(args.out, result, args)
    print(f"mistakes told {result['mistakes_told']}/{result['mistakes']}, false alarms {result['false_alarms']}; "
          f"wrote {args.out}")


if __name__ == "__main__":
    main()
