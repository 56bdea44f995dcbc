"""A map grown by another day's survey (``map NEW --extend MAP``): the new survey found in the
map and joined to it in one graph with the map held, new fields where it saw new space, the
merged map relocalising frames of both; a survey of another place refused in one line with
the map untouched."""

import hashlib
import json

import numpy as np
import pytest

from nap3d_graph.conventions import inv_T
from nap3d_graph.mapping.build import MapSettings, build_map
from nap3d_graph.mapping.extend import (
    CrossPair,
    ExtendSettings,
    MapExtensionRefused,
    extend_map,
    place_survey,
    unseen_frames,
)

SETTINGS = MapSettings(matcher="sift", keyframe_every=2, model="splat")


def _walk(sim_walk):
    # A walk through simulated room 3 at 15 Hz: its first 36 frames are the map, frames 24-47
    # the next day's survey (12 frames seen both days, 12 only the second).
    return sim_walk(48, fps=15.0, seed=0, width=320, height=240, path="mapping", scene_seed=3)


@pytest.fixture(scope="module")
def first_day(sim_walk, tmp_path_factory):
    from nap3d_graph.datasets import open_sequence

    out = tmp_path_factory.mktemp("extend") / "map"
    build_map(open_sequence(_walk(sim_walk), frames="0:36"), out, SETTINGS, progress=False)
    return out


def _digest(folder) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_second_days_survey_joins_the_map_where_the_ground_truth_puts_it(first_day, sim_walk, tmp_path):
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.start import map_relocaliser
    from nap3d_graph.trajectory import read_tum_trajectory

    before = _digest(first_day)
    second = open_sequence(_walk(sim_walk), frames="24:48")
    # seen_m 0: every frame counts as new space, so the extension trains a field of its own.
    result = extend_map(second, first_day, tmp_path / "grown", SETTINGS, ExtendSettings(seen_m=0.0, min_new_frames=20),
                        progress=False, mesh=False)
    assert _digest(first_day) == before  # the first day's map is untouched
    assert not any(p.name.startswith(f".{first_day.name}.extend") for p in first_day.parent.iterdir())
    record = result.info["extensions"][0]
    assert record["accepted"] >= 20 and record["new_submaps"] == [1], record

    # Its frames in the map's frame against the ground truth moved there by the first day's alignment.
    T_gt_map = np.asarray(json.loads((first_day / "survey_ate.json").read_text())["T_gt_map"])
    stamps, T_map_cam = read_tum_trajectory(result.folder / record["folder"] / "poses_in_map.txt")
    by_stamp = dict(zip(np.round(second.timestamps, 6), second.T_world_cam_gt))
    errors = [np.linalg.norm((inv_T(T_gt_map) @ by_stamp[round(float(t), 6)])[:3, 3] - T[:3, 3])
              for t, T in zip(stamps, T_map_cam)]
    # Through the first day's alignment, so its own survey error (2-3 cm here) is in them too.
    first_ate = json.loads((first_day / "survey_ate.json").read_text())["map"]["rmse_m"]
    assert len(errors) == 24 and np.median(errors) < 0.04 and max(errors) < 0.08, (first_ate, np.round(errors, 3))

    # The map's keyframes held where they were, the new ones after them; both days' fields.
    old_keys = np.load(first_day / "keyframe_poses.npy")
    grown_keys = np.load(result.folder / "keyframe_poses.npy")
    np.testing.assert_allclose(grown_keys[: len(old_keys)], old_keys, atol=1e-9)
    assert len(grown_keys) == len(old_keys) + record["keyframes"]
    field = resolve_field(str(result.folder))
    assert [s.survey for s in field.submaps] == [0, 1] and all(s.look_points is not None for s in field.submaps)
    # Frames of the second day's own stretch are found in the grown map, where the truth is.
    relocaliser = map_relocaliser(result.folder, field, "sift", second.intrinsics)
    found = []
    for i in (0, 6, 12, 18):
        answer = relocaliser.locate(second[i])
        if answer.success:
            found.append(np.linalg.norm((inv_T(T_gt_map) @ second.T_world_cam_gt[i])[:3, 3] - answer.T_map_cam[:3, 3]))
    assert len(found) >= 2 and max(found) < 0.08, found


def test_a_survey_of_another_place_is_refused_in_one_line_and_the_map_is_untouched(first_day, sim_walk, tmp_path,
                                                                                capsys):
    from nap3d_graph.cli import main

    before = _digest(first_day)
    other = sim_walk(16, fps=15.0, seed=0, width=320, height=240, path="mapping", scene_seed=11)
    code = main(["map", str(other), "--extend", str(first_day), "--out", str(tmp_path / "grown"), "--matcher", "sift",
                 "--keyframe-every", "2", "--model", "splat", "--no-mesh", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "not found in the map" in err[-1], err
    assert _digest(first_day) == before and not (tmp_path / "grown").exists()
    assert not any(p.name.startswith(f".{first_day.name}.extend") for p in first_day.parent.iterdir())


def _pair(new: int, x_m: float, status: str = "verified") -> CrossPair:
    anchor = np.eye(4)
    anchor[0, 3] = x_m
    return CrossPair(new, 0, inliers=50, anchor=anchor, status=status)


def test_placement_takes_the_agreeing_group_and_refuses_another_place_or_two_places():
    pairs = [_pair(k, 0.01 * k) for k in range(4)] + [_pair(4, 5.0), _pair(5, 0.0, "refused")]
    anchor = place_survey(pairs, ExtendSettings())
    assert abs(anchor[0, 3] - 0.0) < 1e-9 and [p.status for p in pairs[:5]] == ["placement"] * 4 + ["look-alike"]
    # Twin rooms: two groups as large, 5 m apart.
    with pytest.raises(MapExtensionRefused, match="two places"):
        place_survey([_pair(k, 0.0) for k in range(4)] + [_pair(k, 5.0) for k in range(4, 7)], ExtendSettings())
    # Too few agreeing keyframes (the same keyframe twice counts once).
    with pytest.raises(MapExtensionRefused, match="not found"):
        place_survey([_pair(0, 0.0), _pair(0, 0.01), _pair(1, 0.02)], ExtendSettings())
    with pytest.raises(MapExtensionRefused, match="none of 1 pairs"):
        place_survey([_pair(0, 0.0, "refused")], ExtendSettings())


def test_only_frames_far_from_every_map_keyframe_are_new_space():
    T_key = np.tile(np.eye(4), (3, 1, 1))
    T_key[:, 0, 3] = [0.0, 0.5, 1.0]
    T_new = np.tile(np.eye(4), (4, 1, 1))
    T_new[:, 0, 3] = [0.2, 1.2, 2.0, 3.0]
    T_new[1, :3, :3] = np.array([[-1, 0, 0], [0, 1, 0], [0, 0, -1.0]])  # beside a keyframe, looking back
    T_new[3] = np.nan  # unposed: neither
    assert unseen_frames(T_new, T_key, ExtendSettings()).tolist() == [1, 2]
