"""``nap3d-graph study``: train on one part of a recording, correct the rest, evaluate it."""

from __future__ import annotations

from pathlib import Path

from .common import RUN_MATCHER, UsageError, add_matcher_argument, add_topics_argument, empty_or_new_dir, positive_int
from .options import add_force, add_seed


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
    p.add_argument("--model", choices=("grid", "splat", "views"), default="grid",
                   help="field model (default grid; see train-field --help)")
    p.add_argument("--train-steps", type=positive_int, default=None, help="grid: training steps (default: 5 minutes)")
    p.add_argument("--keyframe-every", type=positive_int, default=5, help="a correction every N frames (default 5)")
    p.add_argument("--scenarios", type=positive_int, default=40, help="Evaluation K scenarios (default 40)")
    p.add_argument("--eval-k-full", action="store_true",
                   help="all 16 cells of Evaluation K (blur x intrinsics), not only CLEAN / no blur")
    p.add_argument("--odom", default="vo,noisy", help="odometries to run, comma-separated (default vo,noisy)")
    add_seed(p, "the training, the odometry noise and Evaluation K's scenarios")
    add_matcher_argument(p, RUN_MATCHER)
    add_force(p)
    p.add_argument("--config", type=Path, metavar="CONFIG.yaml",
                   help="reproduce a study from the config.yaml it wrote: its recordings, frames and settings, "
                   "except the options given here (--out is always given)")
    add_topics_argument(p)
    p.set_defaults(parser=p)
    p.set_defaults(func=run)


#: config.yaml key -> study option (argparse dest); the settings are under "study".
_RECORDINGS = {"data": "data", "map": "map_data", "map_frames": "map_frames", "query": "query",
               "query_frames": "query_frames"}
_SETTINGS = {"split": "split", "model": "model", "train_steps": "train_steps", "keyframe_every": "keyframe_every",
             "eval_k_scenarios": "scenarios", "eval_k_full": "eval_k_full", "seed": "seed", "matcher": "matcher",
             "topics": "topics"}


def _apply_config(args, path: Path) -> None:
    """Set every option the command line left at its default from a study's config.yaml."""
    from .run_config import load_config_file, set_unless_given

    config = load_config_file(path, "study", "study")
    values = {dest: config.get(key) for key, dest in _RECORDINGS.items()}
    values = {k: (Path(v) if k in ("data", "map_data", "query") and v is not None else v) for k, v in values.items()}
    values.update({dest: config["study"][key] for key, dest in _SETTINGS.items() if key in config["study"]})
    if "odometries" in config["study"]:
        values["odom"] = ",".join(config["study"]["odometries"])
    set_unless_given(args, args.parser, values)


def run(args) -> int:
    from nap3d_graph.evaluation.study import StudyConfig, run_study

    if args.config is not None:
        _apply_config(args, args.config)
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
    print(f"study in {args.out}/ (summary.md, summary.json, config.yaml, field.pt, runs/, eval_k/)")
    return 0
