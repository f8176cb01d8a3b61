"""`from pipeline import replay`: the Python API returns a typed result and raises, never prints or exits."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from frontends.errors import FrontendError
from frontends.slam2d.slam import ScanEstimate
from optimizer.cost import chi2
from optimizer.errors import GraphFileError
from optimizer.graph_files import read_graph
from optimizer.iteration import Iteration
from pipeline import ReplayConfig, replay
from pipeline.api import input_kind
from pipeline.errors import PipelineError
from pipeline.outputs import output_stem
from pipeline.trajectory_io import read_tum
from tests.pipeline_fixtures import LOOP_POSES, loop_graph_text, write_drive, write_loop_graph

REPO = Path(__file__).resolve().parents[1]
DRIVE_SCANS = 12


def test_replay_of_a_pose_graph(tmp_path: Path) -> None:
    graph_path = write_loop_graph(tmp_path / "loop.g2o")
    seen: list[Iteration] = []
    result = replay(graph_path, ReplayConfig(optimizer={"method": "sgd", "iterations": 5}),
                    out_dir=tmp_path / "out", on_iteration=seen.append)
    assert result.kind == "graph"
    assert result.poses.shape == (LOOP_POSES, 3)
    np.testing.assert_array_equal(result.graph.poses, result.poses)
    assert result.stamps_ns is None
    assert dict(result.stats.iterations) == {"sgd": 5}
    assert [iteration.stage for iteration in seen] == ["initial"] + ["sgd"] * 5
    # χ² recomputed from the input file and the returned poses
    original = read_graph(graph_path).graph
    assert result.stats.chi2_initial == pytest.approx(chi2(original), rel=1e-9)
    assert result.stats.chi2_final == pytest.approx(chi2(original, result.poses), rel=1e-9)
    assert result.stats.chi2_final < result.stats.chi2_initial
    stats = result.stats
    assert (stats.poses, stats.constraints, stats.loop_closures) == (LOOP_POSES, LOOP_POSES + 1, 2)
    assert result.stats.scans is None
    assert set(result.outputs) == {"g2o", "json", "rrd"}
    assert all(path.is_file() and path.parent == tmp_path / "out" for path in result.outputs.values())
    assert json.loads(result.outputs["json"].read_text()) == json.loads(json.dumps(result.summary))


def test_replay_of_a_log(tmp_path: Path) -> None:
    log = tmp_path / "drive.mcap"
    write_drive(log, scans=DRIVE_SCANS)
    scans: list[ScanEstimate] = []
    result = replay(log, out_dir=tmp_path / "out", on_scan=scans.append)
    assert result.kind == "log"
    assert [estimate.index for estimate in scans] == list(range(DRIVE_SCANS))
    assert result.poses.shape == (DRIVE_SCANS, 3)
    assert result.stamps_ns is not None and len(result.stamps_ns) == DRIVE_SCANS
    assert result.stats.scans == DRIVE_SCANS
    assert result.stats.poses == result.graph.num_poses
    # Optimizer stages only, as for a pose graph: not the starting estimates' "initial" or the "selected".
    stages = json.loads(result.outputs["json"].read_text())["chi2_per_iteration"]
    assert result.stats.iterations and set(result.stats.iterations) <= {s["stage"] for s in stages}
    assert not {"initial", "selected"} & set(result.stats.iterations)
    assert {"tum", "g2o", "json", "rrd"} <= set(result.outputs)
    trajectory = read_tum(result.outputs["tum"])  # the file holds what the result says
    np.testing.assert_array_equal(trajectory.stamps_ns, result.stamps_ns)
    np.testing.assert_allclose(trajectory.positions[:, :2], result.poses[:, :2], atol=1e-6)


def test_config_may_be_a_toml_path(tmp_path: Path) -> None:
    config = tmp_path / "replay.toml"
    config.write_text("[optimizer]\nmethod = \"gauss-seidel\"\niterations = 3\n")
    result = replay(write_loop_graph(tmp_path / "loop.g2o"), str(config), out_dir=tmp_path / "out")
    assert dict(result.stats.iterations) == {"gauss-seidel": 3}


def test_config_may_be_a_mapping_of_sections_as_the_toml_file_holds_them(tmp_path: Path) -> None:
    graph = write_loop_graph(tmp_path / "loop.g2o")
    sections = {"optimizer": {"method": "gauss-seidel", "iterations": 3}}
    result = replay(graph, sections, out_dir=tmp_path / "out")
    assert dict(result.stats.iterations) == {"gauss-seidel": 3}
    with pytest.raises(PipelineError, match=r"optimizer.*method"):
        replay(graph, {"optimizer": {"method": "newton"}}, out_dir=tmp_path / "bad")
    assert not (tmp_path / "bad").exists()


def test_bad_input_raises_and_prints_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.g2o"
    bad.write_text(loop_graph_text().replace("EDGE_SE2 3 4", "EDGE_SE2 3 4 oops", 1))
    with pytest.raises(GraphFileError, match=r"bad\.g2o:\d+: "):
        replay(bad, out_dir=tmp_path / "out")
    with pytest.raises(FrontendError, match="nowhere"):
        replay(tmp_path / "nowhere.mcap", out_dir=tmp_path / "out")
    captured = capsys.readouterr()
    assert (captured.out, captured.err) == ("", "")
    assert not (tmp_path / "out").exists()


def test_inputs_are_told_apart_by_suffix_and_content(tmp_path: Path) -> None:
    toro = tmp_path / "graph.txt"
    toro.write_text("# a comment\nVERTEX2 0 0 0 0\n")
    other = tmp_path / "notes.txt"
    other.write_text("hello\n")
    bag = tmp_path / "rosbag2_run"
    bag.mkdir()
    assert [input_kind(path) for path in (toro, other, bag, tmp_path / "x.g2o")] == ["graph", "log", "log",
                                                                                     "graph"]
    # A 3D graph is a graph too, so that its replay says what it is (not "no topic" from the log reader).
    for tag in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "VERTEX3"):
        (tmp_path / "poses.txt").write_text(f"{tag} 0 0 0 0 0 0 0 1\n")
        assert input_kind(tmp_path / "poses.txt") == "graph"
    assert [output_stem(path) for path in (toro, bag, bag / ".", bag / "..")] == [
        "graph", "rosbag2_run", "rosbag2_run", tmp_path.name]  # `replay .` in the bag: not ".rrd", "_map.png"


def test_import_pipeline_stays_light() -> None:
    code = ("import sys, pipeline; heavy = {'rerun', 'numba'} & set(sys.modules); assert not heavy, heavy; "
            "from pipeline import replay, ReplayConfig; assert callable(replay)")
    completed = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                               timeout=120)
    assert completed.returncode == 0, completed.stderr
