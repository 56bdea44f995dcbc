"""Shared fixtures: a small simulated room and the real TUM frames in tests/data.

A test may skip only when an *optional extra* is missing (nerfstudio): its reason must
start with ``OPTIONAL_EXTRA``. Any other skip fails the run, so a missing fixture file or a
forgotten ``skipif`` cannot hide a test (a clone has everything the suite needs).
"""

from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parent / "data"
TUM_FR1_XYZ = DATA / "tum" / "rgbd_dataset_freiburg1_xyz"
TUM_FR1_DESK = DATA / "tum" / "rgbd_dataset_freiburg1_desk"
OPTIONAL_EXTRA = "optional extra not installed:"

_forbidden_skips: list[str] = []


@pytest.fixture(scope="session")
def tum_path() -> Path:
    """The first 12 frames of TUM fr1/xyz (tests/data/tum/README.md)."""
    assert (TUM_FR1_XYZ / "rgb.txt").is_file(), f"test data missing: {TUM_FR1_XYZ}"
    return TUM_FR1_XYZ


@pytest.fixture(scope="session")
def sim_walk(tmp_path_factory):
    """``sim_walk(frames, fps=6.0, seed=4, width=160, height=120, **settings) -> Path``: a
    simulated walk through the hold-out room 11 (TUM layout, ideal capture timing unless
    ``timing`` is given), written once per session for each distinct setting: tests that ask
    for the same walk share one folder (read it with ``SimSequence``; do not write into it)."""
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    made: dict[tuple, Path] = {}

    def make(frames: int, fps: float = 6.0, seed: int = 4, width: int = 160, height: int = 120, **settings) -> Path:
        config = {"frames": frames, "fps": fps, "seed": seed, "width": width, "height": height, "scene_seed": 11,
                  "timing": None, **settings}
        key = tuple(sorted((k, repr(v)) for k, v in config.items()))
        if key not in made:
            made[key] = simulate_sequence(tmp_path_factory.mktemp("walk") / "walk", SimConfig(**config))
        return made[key]

    return make


@pytest.fixture(scope="session")
def field_survey(tmp_path_factory):
    """The small survey the field tests build their fields from (room 0's mapping path,
    100 frames at 128x96), simulated once per session; read it, do not write into it."""
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    folder = tmp_path_factory.mktemp("fields") / "survey"
    simulate_sequence(folder, SimConfig(frames=100, path="mapping", scene_seed=0, seed=5, width=128, height=96))
    return open_sequence(folder)


@pytest.fixture(scope="session")
def room():
    """A hold-out procedural room (not the default one) and its oracle field."""
    from nap3d_graph.sims.scene import OracleField, make_scene

    scene = make_scene(11)
    return scene, OracleField(scene)


def pytest_runtest_logreport(report):
    if report.skipped:
        reason = str(report.longrepr[2]) if isinstance(report.longrepr, tuple) else str(report.longrepr)
        if OPTIONAL_EXTRA not in reason:
            _forbidden_skips.append(f"{report.nodeid}: {reason}")


def pytest_sessionfinish(session, exitstatus):
    if _forbidden_skips and session.exitstatus == 0:
        session.exitstatus = 1


def pytest_terminal_summary(terminalreporter):
    if _forbidden_skips:
        terminalreporter.write_line("")
        terminalreporter.write_line("tests skipped for a reason other than a missing optional extra (a failure):",
                                    red=True)
        for line in _forbidden_skips:
            terminalreporter.write_line(f"  {line}", red=True)
