"""``nap3d-graph study``: train on one part of a recording, correct the rest, evaluate it."""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.sweep.study import StudySettings, odometry_list, run_study

from .binding import Option, add_options, flag_options, settings_from_args
from .common import UsageError, empty_or_new_dir
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


#: The study's options, generated from its settings tree (each field of StudySettings declares its flag).
STUDY_OPTIONS: tuple[Option, ...] = flag_options(StudySettings)


def run(args) -> int:
    if args.config is not None:
        apply_config(args, args.config, StudySettings, "study", older_section="study")
    if not 0.05 <= args.split <= 0.95:
        raise UsageError(f"--split must be in [0.05, 0.95], got {args.split}")
    odometries = odometry_list(args.odom)
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
