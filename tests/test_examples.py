"""The examples run and do what they say."""

import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_nap3d_factor_in_your_graph(capsys):
    main = runpy.run_path(str(EXAMPLES / "nap3d_factor_in_your_graph.py"))["main"]
    out = main()
    assert out["odometry_error_m"] > 0.1
    last = max(out["optimised_error_m"])
    assert out["optimised_error_m"][last] < 0.005
    assert "NAP3D:" in capsys.readouterr().out


def test_own_estimator_runs_next_to_the_library_ones(capsys):
    rows = runpy.run_path(str(EXAMPLES / "own_estimator.py"))["main"]()
    by_name = {r["estimator"]: r for r in rows}
    assert set(by_name) == {"odometry", "complementary", "eskf", "isam2-causal", "isam2-final"}
    for name in ("complementary", "eskf", "isam2-final"):
        assert by_name[name]["ate_rmse_m"] < 0.3 * by_name["odometry"]["ate_rmse_m"]
    assert "complementary" in capsys.readouterr().out


@pytest.mark.slow
def test_your_frames_in_your_isam2(capsys):
    """Real fr1/xyz frames read with OpenCV, a splat map of the even frames, the odd ones in a
    plain iSAM2 loop with gated NAP3D priors: the drifting odometry is pulled back."""
    out = runpy.run_path(str(EXAMPLES / "your_frames_in_your_isam2.py"))["main"]()
    assert out["accepted"] >= 4
    assert out["odometry_error_m"] > 0.015 and out["estimate_error_m"] < 0.5 * out["odometry_error_m"]
    assert "accepted" in capsys.readouterr().out
