"""The embedded default's inputs: a simulated room, its survey and traversal, a trained field.

``nap3d-graph run`` with no data runs end to end with nothing downloaded: the default room's
mapping survey and a separate traversal that never revisits a place (both simulated once and
cached, keyed by their settings), and a torch field trained on the survey for a fixed number
of steps (cached, keyed by the survey and the budget), with the camera's capture timing
estimated from the survey as for any recording. A step budget, not minutes, so the field and
every figure of the default run are the same on any machine.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

from nap3d_graph.datasets import open_sequence
from nap3d_graph.fields import load_field
from nap3d_graph.fields.build import build_field
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

__all__ = ["DEFAULT_SCENE_SEED", "DEFAULT_MAPPING", "DEFAULT_TRAVERSE", "DEFAULT_TRAIN_STEPS",
           "embedded_default_inputs"]

log = logging.getLogger(__name__)

DEFAULT_SCENE_SEED = 0
DEFAULT_MAPPING = {"frames": 240, "seed": 1, "path": "mapping", "width": 320, "height": 240}
DEFAULT_TRAVERSE = {"frames": 240, "seed": 2, "path": "traverse", "width": 320, "height": 240}
#: About two minutes of training on the 2-core reference machine.
DEFAULT_TRAIN_STEPS = 1200


def _key(d: dict) -> str:
    return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:10]


def _cached_sequence(cache: Path, settings: dict, progress: bool, say) -> Path:
    """Simulate once per settings; a ``.complete`` marker guards against half-written data."""
    folder = cache / "data" / f"room{settings['scene_seed']}_{settings['path']}_{_key(settings)}"
    if (folder / ".complete").exists():
        log.info("reusing simulated %s", folder)
        return folder
    say(f"simulating the {settings['path']} sequence ({settings['frames']} frames) into {folder}")
    simulate_sequence(folder, SimConfig(**settings), progress=progress)
    (folder / ".complete").write_text("ok\n")
    return folder


def _cached_field(cache: Path, mapping: Path, steps: int, progress: bool, settings: dict, say):
    key = _key({"mapping": settings, "steps": steps})
    path = cache / "fields" / f"room{settings['scene_seed']}_{key}.pt"
    if path.exists():
        log.info("reusing trained field %s", path)
        field = load_field(path)
        # Fields cached before they recorded their recording: name it now, so the traversal's
        # frames (same stamps, another recording) are not reported as trained on.
        field.meta.setdefault("train_recording", open_sequence(mapping).recording_id)
        return field, path, None
    say(f"training the field on the survey for {steps} steps (cached for later runs as {path})")
    path.parent.mkdir(parents=True, exist_ok=True)
    field, report = build_field(open_sequence(mapping), "grid", steps=steps, progress=progress)
    field.save(path)
    path.with_suffix(".report.json").write_text(json.dumps(report, indent=1, default=float))
    return field, path, report


def embedded_default_inputs(cache: Path, train_steps: int = DEFAULT_TRAIN_STEPS, progress: bool = True,
                            say=log.info):
    """Simulate (or reuse) the default room's survey and traversal and train (or reuse) its
    field. ``say(message)`` hears about the long steps (the CLI prints them). Returns
    ``(traverse_folder, field, field_path, training_report or None)``."""
    mapping = _cached_sequence(cache, {"scene_seed": DEFAULT_SCENE_SEED, **DEFAULT_MAPPING}, progress, say)
    traverse = _cached_sequence(cache, {"scene_seed": DEFAULT_SCENE_SEED, **DEFAULT_TRAVERSE}, progress, say)
    field, field_path, report = _cached_field(cache, mapping, train_steps, progress,
                                              {"scene_seed": DEFAULT_SCENE_SEED, **DEFAULT_MAPPING}, say)
    return traverse, field, field_path, report
