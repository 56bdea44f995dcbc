"""The run's settings tree: it round-trips through YAML exactly, its defaults are
PipelineConfig's, every run and compare flag is bound to one of its fields with the field's
default, and a config file's tree comes back through the options unchanged; the same for the study."""

from __future__ import annotations

import dataclasses
import math
import typing

import pytest
import yaml

from nap3d_graph.cli import build_parser, command_parsers, main
from nap3d_graph.cli.binding import apply_settings, settings_from_args
from nap3d_graph.cli.run_options import RUN_OPTIONS, SOURCE_OPTIONS
from nap3d_graph.cli.study import STUDY_OPTIONS
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.settings import SECTIONS, RunSettings, SettingsError, pipeline_name
from nap3d_graph.sweep.study import StudySettings

#: PipelineConfig fields no setting sets as it is: the run resolves them (from the render
#: size, the timing switch, NAP3D's settings, the field, the camera's rate, the terminal).
RESOLVED = {"render_width", "render_height", "compensate_timing", "timing", "land_within_s", "overlap",
            "keyframe_when_idle", "progress", "align", "field_error_by_view"}

#: A value other than the default for each option, as typed (a new option needs one here).
SAMPLES = {
    "--traj": "tum", "--data": "some/folder", "--topics": "gt=/tf", "--groundtruth": "gt.txt",
    "--realsense-config": "rs.yaml", "--record": "live.bag", "--seconds": "12.5", "--frames": "10:200",
    "--depth-scale": "1000", "--stamps": "file-order", "--fps": "30",
    "--field": "oracle", "--odom": "dense", "--vo-width": "320", "--imu-noise": "1e-3 1e-4 1e-5 1e-6",
    "--imu-extrinsics": "0 0 0.01 0 0 0 1", "--gravity": "0 -9.81 0", "--fallback-odom": "vo", "--timing": "none",
    "--initial-pose": "1 2 3 0 0 0 1", "--initial-pose-file": "start.txt", "--odom-rot-sigma": "0.004",
    "--odom-trans-sigma": "0.003", "--keyframe-every": "7", "--keyframe-distance": "0.2", "--keyframe-angle": "10",
    "--keyframe-window": "3", "--keyframe-on-doubt": None, "--keyframe-when-idle": "2", "--rolling-shutter": "0.02",
    "--iterations": "2", "--render-size": "160x120", "--matcher": "xfeat", "--gate-p": "0.99",
    "--field-sigma": "0.01", "--overlap": None, "--render-ahead": None, "--land-within": "frame",
    "--graph-window": "8", "--max-frames": "40", "--seed": "3", "--cache": "cache", "--train-steps": "50",
    "--anchor": None, "--pace": "2", "--out": "elsewhere", "--write-bag": "out.bag", "--viz": "run.rrd",
}


def _parse(argv):
    parser = build_parser()
    args = parser.parse_args(["run", *argv])
    args.given = set()
    return args


def _other(value, hint):
    """A value of the type ``hint`` other than ``value``."""
    options = typing.get_args(hint) or (hint,)
    if value is None:
        kind = next(o for o in options if o is not type(None))
        value = {str: "x", int: 1, float: 0.5, bool: False}.get(typing.get_origin(kind) or kind, "x")
        if (typing.get_origin(kind) or kind) is list:
            return [1.0, 2.0, 3.0]
        return value
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value * 2 + 1
    if isinstance(value, dict):
        return {"ratio": 0.7}
    return value + "-other"


def test_every_setting_round_trips_through_yaml_exactly():
    tree = RunSettings()
    changed = {}
    for name, kind in SECTIONS.items():
        hints = typing.get_type_hints(kind)
        for f in dataclasses.fields(kind):
            changed[f"{name}.{f.name}"] = _other(getattr(getattr(tree, name), f.name), hints[f.name])
    tree = tree.replace(changed)
    assert all(tree.get(path) == value for path, value in changed.items())
    assert RunSettings.from_dict(yaml.safe_load(yaml.safe_dump(tree.to_dict(), sort_keys=False))) == tree
    assert RunSettings.from_dict({}) == RunSettings()  # sections left out keep their defaults


def test_the_trees_defaults_are_the_pipelines_and_every_pipeline_field_is_set_or_resolved():
    bound = [pipeline_name(f) for kind in SECTIONS.values() for f in dataclasses.fields(kind) if pipeline_name(f)]
    assert len(bound) == len(set(bound))
    assert set(bound) | RESOLVED == {f.name for f in dataclasses.fields(PipelineConfig)}
    assert not set(bound) & RESOLVED
    tree = RunSettings().replace({"alignment.matcher": "sift"})
    built = tree.pipeline_config(land_within_s=0.0, overlap=False, keyframe_when_idle=0, progress=False)
    assert built == PipelineConfig()
    tree = tree.replace({"keyframes.every": 9, "graph.prior_trans_sigma_m": 0.02, "alignment.nap3d": {"ratio": 0.7},
                         "alignment.render_size": "160x120", "alignment.timing": "none"})
    built = tree.pipeline_config(land_within_s=0.03, overlap=True, keyframe_when_idle=2)
    assert (built.keyframe_every, built.prior_trans_sigma_m, built.align.ratio) == (9, 0.02, 0.7)
    assert (built.render_width, built.render_height, built.compensate_timing) == (160, 120, False)
    assert (built.land_within_s, built.overlap, built.keyframe_when_idle) == (0.03, True, 2)


