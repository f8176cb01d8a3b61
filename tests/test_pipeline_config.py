"""The replay configuration: TOML round trip, units, validation errors naming file, line and key, and the
precedence of command-line options over the file."""

from __future__ import annotations

import dataclasses
import json
import math
import pickle
from pathlib import Path

import pytest
from typer.testing import CliRunner

from frontends.slam2d.config import KeyframeConfig, LoopClosureConfig, OdometryConfig, Slam2DConfig
from frontends.slam3d import Slam3DConfig
from frontends.slam3d.config import KeyframeConfig as Keyframe3DConfig
from frontends.slam3d.config import OdometryConfig as Odometry3DConfig
from optimizer.solve import DEFAULT_POLISH_ITERATIONS
from pipeline.cli import app
from pipeline.config import (
    _AT_LEAST,
    _AT_MOST,
    _BOUNDS,
    SLAM2D_SECTIONS,
    SLAM3D_SECTIONS,
    ConfigError,
    ReplayConfig,
    is_angle_field,
    load_config,
)
from tests.pipeline_fixtures import write_loop_graph


def write_config(tmp_path: Path, text: str, name: str = "replay.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_round_trip_through_toml(tmp_path: Path) -> None:
    path = write_config(tmp_path, ReplayConfig().to_toml())
    loaded = load_config(path)
    assert loaded == ReplayConfig()
    # The frontend gets exactly its own defaults back (degrees in the file, radians inside).
    assert loaded.to_slam2d() == Slam2DConfig()
    assert loaded.to_slam3d() == Slam3DConfig()
    # Iterations left to the optimizer (100, a cap where the default hands a large graph's SGD over).
    assert (loaded.optimizer.method, loaded.optimizer.iterations) == ("sgd+gn", None)
    assert loaded.input.scan_topic is None and loaded.input.odom_topic is None


def test_an_empty_file_is_the_defaults(tmp_path: Path) -> None:
    assert load_config(write_config(tmp_path, "")) == ReplayConfig()


def test_sections_mirror_the_dataclasses() -> None:
    assert list(SLAM2D_SECTIONS) == ["matching", "odometry", "keyframes", "loop_closure"]
    assert list(SLAM3D_SECTIONS) == ["odometry", "keyframes", "loop_closure", "se3_polish"]
    frontends = {"slam2d": (SLAM2D_SECTIONS, Slam2DConfig()), "slam3d": (SLAM3D_SECTIONS, Slam3DConfig())}
    for sections, defaults in frontends.values():
        for name, model in sections.items():
            dataclass_type = type(getattr(defaults, name))
            assert list(model.model_fields) == [item.name for item in dataclasses.fields(dataclass_type)]
    rule_keys = [(section, key) for section, keys in _BOUNDS.items() for key in keys]
    rule_keys += [*_AT_LEAST, *_AT_MOST]
    rule_keys += [(section, other) for (section, _), other in [*_AT_LEAST.items(), *_AT_MOST.items()]]
    for qualified, key in rule_keys:  # a misspelt rule would silently never apply
        frontend, section = qualified.split(".")
        assert key in frontends[frontend][0][section].model_fields, (qualified, key)


def test_the_file_has_a_section_per_frontend_setting_group() -> None:
    text = ReplayConfig().to_toml()
    for header in ("[input]", "[optimizer]", "[slam2d.matching]", "[slam2d.loop_closure]",
                   "[slam3d.odometry]", "[slam3d.keyframes]", "[slam3d.loop_closure]"):
        assert f"\n{header}\n" in text, header
    assert "\n[matching]\n" not in text  # the 2D settings moved under [slam2d]


def test_3d_settings_reach_the_3d_frontend_in_its_units(tmp_path: Path) -> None:
    path = write_config(tmp_path, "[slam3d.odometry]\nmax_range = 60\nvoxel_size = 0.4\n\n"
                                  "[slam3d.keyframes]\nangle = 20\n")
    frontend = load_config(path).to_slam3d()
    assert frontend.odometry == Odometry3DConfig(max_range=60.0, voxel_size=0.4)
    assert frontend.keyframes == Keyframe3DConfig(angle=math.radians(20))
    assert ReplayConfig().to_slam3d().odometry.voxel_size is None  # left out: KISS-ICP's rule
    assert ReplayConfig().to_slam3d() == Slam3DConfig()


def test_angles_are_degrees_in_the_file() -> None:
    angle_fields = {(name, key) for name, model in SLAM2D_SECTIONS.items() for key in model.model_fields
                    if is_angle_field(key)}
    assert angle_fields == {
        ("odometry", "window_angular"), ("odometry", "window_angular_without_odometry"),
        ("odometry", "angular_step"), ("odometry", "odometry_sigma_angular"),
        ("odometry", "constant_velocity_sigma_angular"),
        ("keyframes", "angle"), ("keyframes", "max_turn_rate"),
        ("loop_closure", "angular_window"), ("loop_closure", "angular_step"),
    }
    config = ReplayConfig(slam2d={"keyframes": {"angle": 30, "max_turn_rate": 90.0, "distance": 0.5},
                                  "odometry": {"odometry_sigma_per_radian": 0.2}})
    assert config.slam2d.keyframes.angle == 30.0
    frontend = config.to_slam2d()
    assert frontend.keyframes == KeyframeConfig(distance=0.5, angle=math.pi / 6, max_turn_rate=math.pi / 2)
    assert frontend.odometry == OdometryConfig(odometry_sigma_per_radian=0.2)  # a ratio, not an angle


def test_values_from_a_file(tmp_path: Path) -> None:
    path = write_config(tmp_path, """
[input]
scan_topic = "/front/scan"

[optimizer]
method = "sgd"
iterations = 7

[slam2d.loop_closure]
enabled = false
angular_window = 40
""")
    config = load_config(path)
    assert config.input.scan_topic == "/front/scan"
    assert (config.optimizer.method, config.optimizer.iterations) == ("sgd", 7)
    expected = LoopClosureConfig(enabled=False, angular_window=math.radians(40))
    assert config.to_slam2d().loop_closure == expected


def test_derived_defaults_follow_the_values_they_depend_on() -> None:
    # Raising the search radius alone raises the cap with it rather than failing ...
    for frontend, default in (("slam2d", 30.0), ("slam3d", 30.0)):
        raised = ReplayConfig(**{frontend: {"loop_closure": {"search_radius": default + 2}}})
        assert getattr(raised, frontend).loop_closure.max_search_radius == default + 2
        lowered = ReplayConfig(**{frontend: {"loop_closure": {"search_radius": 3.0}}})
        assert getattr(lowered, frontend).loop_closure.max_search_radius == default
    # ... and Gauss-Newton alone gets the polish cap unless iterations are given.
    assert ReplayConfig(optimizer={"method": "gn"}).optimizer.iterations == DEFAULT_POLISH_ITERATIONS
    assert ReplayConfig(optimizer={"method": "gn", "iterations": 4}).optimizer.iterations == 4
    assert ReplayConfig(optimizer={"method": "gauss-seidel"}).optimizer.iterations is None


def test_a_configuration_pickles() -> None:  # it travels to the worker processes of a batch
    config = ReplayConfig(optimizer={"method": "sgd"}, slam2d={"matching": {"resolution": 0.1}},
                          slam3d={"odometry": {"voxel_size": 0.5}})
    assert pickle.loads(pickle.dumps(config)) == config


BAD_FILES = {
    "typo in a key": ("[optimizer]\nmethod = \"sgd\"\n\n[slam2d.loop_closure]\nserach_radius = 3.0\n", 5,
                      "slam2d.loop_closure.serach_radius: ", "did you mean search_radius"),
    "typo in a section": ("[slam2d.matchin]\nresolution = 0.1\n", 1, "slam2d.matchin: ",
                          "did you mean matching"),
    "typo in a frontend": ("[slam4d.odometry]\nmax_range = 10\n", 1, "slam4d: ", "unknown section"),
    "2D section at the top": ("[matching]\nresolution = 0.1\n", 1, "matching: ", "unknown section"),
    "negative length": ("[slam2d.matching]\nresolution = 0.1\nmax_range = -5\n", 3,
                        "slam2d.matching.max_range: ", "greater than 0"),
    "text for a number": ("[slam2d.keyframes]\ndistance = \"far\"\n", 2, "slam2d.keyframes.distance: ",
                          "valid number"),
    "boolean for a count": ("[slam2d.matching]\nmin_points = true\n", 2, "slam2d.matching.min_points: ",
                            "valid integer"),
    "fraction above one": ("[slam2d.loop_closure]\nmin_score = 1.5\n", 2, "slam2d.loop_closure.min_score: ",
                           "less than or equal to 1"),
    "unknown method": ("[optimizer]\nmethod = \"lm\"\n", 2, "optimizer.method: ", "sgd+gn"),
    "cap below radius": ("[slam2d.loop_closure]\nsearch_radius = 8.0\nmax_search_radius = 5.0\n", 3,
                         "slam2d.loop_closure.max_search_radius: ", "at least search_radius"),
    "3D cap below radius": ("[slam3d.loop_closure]\nsearch_radius = 40.0\nmax_search_radius = 35.0\n", 3,
                            "slam3d.loop_closure.max_search_radius: ", "at least search_radius"),
    "step wider than window": ("[slam2d.odometry]\nangular_step = 10\n", 2, "slam2d.odometry.angular_step: ",
                               "at most window_angular"),
    "not infinite": ("[slam2d.matching]\nmax_range = inf\n", 2, "slam2d.matching.max_range: ", "finite"),
    "3D voxel too fine": ("[slam3d.odometry]\nvoxel_size = 0.001\n", 2, "slam3d.odometry.voxel_size: ",
                          "greater than or equal to 0.01"),
    "3D range beyond any sensor": ("[slam3d.odometry]\nmax_range = 1e300\n", 2,
                                   "slam3d.odometry.max_range: ", "less than or equal to 1000"),
    "3D text for a switch": ("[slam3d.odometry]\ndeskew = \"yes\"\n", 2, "slam3d.odometry.deskew: ",
                             "valid boolean"),
    "dotted key": ("slam2d.matching.resolutoin = 0.1\n", 1, "slam2d.matching.resolutoin: ",
                   "did you mean resolution"),
    "syntax error": ("[slam2d.matching]\nresolution = \n", 2, "not valid TOML: ", "Invalid value"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_files_give_one_line_naming_file_line_and_key(tmp_path: Path, case: str) -> None:
    text, line, key, reason = BAD_FILES[case]
    path = write_config(tmp_path, text)
    with pytest.raises(ConfigError) as raised:
        load_config(path)
    message = str(raised.value)
    assert message.startswith(f"{path}:{line}: {key}"), message
    assert reason in message
    assert "\n" not in message
    assert raised.value.line == line


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nowhere\.toml: no such file"):
        load_config(tmp_path / "nowhere.toml")


def test_overrides_replace_file_values_before_derivation(tmp_path: Path) -> None:
    path = write_config(tmp_path, "[optimizer]\nmethod = \"gn\"\n\n[input]\nodom_topic = \"/odom\"\n")
    assert load_config(path).optimizer.iterations == DEFAULT_POLISH_ITERATIONS
    config = load_config(path, {"optimizer": {"method": "sgd"}, "input": {"scan_topic": "/scan"}})
    assert (config.optimizer.method, config.optimizer.iterations) == ("sgd", None)
    assert (config.input.scan_topic, config.input.odom_topic) == ("/scan", "/odom")


# --------------------------------------------------------------------------------------------- the CLI


def run_replay(*args: object) -> object:
    return CliRunner().invoke(app, [str(arg) for arg in args])


def test_dump_config_prints_defaults_that_load_back(tmp_path: Path) -> None:
    result = run_replay("--dump-config")
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    assert "[slam2d.loop_closure]" in result.stdout and "[slam3d.loop_closure]" in result.stdout
    assert "degrees" in result.stdout
    assert load_config(write_config(tmp_path, result.stdout)) == ReplayConfig()


def test_options_override_the_config_file_in_dump_config(tmp_path: Path) -> None:
    path = write_config(tmp_path, "[optimizer]\nmethod = \"gn\"\niterations = 7\n\n"
                                  "[input]\nscan_topic = \"/a\"\n\n[slam2d.keyframes]\ndistance = 0.5\n\n"
                                  "[slam3d.keyframes]\ndistance = 2.5\n")
    result = run_replay("--config", path, "--method", "sgd", "--scan-topic", "/b", "--base-frame", "chassis",
                        "--dump-config")
    assert result.exit_code == 0, result.output
    dumped = load_config(write_config(tmp_path, result.stdout, "dumped.toml"))
    assert (dumped.optimizer.method, dumped.optimizer.iterations) == ("sgd", 7)
    assert (dumped.input.scan_topic, dumped.input.base_frame) == ("/b", "chassis")
    assert (dumped.slam2d.keyframes.distance, dumped.slam3d.keyframes.distance) == (0.5, 2.5)


def test_options_override_the_config_file_in_a_run(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    path = write_config(tmp_path, "[optimizer]\nmethod = \"sgd\"\niterations = 2\n")
    out = tmp_path / "out"

    from_file = run_replay(graph, "--config", path, "--out", out, "--quiet", "--allow-unconverged")
    assert from_file.exit_code == 0, from_file.output
    assert json.loads((out / "loop.json").read_text())["iterations"] == {"sgd": 2}

    overridden = run_replay(graph, "--config", path, "--out", out, "--quiet", "--method", "gauss-seidel",
                            "--iterations", 3, "--allow-unconverged")
    assert overridden.exit_code == 0, overridden.output
    summary = json.loads((out / "loop.json").read_text())
    assert (summary["method"], summary["iterations"]) == ("gauss-seidel", {"gauss-seidel": 3})


def test_a_bad_config_file_is_a_one_line_error_before_anything_runs(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    path = write_config(tmp_path, "[optimizer]\niteratons = 5\n")
    result = run_replay(graph, "--config", path, "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"replay: error: {path}:2: optimizer.iteratons: unknown key in [optimizer]; did you mean iterations?"
    ]
    assert not (tmp_path / "out").exists()


def test_options_that_apply_to_no_input_are_refused_in_one_line(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    graph_list, log_list = tmp_path / "graphs.txt", tmp_path / "logs.txt"
    graph_list.write_text(f"{graph}\n")
    (tmp_path / "run.mcap").write_bytes(b"")  # a list names existing inputs; its kind is told by the path
    log_list.write_text(f"{tmp_path / 'run.mcap'}\n")
    cases = [
        ((tmp_path / "run.mcap", "--repair-information"), "--repair-information", "pose-graph inputs only"),
        (("--repair-information",), "--repair-information", "pose-graph inputs only"),  # the sample log
        ((graph, "--scan-topic", "/scan"), "--scan-topic", "logs only"),
        ((graph, "--odom-topic", "/odom"), "--odom-topic", "logs only"),
        ((graph, "--base-frame", "base_link"), "--base-frame", "logs only"),
        # the inputs listed in a file count as those named
        (("--inputs", graph_list, "--odom-topic", "/odom"), "--odom-topic", "logs only"),
        (("--inputs", log_list, "--repair-information"), "--repair-information", "pose-graph inputs only"),
    ]
    for args, option, reason in cases:
        result = run_replay(*args, "--out", tmp_path / "out")
        assert result.exit_code == 2, (args, result.output)
        assert len(result.stderr.splitlines()) == 1 and option in result.stderr and reason in result.stderr
    assert not (tmp_path / "out").exists()
    mixed = run_replay(graph, tmp_path / "run.mcap", "--repair-information", "--out", tmp_path / "out")
    assert "--repair-information" not in mixed.stderr  # it applies to the graph: accepted


def test_a_robust_kernel_with_a_method_without_one_is_refused_whatever_the_input(tmp_path: Path) -> None:
    """Refused before any input is read: a log whose graph has no loop closure is never optimized, and
    accepted the setting before (a graph, or a log with loops, refused it)."""
    path = write_config(tmp_path, '[optimizer]\nmethod = "gn"\nrobust = "cauchy"\n')
    reason = "works with the methods sgd+gn, sgd, not 'gn'"
    cases = ((("--config", path), f"{path}:1"), (("--robust", "dcs", "--method", "gn"), "configuration"))
    for args, where in cases:
        result = run_replay("--dump-config", *args)
        assert result.exit_code == 2, result.output  # type: ignore[attr-defined]
        kernel = "cauchy" if args[0] == "--config" else "dcs"
        assert result.stderr.splitlines() == [  # type: ignore[attr-defined]
            f"replay: error: {where}: optimizer: robust = '{kernel}' {reason}"]
    assert run_replay("--dump-config", "--robust", "dcs").exit_code == 0  # type: ignore[attr-defined]


def test_a_retired_setting_says_it_is_fixed_now(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    path = write_config(tmp_path, "[slam2d.loop_closure]\nmin_score = 0.6\nquery_thinning = 0.2\n")
    result = run_replay(graph, "--config", path, "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"replay: error: {path}:3: slam2d.loop_closure.query_thinning: query_thinning is no longer a setting "
        "(fixed at 0.1 m, which served every log tried); remove it from the file"
    ]
    assert not (tmp_path / "out").exists()
