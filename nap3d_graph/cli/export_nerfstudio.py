"""``nap3d-graph export-nerfstudio``: a posed RGB-D sequence as a nerfstudio dataset."""

from __future__ import annotations

import json
from pathlib import Path

from nap3d_graph.arguments import positive_int
from nap3d_graph.datasets import open_sequence
from nap3d_graph.fields.nerfstudio_export import export_nerfstudio

from .common import add_frames_argument, empty_or_new_dir
from .options import add_force


def add_parser(sub) -> None:
    p = sub.add_parser(
        "export-nerfstudio",
        help="write a posed RGB-D sequence as a nerfstudio dataset (transforms.json + images + depth)",
        description="Write transforms.json (OpenGL cameras, fl_x fl_y cx cy w h, transform_matrix and "
        "depth_file_path per frame), images/ and depth/ (16-bit millimetre PNG) so the sequence can be "
        "trained with `ns-train depth-nerfacto --data OUT`.",
    )
    p.add_argument("data", type=Path, help="sequence folder (TUM layout, with ground-truth poses), or a RealSense "
                   "recording (.bag/.db3) with --poses")
    p.add_argument("--poses", type=Path, metavar="TUM_FILE",
                   help="for a RealSense recording: the camera poses of its frames (TUM file)")
    p.add_argument("out", type=Path, help="output folder (created; must be empty unless --force)")
    p.add_argument("--every", type=positive_int, default=1, help="keep every K-th frame (the paper kept every 2nd)")
    add_frames_argument(p, "the export")
    add_force(p)
    p.set_defaults(func=run)


def run(args) -> int:
    empty_or_new_dir(args.out, args.force)
    sequence = open_sequence(args.data, frames=args.frames, groundtruth=args.poses)
    path = export_nerfstudio(sequence, args.out, every=args.every, progress=True)
    count = len(json.loads(path.read_text())["frames"])
    print(f"wrote {count} frames to {path}; train with: ns-train depth-nerfacto --data {args.out}")
    return 0
