"""The run's report that says whether it worked without ground truth: on a good run nothing
is past its bad line; a field of another room and a run that never finds its map move the
figure meant to reveal them past it (the map's report: tests/test_mapping.py)."""

from __future__ import annotations

import numpy as np
import pytest

from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.run.report import run_report, write_run_report
from nap3d_graph.sims.sensors import OdometryNoise

DRIFT = OdometryNoise(bias_init=(0.0, 0.0, 0.01, 0.03, 0.0, 0.01), heading_bias_rad_s=0.02)
CONFIG = PipelineConfig(keyframe_every=4, render_width=None, render_height=None, progress=False)


@pytest.fixture(scope="module")
def walk(sim_walk):
    from nap3d_graph.datasets import open_sequence

    return open_sequence(sim_walk(40, odometry=DRIFT))


def _run(sequence, field):
    return Pipeline(sequence, field, make_odometry("recorded", sequence), CONFIG).run()


def test_a_good_run_is_good_and_a_field_of_another_room_is_told(walk, tmp_path):
    from nap3d_graph.sims.scene import OracleField, make_scene

    good = _run(walk, walk.oracle_field())
    report = write_run_report(tmp_path, good.keyframes, {})
    assert report.bad == [], report.rows
    text = (tmp_path / "report.md").read_text()
    assert "Nothing is past its bad line" in text and (tmp_path / "corrections.png").is_file()
    d2 = [k.gate_d2 for k in good.keyframes if np.isfinite(k.gate_d2)]
    assert len(d2) >= 5 and np.median(d2) < 16.8
    # The same walk against another room's field: the corrections are refused, and the
    # report says so (not covered, or covered and refused).
    other = _run(walk, OracleField(make_scene(3)))
    bad = run_report(other.keyframes, {}).bad
    assert any(figure.startswith(("corrections accepted", "map coverage")) for figure in bad), bad


def test_a_run_never_placed_in_its_map_is_told(walk):
    metrics = {"map": {"placement": {"placed": False, "placed_at_frame": None}, "recoveries": []}}
    report = run_report([], metrics)
    assert "placed in the map" in report.bad
    placed = run_report([], {"map": {"placement": {"placed": True, "placed_at_frame": 5}, "recoveries": []}})
    assert "placed in the map" not in placed.bad


def test_gate_consistency_is_two_sided(walk):
    """The same run's d2 as if its covariances were 10x too small (d2 x10) or 10x too large
    (d2 / 10): each past its own side's line, saying which side and by about what factor; the
    run as it is within both lines."""
    from nap3d_graph.run.report import consistency

    good = _run(walk, walk.oracle_field())
    d2 = np.array([k.gate_d2 for k in good.keyframes if np.isfinite(k.gate_d2)])
    value, line, verdict = consistency(d2)
    assert verdict is True and line.startswith("0.87 - 16.8"), (value, line)
    value, _, verdict = consistency(d2 * 10)
    assert verdict is False and "too confident" in value, value
    value, _, verdict = consistency(d2 / 10)
    assert verdict is False and "too cautious" in value, value
    # The run: median 0.78 over 40, about seven times too cautious.
    value, _, verdict = consistency(np.full(40, 0.78))
    assert verdict is False and "about 7x larger" in value, value
    assert consistency(np.array([]))[2] is None
