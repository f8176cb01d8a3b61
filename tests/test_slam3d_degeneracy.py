"""A LiDAR between featureless walls cannot measure motion along them: the replay says so."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from frontends.slam3d.degeneracy import UNDERCONSTRAINED_SHARE, weakest_horizontal_share
from pipeline.cli import app
from tests.lidar_world import Lidar, Route, World, drive, straight_street, town_loop, write_cloud_log

STREET = World(straight_street(length=600.0), Route(x0=-250.0, long_side=500.0, short_side=6.0, radius=7.0,
                                                    ease=4.0, start_x=-200.0))
"""Two long flat walls (and the ground): every stretch of the street looks the same."""


def test_clouds_between_two_walls_are_told_from_clouds_in_a_town() -> None:
    street = drive(STREET, sweeps=2, step=1.0, lidar=Lidar(columns=360))
    town = drive(town_loop(), sweeps=2, step=1.0, lidar=Lidar(columns=360))
    # the walls face ±y only: x gets nothing; the town's buildings face every way
    assert weakest_horizontal_share(street.clouds[-1]) < 0.2 * UNDERCONSTRAINED_SHARE
    assert weakest_horizontal_share(town.clouds[-1]) > 10 * UNDERCONSTRAINED_SHARE
    assert weakest_horizontal_share(np.zeros((5, 3))) == 1.0  # too few points to tell


def test_a_drive_down_a_featureless_street_is_warned_of_and_counted(tmp_path: Path) -> None:
    street = drive(STREET, sweeps=30, step=1.5, ramp=5, lidar=Lidar(columns=360))
    log = tmp_path / "street.mcap"
    write_cloud_log(log, street)
    result = CliRunner().invoke(app, [str(log), "--out", str(tmp_path / "out"), "--quiet"])
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "out" / "street.json").read_text())
    keyframes = summary["counts"]["keyframes"]
    assert summary["counts"]["keyframes_underconstrained"] == keyframes
    [warning] = [w["message"] for w in summary["warnings"]]
    assert warning.startswith(f"{keyframes} of the {keyframes} keyframes (")
    assert "saw surfaces facing almost only one horizontal direction" in warning
    # what it warns of: the 40 m driven came out far shorter
    driven = np.linalg.norm(np.diff(street.base_poses[:, :2], axis=0), axis=1).sum()
    tum = np.loadtxt(tmp_path / "out" / "street.tum")
    estimated = np.linalg.norm(np.diff(tum[:, 1:3], axis=0), axis=1).sum()
    assert estimated < 0.8 * driven
