"""``nap3d-graph sweep SWEEP.yaml --out DIR``: recordings x settings x seeds, on a pool or on Ray."""

from __future__ import annotations

import argparse
from pathlib import Path

from nap3d_graph.arguments import positive_int
from nap3d_graph.pools import LocalPool, RayPool
from nap3d_graph.sweep.report import write_report
from nap3d_graph.sweep.run import SweepLocked, cell_status, run_sweep
from nap3d_graph.sweep.spec import SweepError, SweepSpec

from . import build_parser, main
from .common import UsageError

__all__ = ["add_parser", "run"]

EXAMPLE = """\
example SWEEP.yaml:
  recordings:
    - data: rgbd_dataset_freiburg1_desk          # field on 0:0.5, corrected 0.5:1
    - {name: kitchen, data: 7scenes/redkitchen/seq-01, split: 0.5}
    - {name: cross, map: data/room_map, query: data/room_walk}   # a map from one recording, another corrected
  field: {model: [splat, grid], steps: 400}      # train-field options; a list is a grid dimension
  run: {matcher: [sift, xfeat], odom: vo}        # run options; a list is a grid dimension
  seeds: [0, 1, 2]                               # run --seed
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "sweep",
        help="many runs: recordings x field and run settings x seeds, resumable, on a process pool or Ray",
        description="Run a grid of drift-correction runs from a YAML file: each field is trained once per "
        "(recording, field settings) and shared by its runs; each cell writes its own folder under "
        "DIR/cells/ (its run, log.txt, result.json); DIR/sweep.csv has one row per cell (with the command that "
        "reproduces it), DIR/summary.md the mean, spread and worst per setting with failures counted, and "
        "DIR/plot_<setting>.png a plot per swept setting. Run the same command again to resume: finished cells "
        "are skipped; a failed cell was retried once and is recorded with its error.",
        epilog=EXAMPLE, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("spec", type=Path, metavar="SWEEP.yaml", help="the sweep (see the example below)")
    p.add_argument("--out", type=Path, required=True, help="the sweep folder (created; resumed when it holds this sweep)")
    p.add_argument("--workers", type=positive_int, default=2,
                   help="tasks at a time on this machine, one core each (default 2); with --ray auto, the CPUs of "
                   "the local Ray instance")
    p.add_argument("--ray", metavar="auto|ADDRESS", default=None,
                   help="run the cells as Ray tasks (extra 'ray'): auto starts a local Ray instance, ADDRESS joins a "
                   "cluster started with 'ray start --head' (recordings and DIR must be on storage every node mounts "
                   "at the same path). Default: a local process pool")
    p.add_argument("--retry-failed", action="store_true", help="run the cells that failed last time again")
    p.add_argument("--report-only", action="store_true", help="rebuild sweep.csv, summary.md and the plots from "
                   "the cells' files, running nothing")
    p.add_argument("--dry-run", action="store_true", help="list the fields and cells (and which are finished)")
    p.set_defaults(func=run)


def _same_sweep(out: Path, spec_path: Path) -> None:
    """A folder holds one sweep: its saved sweep.yaml must be this file's text (an edited file
    is another sweep: give it another folder)."""
    saved = out / "sweep.yaml"
    if saved.is_file() and saved.read_text() != spec_path.read_text():
        raise UsageError(f"{out} holds another sweep (its sweep.yaml differs from {spec_path}): choose another --out")
    if not saved.is_file() and out.is_dir() and any(p for p in out.iterdir() if p.name != "sweep.lock"):
        raise UsageError(f"{out} is not empty and holds no sweep: choose another --out")


def check_argv(argv: list[str]) -> None:
    """Parse ``argv`` with the command line's parser; a bad one raises ValueError (what a
    sweep file's grids are checked with)."""
    try:
        build_parser().parse_args(argv)
    except UsageError as exc:
        raise ValueError(str(exc)) from None


def run(args) -> int:
    try:
        spec = SweepSpec.load(args.spec, check_argv)
    except SweepError as exc:
        raise UsageError(str(exc)) from None
    _same_sweep(args.out, args.spec)
    cells = spec.cells()
    if args.dry_run:
        done = sum(cell_status(args.out, c) is not None for c in cells) if args.out.is_dir() else 0
        print(f"{len(spec.fields())} fields, {len(cells)} cells ({done} finished) in {args.out}")
        for cell in cells:
            print(f"  {cell.id}")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sweep.yaml").write_text(args.spec.read_text())
    counts = None
    if not args.report_only:
        try:
            pool = RayPool(args.ray, args.workers) if args.ray else LocalPool(args.workers)
        except RuntimeError as exc:
            raise UsageError(str(exc)) from None
        try:
            counts = run_sweep(spec, args.out, pool, main, progress=True, retry_failed=args.retry_failed)
        except SweepLocked as exc:
            raise UsageError(str(exc)) from None
        finally:
            pool.close()
    tally = write_report(spec, args.out, counts)
    print((args.out / "summary.md").read_text())
    print(f"sweep in {args.out}/ (sweep.csv, summary.md, plot_*.png, cells/, fields/): {tally['ok']} ok, "
          f"{tally['failed']} failed, {tally['pending']} pending")
    return 0 if tally["failed"] == 0 and tally["pending"] == 0 else 1
