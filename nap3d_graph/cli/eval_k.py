"""``nap3d-graph eval-k``: the paper's Evaluation K, and the project's variants beside it."""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.arguments import positive_int
from nap3d_graph.datasets import open_sequence
from nap3d_graph.datasets.depth_timing import resolve_capture_timing
from nap3d_graph.fields import resolve_field
from nap3d_graph.nap3d.config import AlignConfig

from .common import add_frames_argument, add_matcher_argument, empty_or_new_dir, parse_methods, warn_trained_frames
from .options import add_output_folder, add_seed


def add_parser(sub) -> None:
    from nap3d_graph.evaluation.eval_k import DEFAULT_METHODS, METHODS

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
    add_frames_argument(p, "the scenarios (e.g. the part of a recording the field was not trained on)")
    p.add_argument("--scenarios", type=positive_int, default=40, help="number of scenarios (default 40)")
    add_seed(p, "the scenarios")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated methods (default {','.join(DEFAULT_METHODS)}). {methods_help}")
    p.add_argument("--shift", choices=("real", "both"), default="real",
                   help="which cameras' intrinsics the methods are told shifted: the real one (default) or both "
                   "(the rendered view's too; the renders themselves always use the true intrinsics)")
    p.add_argument("--iterate", action="store_true",
                   help="also run correct_pose (re-render at the corrected pose, 3 rounds) as 'nap3d-iter'")
    p.add_argument("--timing", choices=("auto", "none"), default="auto",
                   help="auto (default): move each scenario's depth to its colour's capture instant with the "
                   "ground-truth motion, at the capture timing the field records or, for a field that records "
                   "none, the timing estimated from DATA's ground truth (a real or Kinect-like camera takes depth "
                   "tens of ms before colour: uncompensated, a 3D-3D method measures that asynchrony); none: the "
                   "frames as stamped")
    add_matcher_argument(p)
    add_output_folder(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from nap3d_graph.evaluation.eval_k import METHODS, EvalKConfig, run_eval_k
    methods = parse_methods(args.methods, METHODS)
    empty_or_new_dir(args.out, args.force)
    if args.iterate and "nap3d-iter" not in methods:
        methods += ("nap3d-iter",)
    sequence = open_sequence(args.data, frames=args.frames)
    field_obj = resolve_field(args.field, sequence)
    config = EvalKConfig(scenarios=args.scenarios, seed=args.seed, methods=methods, shift=args.shift,
                         align=AlignConfig(matcher=args.matcher),
                         timing=resolve_capture_timing(field_obj, sequence, compensate=args.timing == "auto")[0])
    warn_trained_frames(field_obj, sequence, "frames the scenarios are drawn from")
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
