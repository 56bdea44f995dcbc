"""``nap3d-graph study``: train on one part of a recording, correct the rest, evaluate it."""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.sweep.study import StudySettings, run_study

from .binding import Option, add_options, settings_from_args
from .common import RUN_MATCHER, TOPICS_OPTION, UsageError, empty_or_new_dir, matcher_option, positive_int
from .options import add_force
from .run_config import apply_config


def add_parser(sub) -> None:
    p = sub.add_parser(
        "study",
        help="the study of one recording: field on the first part, drift correction and Evaluation K on the rest",
        description="Build a field on the first part of a recording with ground truth (--split, default the first "
        "half), then on the rest, which the field never saw: drift correction with visual odometry and with noise "
        "injected on the ground-truth increments, and Evaluation K. Or, with --map A --query B, build the field on "
        "one recording and correct another of the same place (checked to share its world frame). Writes one "
        "folder: field.pt, field_report.json, runs/vo, runs/noisy, eval_k/, summary.md and summary.json.",
    )
    add_options(p, STUDY_OPTIONS, StudySettings())
    p.add_argument("--out", type=Path, required=True, help="output folder (must be empty unless --force)")
    add_force(p)
    p.add_argument("--config", type=Path, metavar="CONFIG.yaml",
                   help="reproduce a study from the config.yaml it wrote: its recordings, frames and settings, "
                   "except the options given here (--out is always given)")
    p.set_defaults(parser=p)
    p.set_defaults(func=run)


def _odometries(text: str) -> tuple[str, ...]:
    return tuple(o.strip() for o in text.split(",") if o.strip())


#: The study's options, bound to its settings tree (StudySettings) by one table.
STUDY_OPTIONS: tuple[Option, ...] = (
    Option("data", "recordings.data", type=Path, nargs="?", help="a recording with ground truth (TUM layout, "
           "simulated, 7-Scenes), split in time; or use --map and --query"),
    Option("--map", "recordings.map", dest="map_data", type=Path, metavar="REC_A",
           help="the recording the field is built from (with --query)"),
    Option("--map-frames", "recordings.map_frames", metavar="START:STOP", help="--map: its frames to use (default all)"),
    Option("--query", "recordings.query", type=Path, metavar="REC_B", help="the recording corrected with --map's field"),
    Option("--query-frames", "recordings.query_frames", metavar="START:STOP",
           help="--query: its frames to correct (default all)"),
    Option("--split", "study.split", type=float,
           help="fraction of the frames the field is built on (default %(default)s)"),
    Option("--model", "study.model", choices=("grid", "splat", "views"),
           help="field model (default %(default)s; see train-field --help)"),
    Option("--train-steps", "study.train_steps", type=positive_int, help="grid: training steps (default: 5 minutes)"),
    Option("--keyframe-every", "study.keyframe_every", type=positive_int,
           help="a correction every N frames (default %(default)s)"),
    Option("--scenarios", "study.eval_k_scenarios", type=positive_int,
           help="Evaluation K scenarios (default %(default)s)"),
    Option("--eval-k-full", "study.eval_k_full", action="store_true",
           help="all 16 cells of Evaluation K (blur x intrinsics), not only CLEAN / no blur"),
    Option("--odom", "study.odometries", setting=_odometries, option=",".join,
           help="odometries to run, comma-separated (default %(default)s)"),
    Option("--seed", "study.seed", type=int,
           help="seed of the training, the odometry noise and Evaluation K's scenarios (default %(default)s)"),
    Option("--matcher", "study.matcher", **matcher_option(RUN_MATCHER)),
    Option("--topics", "study.topics", **TOPICS_OPTION),
)


def run(args) -> int:
    if args.config is not None:
        apply_config(args, args.config, StudySettings, "study", older_section="study")
    if not 0.05 <= args.split <= 0.95:
        raise UsageError(f"--split must be in [0.05, 0.95], got {args.split}")
    odometries = _odometries(args.odom)
    unknown = [o for o in odometries if o not in ("vo", "dense", "noisy", "recorded")]
    if unknown or not odometries:
        raise UsageError(f"--odom: unknown {unknown or 'empty list'}; choose from vo, dense, noisy, recorded")
    if (args.map_data is None) != (args.query is None):
        raise UsageError("--map and --query go together (a field from one recording, the other corrected)")
    if (args.data is None) == (args.map_data is None):
        raise UsageError("give one recording (split in time) or --map REC_A --query REC_B, not both")
    empty_or_new_dir(args.out, args.force)
    config = settings_from_args(args, getattr(args, "config_settings", None) or StudySettings()).study
    if args.map_data is not None:
        run_study(args.map_data, args.out, config, query=args.query, map_frames=args.map_frames,
                  query_frames=args.query_frames)
    else:
        run_study(args.data, args.out, config)
    print((args.out / "summary.md").read_text())
    print(f"study in {args.out}/ (summary.md, summary.json, config.yaml, field.pt, runs/, eval_k/)")
    return 0
