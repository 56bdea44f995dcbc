"""``nap3d-graph study``: train on one part of a recording, correct the rest, evaluate it."""

from __future__ import annotations

from pathlib import Path

from .common import RUN_MATCHER, UsageError, add_matcher_argument, add_topics_argument, empty_or_new_dir, positive_int


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
    p.add_argument("data", type=Path, nargs="?", help="a recording with ground truth (TUM layout, simulated, "
                   "7-Scenes), split in time; or use --map and --query")
    p.add_argument("--map", type=Path, dest="map_data", metavar="REC_A",
                   help="the recording the field is built from (with --query)")
    p.add_argument("--map-frames", metavar="START:STOP", default=None, help="--map: its frames to use (default all)")
    p.add_argument("--query", type=Path, metavar="REC_B", help="the recording corrected with --map's field")
    p.add_argument("--query-frames", metavar="START:STOP", default=None,
                   help="--query: its frames to correct (default all)")
    p.add_argument("--out", type=Path, required=True, help="output folder (must be empty unless --force)")
    p.add_argument("--split", type=float, default=0.5, help="fraction of the frames the field is built on (default 0.5)")
    p.add_argument("--model", choices=("grid", "splat"), default="grid", help="field model (default grid)")
    p.add_argument("--train-steps", type=positive_int, default=None, help="grid: training steps (default: 5 minutes)")
    p.add_argument("--keyframe-every", type=positive_int, default=5, help="a correction every N frames (default 5)")
    p.add_argument("--scenarios", type=positive_int, default=40, help="Evaluation K scenarios (default 40)")
    p.add_argument("--eval-k-full", action="store_true",
                   help="all 16 cells of Evaluation K (blur x intrinsics), not only CLEAN / no blur")
    p.add_argument("--odom", default="vo,noisy", help="odometries to run, comma-separated (default vo,noisy)")
    p.add_argument("--seed", type=int, default=0)
    add_matcher_argument(p, RUN_MATCHER)
    p.add_argument("--force", action="store_true", help="write into a non-empty folder")
    add_topics_argument(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from nap3d_graph.evaluation.study import StudyConfig, run_study

    if not 0.05 <= args.split <= 0.95:
        raise UsageError(f"--split must be in [0.05, 0.95], got {args.split}")
    odometries = tuple(o.strip() for o in args.odom.split(",") if o.strip())
    unknown = [o for o in odometries if o not in ("vo", "dense", "noisy", "recorded")]
    if unknown or not odometries:
        raise UsageError(f"--odom: unknown {unknown or 'empty list'}; choose from vo, dense, noisy, recorded")
    if (args.map_data is None) != (args.query is None):
        raise UsageError("--map and --query go together (a field from one recording, the other corrected)")
    if (args.data is None) == (args.map_data is None):
        raise UsageError("give one recording (split in time) or --map REC_A --query REC_B, not both")
    empty_or_new_dir(args.out, args.force)
    config = StudyConfig(split=args.split, model=args.model, train_steps=args.train_steps,
                         keyframe_every=args.keyframe_every, odometries=odometries, eval_k_scenarios=args.scenarios,
                         eval_k_full=args.eval_k_full, seed=args.seed, matcher=args.matcher,
                         topics=args.topics)
    if args.map_data is not None:
        run_study(args.map_data, args.out, config, query=args.query, map_frames=args.map_frames,
                  query_frames=args.query_frames)
    else:
        run_study(args.data, args.out, config)
    print((args.out / "summary.md").read_text())
    print(f"study in {args.out}/ (summary.md, summary.json, field.pt, runs/, eval_k/)")
    return 0
