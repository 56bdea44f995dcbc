"""A run's config.yaml reproduces it: a bag run (its --topics), an IMU run (its --imu-noise)
and a windowed run (its --graph-window) each run again from their own config.yaml to the same
trajectory bit for bit; a flag given beside --config wins over the file, even when it gives
the option's default."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from nap3d_graph.cli import main
from nap3d_graph.datasets import SimSequence, read_tum_trajectory
from nap3d_graph.datasets.rosbag_write import write_sequence_bag


@pytest.fixture(scope="module")
def walk(sim_walk):
    return sim_walk(24, seed=2)


def _run(*argv) -> None:
    assert main(["run", *[str(a) for a in argv]]) == 0


def _config(out):
    return yaml.safe_load((out / "latest" / "config.yaml").read_text())


def _same_run(first, again) -> None:
    for name in ("estimate.txt", "odometry.txt"):
        stamps_a, T_a = read_tum_trajectory(first / "latest" / name)
        stamps_b, T_b = read_tum_trajectory(again / "latest" / name)
        np.testing.assert_array_equal(stamps_a, stamps_b)
        np.testing.assert_array_equal(T_a, T_b)  # bit for bit


@pytest.mark.parametrize("case", ["bag", "imu", "window"])
@pytest.mark.slow
def test_a_run_is_reproduced_bit_for_bit_from_its_config(case, walk, tmp_path):
    if case == "bag":
        bag = write_sequence_bag(SimSequence(walk), tmp_path / "walk.bag", ros=1)
        argv = ["--traj", "rosbag", "--data", bag, "--topics", "gt=/tf", "--field", "none", "--odom", "noisy"]
        option, value = "source.topics", "gt=/tf"
    elif case == "imu":
        argv = ["--traj", "sim", "--data", walk, "--field", "oracle", "--odom", "imu", "--render-size", "160x120",
                "--imu-noise", "2e-3 2.4e-4 1e-4 2e-6"]
        option, value = "odometry.imu_noise", "2e-3 2.4e-4 1e-4 2e-6"
    else:
        argv = ["--traj", "sim", "--data", walk, "--field", "oracle", "--odom", "noisy", "--render-size", "160x120",
                "--keyframe-every", "2", "--graph-window", "4"]
        option, value = "graph.window", 4
    first, again = tmp_path / "first", tmp_path / "again"
    _run(*argv, "--out", first)
    written = _config(first)

    def recorded(config):
        section, name = option.split(".")
        return config["settings"][section][name]

    assert recorded(written) == value
    _run("--config", first / "latest" / "config.yaml", "--out", again)
    _same_run(first, again)
    reproduced = _config(again)
    assert recorded(reproduced) == value
    assert reproduced["settings"]["output"]["out"] == str(again)  # given: the flag wins
    assert {**reproduced["settings"], "output": None} == {**written["settings"], "output": None}
    assert reproduced["resolved"] == written["resolved"]


@pytest.mark.slow
def test_flags_beside_config_win_even_at_their_default(walk, tmp_path):
    first = tmp_path / "first"
    _run("--traj", "sim", "--data", walk, "--field", "oracle", "--odom", "noisy", "--render-size", "160x120",
         "--keyframe-every", "2", "--graph-window", "4", "--out", first)
    config = first / "latest" / "config.yaml"
    _run("--config", config, "--graph-window", "6", "--out", tmp_path / "b")
    assert _config(tmp_path / "b")["settings"]["graph"]["window"] == 6
    # --keyframe-every 5 is the default: given, it still wins over the file's 2.
    _run("--config", config, "--keyframe-every", "5", "--graph-window", "0", "--out", tmp_path / "c")
    settings = _config(tmp_path / "c")["settings"]
    assert settings["keyframes"]["every"] == 5 and settings["graph"]["window"] == 0