@pytest.mark.parametrize("command", ["run", "compare"])
def test_every_option_is_bound_to_a_setting_with_its_default(command):
    parser = command_parsers(build_parser())[command]
    options = SOURCE_OPTIONS + (RUN_OPTIONS if command == "run" else ())
    paths = [o.path for o in options]
    assert len(paths) == len(set(paths)), "two options set one setting"
    defaults = RunSettings()
    for option in options:
        assert parser.get_default(option.dest) == option.default_in(defaults), option.flag
    flags = {f for action in parser._actions for f in action.option_strings}  # noqa: SLF001
    unbound = {f for f in flags if f.startswith("--")} - {o.flag for o in options}
    unbound -= {f"--no-{o.flag[2:]}" for o in options}  # --no-overlap is --overlap's
    meta = {"--help", "--verbose"} | ({"--config"} if command == "run" else {"--out", "--force"})
    assert unbound == meta


def _declarations(flags: set[str], modules: list[str]) -> dict[str, list[str]]:
    """Where each flag of ``flags`` is declared among ``modules`` (package-relative paths): a
    call to setting/Option/add_argument that names it."""
    import ast
    from pathlib import Path

    import nap3d_graph

    declaring = {"setting", "Option", "add_argument"}
    places: dict[str, list[str]] = {flag: [] for flag in flags}
    package = Path(nap3d_graph.__file__).parent
    for module in modules:
        for node in ast.walk(ast.parse((package / module).read_text())):
            if not isinstance(node, ast.Call):
                continue
            name = getattr(node.func, "id", getattr(node.func, "attr", ""))
            flag = next((a.value for a in node.args[:2] if isinstance(a, ast.Constant) and a.value in flags), None)
            if name in declaring and flag is not None:
                places[flag].append(f"{module}:{node.lineno}")
    return places


def test_each_run_option_is_declared_in_one_place():
    """A run or compare flag is declared once, by the settings field it sets (its name, type,
    default, flag and help); the command line's options are generated from the fields. (Other
    commands' flags of the same name, map's --keyframe-every say, are their own options.)"""
    places = _declarations({o.flag for o in SOURCE_OPTIONS + RUN_OPTIONS},
                           ["run/settings.py", "run/config.py", "cli/run.py", "cli/compare.py", "cli/sources.py",
                            "cli/run_options.py", "cli/binding.py", "cli/run_config.py"])
    assert {flag: len(where) for flag, where in places.items() if len(where) != 1} == {}
    assert {where[0].split(":")[0] for where in places.values()} == {"run/settings.py", "run/config.py"}
    # ... and each setting of the tree once: a section's own field, or a PipelineConfig field
    # that says where it sits in the tree (RunSettings takes it from there), never both.
    import ast
    from pathlib import Path

    import nap3d_graph

    source = (Path(nap3d_graph.__file__).parent / "run" / "settings.py").read_text()
    own = {(cls.name, node.target.id) for cls in ast.parse(source).body if isinstance(cls, ast.ClassDef)
           for node in cls.body if isinstance(node, ast.AnnAssign)}
    from_config = {f.metadata["tree"] for f in dataclasses.fields(PipelineConfig) if "tree" in f.metadata}
    for section, kind in SECTIONS.items():
        for f in dataclasses.fields(kind):
            declared = [(kind.__name__, f.name) in own, (section, f.name) in from_config]
            assert declared.count(True) == 1, f"{section}.{f.name}"


@pytest.mark.parametrize("command", ["map", "train-field"])
def test_each_map_and_field_setting_flag_is_declared_once_by_its_field(command):
    """map's and train-field's flags that set their settings are declared by the fields of
    MapSettings and SubmapSettings, and of FieldSettings, with the fields' defaults but where
    the command line's own differs (the matcher: chosen by the data; train-field's 5 minutes)."""
    from nap3d_graph.cli.binding import SectionDefaults
    from nap3d_graph.cli.map import MAP_OPTIONS, MAP_SECTIONS
    from nap3d_graph.cli.train_field import FIELD_OPTIONS, FIELD_SECTIONS

    options, sections, modules, declared_in, differs = {
        "map": (MAP_OPTIONS, MAP_SECTIONS, ["cli/map.py", "mapping/build.py", "fields/submaps.py"],
                {"mapping/build.py", "fields/submaps.py"}, {"--matcher": "auto"}),
        "train-field": (FIELD_OPTIONS, FIELD_SECTIONS, ["cli/train_field.py", "fields/build.py"], {"fields/build.py"},
                        {"--matcher": "auto", "--minutes": 5.0})}[command]
    places = _declarations({o.flag for o in options}, modules)
    assert {flag: len(where) for flag, where in places.items() if len(where) != 1} == {}
    assert {where[0].split(":")[0] for where in places.values()} == declared_in
    parser = command_parsers(build_parser())[command]
    defaults = SectionDefaults(sections)
    assert {o.flag: parser.get_default(o.dest) for o in options
            if parser.get_default(o.dest) != defaults.get(o.path)} == differs


