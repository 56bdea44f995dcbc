"""``nap3d-graph simulate``: a procedural room (or a floor of rooms) rendered along a path, in the TUM layout."""

from __future__ import annotations

from pathlib import Path

from nap3d_graph.arguments import positive_float, positive_int
from nap3d_graph.datasets import SimSequence
from nap3d_graph.datasets.realsense_io import import_pyrealsense2
from nap3d_graph.datasets.realsense_sim import write_realsense_recording
from nap3d_graph.datasets.rosbag_write import write_sequence_bag
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

from .common import PartialOutput, StopOnSignal, UsageError, empty_or_new_dir
from .options import add_force


def add_parser(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="render a simulated RGB-D sequence in the TUM layout",
        description="Render a procedural room along a camera path and write it as a TUM RGB-D "
        "sequence (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt) plus drifting "
        "odometry.txt, imu.txt, intrinsics.json and scene.json (rebuilds the oracle field). "
        "Refuses a non-empty folder unless --force.",
    )
    p.add_argument("out", type=Path, help="output folder (created; must be empty unless --force)")
    p.add_argument("--count", type=positive_int, default=150, help="number of RGB-D frames, >= 2 (default %(default)s)")
    p.add_argument("--frames", metavar="N", default=None,
                   help="deprecated: --count N (--frames is a range of frames to read everywhere else)")
    p.add_argument("--scene-seed", type=int, default=0, help="picks the room (default 0)")
    p.add_argument("--seed", type=int, default=0, help="picks the path and all sensor noise (default 0)")
    p.add_argument("--path", choices=("traverse", "mapping"), default="traverse",
                   help="traverse: a walk that never revisits a place; mapping: a survey for "
                   "training a field (default traverse)")
    p.add_argument("--rooms", type=positive_int, default=None, metavar="N",
                   help="a floor of N furnished rooms in a row joined by doors instead of one room; every third room "
                   "is a twin of the one two before it (same furniture, same textures): --scene-seed picks the floor. "
                   "The mapping path surveys it room by room, the traverse crosses it without coming back")
    p.add_argument("--start-room", type=int, default=0, metavar="R",
                   help="with --rooms, a traverse starts in room R (0 = first; default 0)")
    p.add_argument("--end-room", type=int, default=None, metavar="R",
                   help="with --rooms, a traverse ends in room R (default: the far end of the floor)")
    p.add_argument("--look-aside", type=float, default=0.0, metavar="DEG",
                   help="with --rooms, a traverse starts looking DEG to its left at the side wall and turns ahead over "
                   "its first metre (a start that first sees only what a twin room has too; default 0)")
    p.add_argument("--fps", type=positive_float, default=None,
                   help="frame rate in Hz (default 15 for a traverse; 3.75 for a mapping survey: every fourth frame "
                   "of a 15 Hz recording, so the survey's pace and motion blur are realistic)")
    p.add_argument("--width", type=positive_int, default=640, help="image width in pixels (default 640)")
    p.add_argument("--height", type=positive_int, default=480, help="image height in pixels (default 480)")
    p.add_argument("--realsense", type=Path, metavar="FILE.db3",
                   help="also write the traversal as a RealSense recording (depth z16 from a depth camera 15 mm to the "
                   "side, colour rgb8, accel and gyro; FILE.yaml beside it holds the IMU extrinsics and noise): run it "
                   "with --traj realsense --data FILE.db3 --groundtruth OUT/groundtruth.txt --field OUT")
    p.add_argument("--rosbag", type=Path, metavar="FILE.bag|DIR",
                   help="also write the sequence as a ROS bag in TUM's bag layout (colour rgb8, depth 32FC1, camera "
                   "info, IMU, ground truth on /tf): a .bag is ROS 1, any other name a ROS 2 bag folder. Run it with "
                   "--traj rosbag --data FILE.bag --field OUT")
    add_force(p)
    p.set_defaults(func=run)


def run(args) -> int:
    if args.frames is not None:
        args.count = _deprecated_frames(args.frames)
    if args.count < 2:
        raise UsageError(f"--count must be at least 2, got {args.count}")
    if args.realsense is not None:
        if args.realsense.suffix.lower() != ".db3":
            raise UsageError(f"--realsense must name a .db3 file (what pyrealsense2 writes), got {args.realsense}")
        if args.realsense.exists() and not args.force:
            raise UsageError(f"{args.realsense} exists; choose another name, or add --force to replace it")

        import_pyrealsense2()  # a missing libusb is said now, not after the rendering
    if args.rosbag is not None and args.rosbag.exists():
        raise UsageError(f"--rosbag {args.rosbag} exists; a bag is never overwritten: choose another name")
    if args.rooms is None and (args.start_room != 0 or args.end_room is not None or args.look_aside != 0.0):
        raise UsageError("--start-room, --end-room and --look-aside walk across a floor: add --rooms N")
    if args.rooms is not None:
        for name, room in (("--start-room", args.start_room), ("--end-room", args.end_room)):
            if room is not None and not 0 <= room < args.rooms:
                raise UsageError(f"{name} {room} is not on a floor of {args.rooms} room(s) (0 to {args.rooms - 1})")
    empty_or_new_dir(args.out, args.force)
    config = SimConfig(frames=args.count, scene_seed=args.scene_seed, seed=args.seed, path=args.path,
                       fps=args.fps, width=args.width, height=args.height, rooms=args.rooms,
                       start_room=args.start_room, end_room=args.end_room, look_aside_deg=args.look_aside)
    # SIGINT / SIGTERM set a flag the rendering loop reads after each frame (a second one stops
    # at once): raised wherever the main thread is, an interruption can land in the process
    # pool's finalizers, where Python prints and drops it, and the simulation went on to the end.
    with PartialOutput(args.out, f"nap3d-graph simulate {args.out}"), StopOnSignal() as stop:
        out = simulate_sequence(args.out, config, progress=True, stop=stop)
    where = f"room {args.scene_seed}" if args.rooms is None else f"a floor of {args.rooms} rooms, floor {args.scene_seed}"
    print(f"wrote {args.count} frames ({args.path}, {where}, seed {args.seed}) to {out}")
    if args.realsense is not None:
        recording = write_realsense_recording(out, args.realsense, seed=args.seed, progress=True)
        print(f"wrote the RealSense recording {recording} and {recording.with_suffix('.yaml')}; run it with: "
              f"nap3d-graph run --traj realsense --data {recording} --groundtruth {out}/groundtruth.txt --field {out}")
    if args.rosbag is not None:
        bag = write_sequence_bag(SimSequence(out), args.rosbag, ros=1 if args.rosbag.suffix == ".bag" else 2)
        print(f"wrote the ROS bag {bag}; run it with: nap3d-graph run --traj rosbag --data {bag} --field {out}")
    return 0


def _deprecated_frames(text: str) -> int:
    """``simulate --frames N``, the count it was before ``--count``: taken as ``--count N``
    with a warning; a range (what ``--frames`` is everywhere else) is an error."""
    import sys


    try:
        count = int(text)
    except ValueError:
        raise UsageError(f"simulate writes frames, it reads none: --frames {text} is not a count; give --count N") from None
    print(f"warning: simulate --frames N is deprecated (everywhere else --frames is a range to read): taken as "
          f"--count {count}", file=sys.stderr)
    return count
