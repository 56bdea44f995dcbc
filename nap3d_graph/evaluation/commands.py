"""``nap3d-graph eval-k`` and ``eval-j``: the paper's two protocols."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["add_eval_k", "add_eval_j", "resolve_field"]


def resolve_field(field_arg: str, sequence=None):
    """``oracle`` (the simulated room the data came from) or a path for ``load_field``."""
    from nap3d_graph.fields import FieldError, load_field

    if field_arg == "oracle":
        oracle = getattr(sequence, "oracle_field", None)
        if oracle is None:
            where = getattr(sequence, "path", "the data")
            raise FieldError(f"--field oracle needs a simulated sequence (with scene.json); {where} is not one")
        return oracle()
    return load_field(field_arg)


def add_eval_k(sub) -> None:
    from .eval_k import DEFAULT_METHODS, METHODS

    methods_help = "; ".join(f"{name}: {text}" for name, text in METHODS.items())
    p = sub.add_parser(
        "eval-k",
        help="the paper's Evaluation K: NAP3D vs PnP-RANSAC under blur and intrinsics noise",
        description="For each scenario a random frame and a random perturbation of its ground truth "
        "(+-10 cm per axis, up to 5 deg); the field renders at the perturbed pose; 16 cells of blur sigma "
        "{0, 1.0, 1.8, 2.2} x intrinsics noise {CLEAN, MILD, MEDIUM, HARSH}. Compares the paper's pair "
        "(nap3d-plain vs pnp, its Figure 4) and the project's variants, each against the PnP that had the "
        "same help (nap3d-refined vs pnp, nap3d-selfcal vs pnp-selfcal). A failed correction scores the "
        "uncorrected pose's error. Writes results.csv, summary.json, table.md (median / p90 / max, success "
        "rate, NEES) and one heatmap figure per compared pair.",
    )
    p.add_argument("data", type=Path, help="a sequence with ground truth (TUM folder or simulated)")
    p.add_argument("--field", required=True, help="'oracle' (the simulated room of DATA) or a field checkpoint / "
                   "nerfstudio config.yml")
    p.add_argument("--scenarios", type=int, default=40, help="number of scenarios (default 40)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated methods (default {','.join(DEFAULT_METHODS)}). {methods_help}")
    p.add_argument("--shift", choices=("real", "both"), default="real",
                   help="which cameras' intrinsics the methods are told shifted: the real one (default) or both "
                   "(the rendered view's too; the renders themselves always use the true intrinsics)")
    p.add_argument("--iterate", action="store_true",
                   help="also run correct_pose (re-render at the corrected pose, 3 rounds) as 'nap3d-iter'")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.set_defaults(func=_cmd_eval_k)


def _cmd_eval_k(args) -> int:
    from nap3d_graph.datasets import open_sequence

    from .eval_k import EvalKConfig, run_eval_k

    if args.scenarios < 1:
        raise ValueError(f"--scenarios must be positive, got {args.scenarios}")
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    if args.iterate and "nap3d-iter" not in methods:
        methods += ("nap3d-iter",)
    config = EvalKConfig(scenarios=args.scenarios, seed=args.seed, methods=methods, shift=args.shift)
    sequence = open_sequence(args.data)
    field_obj = resolve_field(args.field, sequence)
    summary = run_eval_k(sequence, field_obj, args.out, config, progress=True)
    print(_format_k(summary))
    print(f"results in {args.out}/ (results.csv, summary.json, table.md, heatmaps)")
    return 0


def _format_k(summary: dict) -> str:
    methods = summary["config"]["methods"]
    lines = [f"{'cell':<16}" + "".join(f"{m:>28}" for m in methods)]
    for key, cell in summary["cells"].items():
        parts = []
        for m in methods:
            s = cell["methods"][m]
            if s["trans_err_m"]["median"] is None:
                parts.append(f"{'-':>28}")
                continue
            parts.append(f"{s['trans_err_m']['median'] * 1000:7.2f}mm {s['rot_err_deg']['median']:6.3f}deg "
                         f"{s['success_rate'] * 100:4.0f}%")
        lines.append(f"{key:<16}" + "".join(f"{p:>28}" for p in parts))
    lines.append("(median translation, median rotation over all trials, a failure scored as the uncorrected pose; "
                 "success rate; p90, max, 3D RMSE and NEES in table.md)")
    return "\n".join(lines)


def add_eval_j(sub) -> None:
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
    p.add_argument("--trials", type=int, default=6, help="trials per sublocation; the first 3 are the paper's "
                   "offsets (default 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the extra offsets and sensor noise")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.set_defaults(func=_cmd_eval_j)


def _cmd_eval_j(args) -> int:
    from nap3d_graph.sims.scene import OracleField, Scene, make_scene
    from nap3d_graph.sims.sequence import default_intrinsics

    from .eval_j import EvalJConfig, run_eval_j

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
