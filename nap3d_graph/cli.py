"""The ``nap3d-graph`` command line: one console script, one subcommand per job.

This is the only module that prints or configures logging handlers. Known errors (bad
input files, missing optional dependencies) end with a one-line message and exit code 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger("nap3d_graph")

EPILOG = """examples:
  nap3d-graph run                                  # the embedded default, end to end
  nap3d-graph simulate data/room_map --frames 300 --path mapping --scene-seed 0 --seed 1
  nap3d-graph simulate data/room_walk --frames 150 --path traverse --scene-seed 0 --seed 2
  nap3d-graph train-field data/room_map --out room.pt --minutes 5
  nap3d-graph run --traj sim --data data/room_walk --field room.pt
  nap3d-graph run --traj tum --data rgbd_dataset_freiburg1_xyz --field fr1.pt --odom noisy
  nap3d-graph eval-k data/room_walk --field oracle --scenarios 40 --out evalk
"""


def _add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="render a simulated RGB-D sequence in the TUM layout",
        description="Render a procedural room along a camera path and write it as a TUM RGB-D "
        "sequence (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt) plus drifting "
        "odometry.txt, imu.txt, intrinsics.json and scene.json (rebuilds the oracle field).",
    )
    p.add_argument("out", type=Path, help="output folder (created)")
    p.add_argument("--frames", type=int, default=150, help="number of RGB-D frames (default 150)")
    p.add_argument("--scene-seed", type=int, default=0, help="picks the room (default 0)")
    p.add_argument("--seed", type=int, default=0, help="picks the path and all sensor noise (default 0)")
    p.add_argument("--path", choices=("traverse", "mapping"), default="traverse",
                   help="traverse: a walk that never revisits a place; mapping: a survey for "
                   "training a field (default traverse)")
    p.add_argument("--fps", type=float, default=15.0, help="frame rate in Hz (default 15)")
    p.add_argument("--width", type=int, default=640, help="image width in pixels (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height in pixels (default 480)")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args) -> int:
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    if args.frames < 2:
        raise _UsageError(f"--frames must be at least 2, got {args.frames}")
    config = SimConfig(frames=args.frames, scene_seed=args.scene_seed, seed=args.seed, path=args.path,
                       fps=args.fps, width=args.width, height=args.height)
    out = simulate_sequence(args.out, config, progress=True)
    print(f"wrote {args.frames} frames ({args.path}, room {args.scene_seed}, seed {args.seed}) to {out}")
    return 0


class _UsageError(Exception):
    """A bad argument the user can fix."""


def _other_builders():
    """Subcommands defined next to the code they run (imported lazily when called)."""
    from nap3d_graph.evaluation.commands import add_eval_j, add_eval_k
    from nap3d_graph.run_command import add_run

    builders = [add_run, add_eval_k, add_eval_j]
    try:
        from nap3d_graph.fields.commands import add_export_nerfstudio, add_train_field

        builders += [add_train_field, add_export_nerfstudio]
    except ImportError:  # pragma: no cover - the fields package always ships
        pass
    return builders


_BUILDERS = [_add_simulate]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nap3d-graph",
        description="Remove odometry drift with NAP3D (NeRF-assisted 3D-3D alignment) in a GTSAM graph.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for builder in [*_BUILDERS, *_other_builders()]:
        builder(sub)
    return parser


def _known_errors() -> tuple[type[BaseException], ...]:
    errors: list[type[BaseException]] = [_UsageError, FileNotFoundError]
    from nap3d_graph.camera import CameraError
    from nap3d_graph.fields import FieldError
    from nap3d_graph.run_command import RunError

    errors += [CameraError, FieldError, RunError]
    try:
        from nap3d_graph.datasets import DatasetError

        errors.append(DatasetError)
    except ImportError:  # pragma: no cover - datasets always ships
        pass
    return tuple(errors)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except _known_errors() as exc:
        print(f"nap3d-graph {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
