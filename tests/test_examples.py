"""The examples run and do what they say."""

import runpy
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_nap3d_factor_in_your_graph(capsys):
    main = runpy.run_path(str(EXAMPLES / "nap3d_factor_in_your_graph.py"))["main"]
    out = main()
    assert out["odometry_error_m"] > 0.1
    last = max(out["optimised_error_m"])
    assert out["optimised_error_m"][last] < 0.005
    assert "NAP3D:" in capsys.readouterr().out
