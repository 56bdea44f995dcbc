"""One keyframe's calls from ``Pipeline.step``, traced as they run: which of the project's
modules they visit and how often they come back to a module already left.

A simulated walk (room 11, recorded odometry, the exact field) runs inline to its third
keyframe; that keyframe's ``Pipeline.step`` is traced with ``sys.setprofile``. Each call from
one project function into a function of another project module is an edge; an edge counts as
a return when the module it enters was entered before in the trace (a part calling back into
the run, or the run's steps hopping between the same modules). Each distinct edge counts once,
however often a loop takes it.

    python benchmarks/keyframe_calls.py --out benchmarks/results/keyframe_calls.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from provenance import write_result

from nap3d_graph.datasets import SimSequence
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

ROOT = Path(__file__).resolve().parents[1]
#: The project's source folders (sims/ and factors/ are installed under the package).
SOURCES = tuple(str(ROOT / name) for name in ("nap3d_graph", "sims", "factors"))


def _module(code) -> str | None:
    """The project module a code object belongs to (None: not the project's)."""
    path = code.co_filename
    if not path.startswith(SOURCES):
        return None
    return str(Path(path).relative_to(ROOT).with_suffix(""))


def trace_step(pipeline: Pipeline, i: int) -> list[tuple[str, str, str, str, bool]]:
    """``Pipeline.step(i)`` traced: each call between project modules as ``(caller module,
    caller function, callee module, callee function, back)``, in the order they were made;
    ``back``: the callee's module is already on the call stack below its caller (a call back
    up into a module that is waiting for what it called)."""
    calls: list[tuple[str, str, str, str, bool]] = []
    stack: list[str | None] = []

    def profile(frame, event, arg):
        if event == "return":
            if stack:
                stack.pop()
            return
        if event != "call":
            return
        callee, caller = _module(frame.f_code), frame.f_back and _module(frame.f_back.f_code)
        if callee and caller and callee != caller:
            calls.append((caller, frame.f_back.f_code.co_qualname, callee, frame.f_code.co_qualname,
                          callee in stack[:-1]))
        stack.append(callee)

    sys.setprofile(profile)
    try:
        pipeline.step(i)
    finally:
        sys.setprofile(None)
    return calls


def returns(calls: list[tuple[str, str, str, str, bool]], start: str) -> dict:
    """The modules visited, the distinct calls between them, those that enter a module
    already entered and those that call back up into a module still on the stack."""
    entered, seen_edges, again, back = {start}, set(), [], []
    for edge in calls:
        if edge in seen_edges:
            continue
        seen_edges.add(edge)
        text = f"{edge[0]}:{edge[1]} -> {edge[2]}:{edge[3]}"
        if edge[2] in entered:
            again.append(text)
        if edge[4]:
            back.append(text)
        entered.add(edge[2])
    return {"modules_visited": len(entered), "edges": len(seen_edges), "returns_to_a_module_left": len(again),
            "calls_back_up_the_stack": len(back), "calls_back": back, "returns": again}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--keyframe", type=int, default=3, help="which keyframe's step to trace (default %(default)s)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        walk = SimSequence(simulate_sequence(Path(tmp) / "walk", SimConfig(frames=20, fps=6.0, seed=4, width=160,
                                                                           height=120, scene_seed=11, timing=None)))
        config = PipelineConfig(keyframe_every=3)
        pipeline = Pipeline(walk, walk.oracle_field(), make_odometry("recorded", walk), config)
        pipeline.start()
        frame = config.keyframe_every * (args.keyframe - 1)
        for i in range(frame):
            pipeline.step(i)
        calls = trace_step(pipeline, frame)
    assert pipeline.keyframe_indices[-1] == frame, "the traced frame was not a keyframe"
    result = {"keyframe_frame": frame, **returns(calls, "nap3d_graph/run/pipeline")}
    write_result(args.out, result, args)
    print(f"frame {frame}: {result['modules_visited']} modules, {result['edges']} distinct calls between modules, "
          f"{result['returns_to_a_module_left']} into a module already entered, "
          f"{result['calls_back_up_the_stack']} back up into a module still waiting on the stack")


if __name__ == "__main__":
    main()
