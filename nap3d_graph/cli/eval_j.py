"""``nap3d-graph eval-j``: the paper's Evaluation J in the simulator."""

from __future__ import annotations

import json
from pathlib import Path

from nap3d_graph.arguments import positive_int
from nap3d_graph.fields import resolve_field
from nap3d_graph.sims.scene import OracleField, Scene, make_scene
from nap3d_graph.sims.sequence import default_intrinsics

from .common import empty_or_new_dir
from .options import add_output_folder, add_seed


def add_parser(sub) -> None:
    p = sub.add_parser(
        "eval-j",
        help="the paper's Evaluation J in the simulator: known planar offsets from two reference views",
        description="The field camera fixed at a reference pose per sublocation (A near, feature-rich; B far); "
        "the real camera at known (x, z) offsets up to +-0.5 m. Writes results.csv, summary.json and "
        "tables.md (per-trial estimated vs true offsets, per-sublocation RMSE, like the paper's Tables I/II).",
    )
    p.add_argument("data", type=Path, nargs="?", help="a simulated sequence folder (its room is used); "
                   "omit to use --scene-seed")
    p.add_argument("--scene-seed", type=int, default=0, help="the room when no DATA is given (default 0)")
    p.add_argument("--field", default="oracle", help="'oracle' (default) or a field checkpoint of that room")
    p.add_argument("--trials", type=positive_int, default=6, help="trials per sublocation; the first 3 are the paper's "
                   "offsets (default 6)")
    add_seed(p, "the extra offsets and sensor noise")
    p.add_argument("--width", type=positive_int, default=640)
    p.add_argument("--height", type=positive_int, default=480)
    add_output_folder(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from nap3d_graph.evaluation.eval_j import EvalJConfig, run_eval_j
    empty_or_new_dir(args.out, args.force)

    if args.data is not None:
        scene_file = Path(args.data) / "scene.json"
        if not scene_file.exists():
            raise FileNotFoundError(f"{scene_file}: eval-j needs a simulated sequence (no scene.json)")
        scene = Scene.load(scene_file)
    else:
        scene = make_scene(args.scene_seed)
    field_obj = OracleField(scene) if args.field == "oracle" else resolve_field(args.field)
    summary = run_eval_j(scene, field_obj, default_intrinsics(args.width, args.height), args.out,
                         EvalJConfig(trials_per_sublocation=args.trials, seed=args.seed))
    print((Path(args.out) / "tables.md").read_text())
    print(json.dumps(summary, indent=1))
    return 0
