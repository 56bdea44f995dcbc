"""``nap3d-graph bench-peers``: NAP3D against its peers and the Cramer-Rao bound, same frames."""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.arguments import positive_float, positive_int
from nap3d_graph.datasets import open_sequence
from nap3d_graph.datasets.depth_timing import resolve_capture_timing
from nap3d_graph.evaluation.peers import PeersConfig, run_bench_peers
from nap3d_graph.fields import resolve_field

from .common import (
    UsageError,
    add_frames_argument,
    add_matcher_argument,
    empty_or_new_dir,
    parse_methods,
    parse_size,
    warn_trained_frames,
)
from .options import add_output_folder, add_seed


def add_parser(sub) -> None:
    from nap3d_graph.baselines import PEERS

    p = sub.add_parser(
        "bench-peers",
        help="NAP3D vs PnP, GICP and dense RGB-D alignment on the same perturbed poses, against the physical limit",
        description="Each trial draws a frame with ground truth and a perturbation of its pose, renders the field "
        "there and runs every method on that frame and view: " + "; ".join(f"{k}: {v}" for k, v in PEERS.items())
        + ". A failure scores the uncorrected pose. The Cramer-Rao bound of each trial comes from the refined "
        "NAP3D's inlier matches at the true pose. Writes trials.csv, summary.json and accuracy_vs_time.png "
        "(median and p90 error against milliseconds per correction).",
    )
    p.add_argument("data", type=Path, help="a sequence with ground truth (TUM folder or simulated)")
    p.add_argument("--field", required=True, help="'oracle' (the simulated room of DATA) or a field checkpoint / "
                   "nerfstudio config.yml")
    add_frames_argument(p, "the trials (the part of a recording the field was not trained on)")
    p.add_argument("--trials", type=positive_int, default=40, help="number of trials (default 40)")
    add_seed(p, "the perturbations")
    p.add_argument("--max-trans", type=positive_float, default=0.10, help="perturbation per axis, m (default 0.10)")
    p.add_argument("--max-rot", type=positive_float, default=5.0, help="perturbation angle, deg (default 5)")
    p.add_argument("--methods", default=None, help=f"comma-separated (default: all that apply to the field, of "
                   f"{','.join(PEERS)}; photometric needs a trained grid field)")
    p.add_argument("--render-size", default="320x240", help="WxH of the render and the real frame (default 320x240)")
    add_matcher_argument(p)
    add_output_folder(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from nap3d_graph.baselines import PEERS
    from nap3d_graph.fields.grid import GridField

    methods = parse_methods(args.methods or ",".join(PEERS), PEERS)
    size = parse_size(args.render_size)
    empty_or_new_dir(args.out, args.force)
    sequence = open_sequence(args.data, frames=args.frames)
    field = resolve_field(args.field, sequence)
    if "photometric" in methods and not isinstance(field, GridField):
        if args.methods:
            raise UsageError(f"--methods photometric needs a trained grid field (it differentiates the field); "
                             f"{args.field!r} is a {getattr(field, 'name', type(field).__name__)} field")
        methods = tuple(m for m in methods if m != "photometric")
        print(f"photometric peer left out: it needs a differentiable grid field, not {args.field!r}")
    warn_trained_frames(field, sequence, "frames the trials are drawn from")
    config = PeersConfig(trials=args.trials, seed=args.seed, max_trans_m=args.max_trans, max_rot_deg=args.max_rot,
                         render_size=size, methods=methods, timing=resolve_capture_timing(field, sequence)[0],
                         matcher=args.matcher)
    summary = run_bench_peers(sequence, field, args.out, config, progress=True)
    print(format_summary(summary))
    print(f"results in {args.out}/ (trials.csv, summary.json, accuracy_vs_time.png)")
    return 0


def format_summary(summary: dict) -> str:
    lines = [f"{'method':<15}{'ok':>6}{'trans med':>11}{'p90':>9}{'max':>9}{'rot med':>10}{'p90':>8}{'ms':>8}"
             f"{'err/CRB':>9}"]
    for name, m in summary["methods"].items():
        t, r = m["trans_mm"], m["rot_deg"]
        ratio = f"{m['trans_over_crb_median']:9.1f}" if m["trans_over_crb_median"] else f"{'-':>9}"
        lines.append(f"{name:<15}{m['success_rate']:6.0%}{t['median']:9.2f}mm{t['p90']:9.2f}{t['max']:9.1f}"
                     f"{r['median']:8.3f}deg{r['p90']:8.3f}{m['ms_median'] or float('nan'):8.0f}{ratio}")
    crb = summary["crb_trans_mm"]
    if crb["median"] is not None:
        lines.append(f"Cramer-Rao bound on translation (sqrt trace): median {crb['median']:.2f} mm, p90 {crb['p90']:.2f} mm")
    lines.append("(errors over every trial, a failure scored as the uncorrected pose; ms: median per correction, "
                 "SIFT and matching included for the feature methods)")
    return "\n".join(lines)
