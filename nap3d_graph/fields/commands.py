"""The ``train-field`` and ``export-nerfstudio`` subcommands (wired into ``nap3d_graph.cli``).

Each ``add_*`` function adds its parser to an ``argparse`` subparsers object; the command
function takes the parsed namespace and returns an exit code. User errors are raised as
:class:`~nap3d_graph.fields.FieldError` or :class:`~nap3d_graph.datasets.DatasetError`; the
CLI turns them into one-line messages. Only these command functions print.
"""

from __future__ import annotations

import json
from pathlib import Path

from .base import FieldError

__all__ = ["add_train_field", "add_export_nerfstudio", "open_sequence"]


def open_sequence(path: Path):
    """A posed RGB-D sequence from a folder: a simulated room (``scene.json``) or a TUM folder."""
    from nap3d_graph.datasets import open_sequence as open_any

    return open_any(Path(path))


def add_train_field(subparsers) -> None:
    p = subparsers.add_parser(
        "train-field",
        help="train a grid radiance field on a posed RGB-D sequence",
        description="Train a dense voxel-grid radiance field (RGB + density, CPU or CUDA) on a posed "
        "RGB-D sequence (TUM folder or simulated room) and write the checkpoint plus "
        "field_report.json (held-out PSNR, depth errors, opacity, unit check) beside it.",
    )
    p.add_argument("data", type=Path, help="sequence folder (TUM layout, with ground-truth poses)")
    p.add_argument("--out", type=Path, required=True, help="checkpoint to write (FIELD.pt)")
    p.add_argument("--minutes", type=float, default=5.0, help="optimisation budget in minutes (default 5)")
    p.add_argument("--steps", type=int, default=None,
                   help="optimisation budget in steps instead of minutes: the same field on any machine "
                   "(--minutes is ignored when given)")
    p.add_argument("--every", type=int, default=1,
                   help="train on every K-th frame, hold out the rest for evaluation (default 1: every "
                   "tenth frame is held out)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--voxel-size", type=float, default=0.03, help="grid spacing in metres (default 0.03)")
    p.add_argument("--coarse-voxel-size", type=float, default=None,
                   help="start on a coarser grid of this spacing for the first 20%% of the budget "
                   "(default: off; the grid starts from the back-projected depth instead)")
    p.add_argument("--eval-frames", type=int, default=8, help="held-out frames to evaluate (default 8)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_field)


def run_train_field(args) -> int:
    import torch

    from .training import TrainConfig, train_field

    if args.steps is not None and args.steps < 1:
        raise FieldError(f"--steps must be at least 1, got {args.steps}")
    if args.steps is None and not args.minutes > 0:
        raise FieldError(f"--minutes must be positive, got {args.minutes}")
    if not args.voxel_size > 0:
        raise FieldError(f"--voxel-size must be positive, got {args.voxel_size}")
    if args.out.suffix != ".pt":
        raise FieldError(f"--out must name a .pt checkpoint, got {args.out}")
    if args.threads is not None:
        if args.threads < 1:
            raise FieldError(f"--threads must be at least 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    sequence = open_sequence(args.data)
    config = TrainConfig(minutes=args.minutes, max_steps=args.steps, every=args.every, seed=args.seed, voxel_size_m=args.voxel_size,
                         coarse_voxel_size_m=args.coarse_voxel_size, eval_frames=args.eval_frames,
                         device=args.device)
    field, report = train_field(sequence, config, progress=not args.quiet)
    report["data"] = str(args.data)
    report["checkpoint"] = str(args.out)
    field.save(args.out)
    report_path = args.out.parent / "field_report.json"
    report_path.write_text(json.dumps(report, indent=1))
    held = report.get("held_out") or {}
    depth = held.get("depth_abs_err_m") or {}
    summary = f"wrote {args.out} ({field!r}) and {report_path}"
    if held:
        summary += (
            f"\nheld-out: PSNR {held['psnr_db']:.2f} dB, depth error median {_cm(depth.get('median'))} / "
            f"p90 {_cm(depth.get('p90'))} ({held['depth_reference']}), opacity on surfaces "
            f"{held['opacity_on_surfaces']:.3f}, unit check R^2 {_num(held['unit_check'].get('r2'))}"
        )
    print(summary)
    return 0


def _cm(value) -> str:
    return "n/a" if value is None else f"{value * 100:.2f} cm"


def _num(value) -> str:
    return "n/a" if value is None else f"{value:.4f}"


def add_export_nerfstudio(subparsers) -> None:
    p = subparsers.add_parser(
        "export-nerfstudio",
        help="write a posed RGB-D sequence as a nerfstudio dataset (transforms.json + images + depth)",
        description="Write transforms.json (OpenGL cameras, fl_x fl_y cx cy w h, transform_matrix and "
        "depth_file_path per frame), images/ and depth/ (16-bit millimetre PNG) so the sequence can be "
        "trained with `ns-train depth-nerfacto --data OUT`.",
    )
    p.add_argument("data", type=Path, help="sequence folder (TUM layout, with ground-truth poses)")
    p.add_argument("out", type=Path, help="output folder (created)")
    p.add_argument("--every", type=int, default=1, help="keep every K-th frame (the paper kept every 2nd)")
    p.set_defaults(func=run_export_nerfstudio)


def run_export_nerfstudio(args) -> int:
    from .nerfstudio import export_nerfstudio

    sequence = open_sequence(args.data)
    path = export_nerfstudio(sequence, args.out, every=args.every, progress=True)
    count = len(json.loads(path.read_text())["frames"])
    print(f"wrote {count} frames to {path}; train with: ns-train depth-nerfacto --data {args.out}")
    return 0
