"""Which colour camera should a 7-Scenes survey be read through? Each half of a recording
surveyed by ``map`` (field left out unless ``--field``: it does not move the poses) through each registration
:class:`~nap3d_graph.datasets.SevenScenesSequence` offers, with the figures a user has without
ground truth (loops the graph kept, turned away and the bundle admitted; the bundle's pixel
and disparity residuals, also as angles so cameras of different focal lengths compare; the
readout it found; with ``--field``, the field's figures on held-out survey frames: PSNR, depth
error, and NAP3D of those frames against it) beside the ATE of the odometry, the pose graph and the survey against
KinectFusion's poses and the SfM poses.

``poses`` reads the recording's pose files to fit the colour camera: it is here to show
where the fit lands with exact-as-tracked motion, not as something ``map`` may do.

    python benchmarks/map_registration.py --data ../shared/data/7scenes/redkitchen \\
        --second-gt ../shared/data/7scenes/redkitchen/pseudo_gt_sfm.txt --work /tmp/map_registration \\
        --out benchmarks/results/map_registration_redkitchen.json
    python benchmarks/map_registration.py ... --field --out benchmarks/results/map_registration_field_redkitchen.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from map_survey import map_trajectory, read_sfm_pseudo_gt, second_gt_for  # noqa: E402  (beside this file)
from provenance import write_result

REGISTRATIONS = ("nominal", "images", "poses")
HALVES = ("0:0.5", "0.5:1")


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--second-gt", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--registrations", nargs="+", default=list(REGISTRATIONS), choices=REGISTRATIONS)
    parser.add_argument("--field", action="store_true",
                        help="build each map's field too and record its held-out figures (what the images say of "
                        "the camera they were read through: a wrong focal length puts colour and depth apart)")
    parser.add_argument("--out", type=Path, required=True)
    return parser.parse_args()


def _self_figures(info: dict, f_px: float) -> dict:
    """What map.json says of the survey with no ground truth."""
    graph, bundle = info["stages"]["graph"], info["bundle"]
    last = bundle["noise_rounds"][-1]
    return {"loops_verified": graph["loops_verified"], "loops_kept": graph["loops_accepted"],
            "loops_admitted": graph["loops_admitted"], "loops_turned_away": graph["loops_rejected"],
            "readout_s": bundle.get("readout_s"), "residual_px": last["residual_px"],
            "residual_disparity_px": last["residual_disparity_px"],
            "residual_mrad": 1000 * last["residual_px"] / f_px,
            "residual_disparity_mrad": 1000 * last["residual_disparity_px"] / f_px}


def _field_figures(folder: Path) -> dict:
    """The field's figures on held-out survey frames, as the map's report reads them."""
    from nap3d_graph.mapping.report import map_report

    values = map_report(folder).values
    return {"held_out": values.get("held_out"), "held_out_nap3d": values.get("held_out_nap3d")}


def _one(args, registration: str, frames: str, references) -> dict:
    from nap3d_graph.datasets import SevenScenesSequence
    from nap3d_graph.evaluation.alignment import aligned_errors
    from nap3d_graph.mapping.build import MapSettings, build_map

    sequence = SevenScenesSequence(args.data, registration=registration, frames=frames)
    folder = args.work / f"{registration}_{frames.replace(':', '-')}"
    t0 = time.perf_counter()
    build_map(sequence, folder, MapSettings(), progress=False, build_field_stage=args.field)
    refs = {name: make(sequence) for name, make in references.items()}
    row = {"registration": registration, "frames": frames, "colour": sequence.intrinsics.to_dict(),
           "seconds": round(time.perf_counter() - t0, 1),
           **_self_figures(json.loads((folder / "map.json").read_text()), sequence.intrinsics.fx)}
    if args.field:
        row["field"] = _field_figures(folder)
        print(registration, frames, "field", row["field"])
    for stage, name in (("odometry", "odometry.txt"), ("survey", "poses.txt")):
        T = map_trajectory(folder, name, sequence)
        row[stage] = {ref: aligned_errors(sequence.timestamps, R, T).summary() for ref, R in refs.items()}
    print(registration, frames, f"f {sequence.intrinsics.fx:.1f}",
          {k: row[k] for k in ("loops_kept", "loops_turned_away", "residual_mrad", "residual_disparity_mrad")},
          {s: {r: round(v["rmse_m"] * 100, 2) for r, v in row[s].items()} for s in ("odometry", "survey")})
    return row


def main() -> None:
    args = _arguments()
    table = read_sfm_pseudo_gt(args.second_gt)
    references = {"KinectFusion": lambda s: np.asarray(s.T_world_cam_gt), "SfM": lambda s: second_gt_for(s, table)}
    rows = [_one(args, registration, frames, references) for registration in args.registrations for frames in HALVES]
    write_result(args.out, {"command": " ".join(sys.argv), "data": str(args.data), "halves": list(HALVES),
                            "field": args.field, "rows": rows}, args)


if __name__ == "__main__":
    main()
