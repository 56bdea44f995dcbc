"""The figures: the plane a trajectory spans (not always x-y), a log error axis that an
exact first frame does not stretch, one palette for run and compare."""

import numpy as np

from nap3d_graph.plots import COLOURS, colour_of, error_axis_floor, plot_errors, plot_trajectories, view_axes


def _walk(plane: str, n: int = 50) -> np.ndarray:
    """Poses (n, 4, 4) along a loop in ``plane`` ("xy" or "xz"), with a little height."""
    t = np.linspace(0, 2 * np.pi, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    loop = np.stack([2 * np.cos(t), 1.5 * np.sin(t), 0.05 * np.sin(3 * t)], axis=1)
    T[:, :3, 3] = loop if plane == "xy" else loop[:, [0, 2, 1]]
    return T


def test_the_view_is_the_plane_the_trajectory_spans(tmp_path):
    assert view_axes(_walk("xy")[:, :3, 3]) == (0, 1)
    assert view_axes(_walk("xz")[:, :3, 3]) == (0, 2)  # a y-down world, seen from above
    gt = _walk("xz")
    path = plot_trajectories(tmp_path / "t.png", {"odometry": gt + 0.01}, gt)
    assert path.stat().st_size > 10_000


def test_error_axis_floor_ignores_an_exact_first_frame(tmp_path):
    errors = [np.r_[0.0, np.linspace(0.5, 10.0, 99)], np.r_[0.0, np.full(99, 0.2)]]
    floor = error_axis_floor(errors)
    assert 0.05 < floor < 0.2
    gt = _walk("xy")
    est = gt.copy()
    est[1:, 0, 3] += 0.01
    assert plot_errors(tmp_path / "e.png", np.arange(50) / 10.0, {"estimate": est}, gt).stat().st_size > 5_000


def test_run_and_compare_share_colours():
    assert colour_of("odometry only") == colour_of("odometry") == COLOURS["odometry"]
    assert colour_of("with NAP3D") == colour_of("isam2-final") and colour_of("with NAP3D, causal") == colour_of(
        "isam2-causal")
    assert colour_of("something else") is None