def test_the_options_settings_come_back_from_a_config_unchanged():
    assert set(SAMPLES) == {o.flag for o in SOURCE_OPTIONS + RUN_OPTIONS}
    argv = [part for flag, value in SAMPLES.items() for part in ((flag,) if value is None else (flag, value))]
    given = settings_from_args(_parse(argv))
    defaults = RunSettings()
    for option in SOURCE_OPTIONS + RUN_OPTIONS:
        assert given.get(option.path) != defaults.get(option.path), option.flag
    assert given.odometry.gravity == [0.0, -9.81, 0.0] and given.source.pace == 2.0
    # Written, read back and applied to a command line that gives nothing: the same tree.
    loaded = RunSettings.from_dict(yaml.safe_load(yaml.safe_dump(given.to_dict())))
    args = _parse([])
    apply_settings(args, loaded, given=set())
    assert settings_from_args(args) == given
    # A flag the command line gave keeps its value; the others and the unflagged settings are the file's.
    loaded = loaded.replace({"graph.final_gnc": False})
    args = _parse(["--keyframe-every", "5"])
    args.given = {"keyframe_every"}
    apply_settings(args, loaded, given=args.given)
    again = settings_from_args(args)
    assert again.keyframes.every == 5 and again.graph.window == 8 and again.graph.final_gnc is False


def test_a_bad_settings_tree_is_one_line_naming_the_setting(tmp_path, capsys):
    with pytest.raises(SettingsError, match="unknown setting keyframes.evry"):
        RunSettings.from_dict({"keyframes": {"evry": 3}})
    with pytest.raises(SettingsError, match="unknown settings section 'keyframe'"):
        RunSettings.from_dict({"keyframe": {}})
    with pytest.raises(SettingsError, match="setting keyframes.every must be int, got '3'"):
        RunSettings.from_dict({"keyframes": {"every": "3"}})
    with pytest.raises(SettingsError, match="setting graph.final_gnc must be bool"):
        RunSettings.from_dict({"graph": {"final_gnc": 1}})
    assert RunSettings.from_dict({"graph": {"gate_p": 1}}).graph.gate_p == 1.0  # an int where a float goes
    assert math.isclose(RunSettings.from_dict({"odometry": {"gravity": 9}}).odometry.gravity, 9.0)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"settings": {"keyframes": {"evry": 3}}}))
    assert main(["run", "--config", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "unknown setting keyframes.evry" in err and len(err.strip().splitlines()) == 1
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump({"traj": "sim", "pipeline": {"keyframe_every": 3}}))
    assert main(["run", "--config", str(old), "--out", str(tmp_path / "x")]) == 2
    assert "written by an older nap3d-graph" in capsys.readouterr().err


def test_every_study_option_is_bound_and_its_config_round_trips():
    parser = command_parsers(build_parser())["study"]
    defaults = StudySettings()
    for option in STUDY_OPTIONS:
        assert parser.get_default(option.dest) == option.default_in(defaults), option.flag
    flags = {f for action in parser._actions for f in action.option_strings}  # noqa: SLF001
    assert flags - {o.flag for o in STUDY_OPTIONS} == {"-h", "--help", "-v", "--verbose", "--out", "--force", "--config"}
    argv = ["study", "rec", "--split", "0.3", "--model", "splat", "--train-steps", "40", "--keyframe-every", "4",
            "--scenarios", "3", "--eval-k-full", "--odom", "vo,dense", "--seed", "2", "--matcher", "sift",
            "--topics", "gt=/tf", "--out", "o"]
    args = build_parser().parse_args(argv)
    tree = settings_from_args(args, StudySettings())
    assert tree.study.odometries == ("vo", "dense") and tree.study.split == 0.3 and tree.recordings.data == "rec"
    assert all(tree.get(o.path) != defaults.get(o.path) for o in STUDY_OPTIONS if o.flag not in ("--map", "--query",
                                                                                               "--map-frames",
                                                                                               "--query-frames"))
    loaded = StudySettings.from_dict(yaml.safe_load(yaml.safe_dump(tree.to_dict())))
    assert loaded == tree
    fresh = build_parser().parse_args(["study", "--out", "o"])
    apply_settings(fresh, loaded, given={"out"})
    assert settings_from_args(fresh, StudySettings()) == tree
