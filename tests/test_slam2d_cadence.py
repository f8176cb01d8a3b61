"""Fast lasers: which scans the 2D SLAM matches (`frontends.slam2d.cadence`), and how the scans between the
matched ones are posed (`LaserSlam2D`)."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from frontends.slam2d.cadence import RECENT_INTERVALS, MatchCadence
from frontends.slam2d.config import Slam2DConfig
from frontends.slam2d.deskew import along_motion
from frontends.slam2d.slam import LaserSlam2D
from optimizer import se2
from pipeline.cli import app
from pipeline.trajectory_io import read_tum
from tests.laser_world import Run, align_to_first, simulate_swept_run, square_loop, wrap
from tests.pipeline_fixtures import START_NS, read_recording, write_drive

FAST_PERIOD_NS = 25_000_000
"""A 40 Hz laser."""


def jittered_stamps(rate: float, count: int, seed: int = 0) -> list[int]:
    """`count` stamps of a laser at `rate` Hz, each off its slot by up to 5 % of the interval."""
    rng = np.random.default_rng(seed)
    slots = np.arange(count) / rate + rng.uniform(-0.05, 0.05, count) / rate
    return [START_NS + round(t * 1e9) for t in slots]


def due_indices(cadence: MatchCadence, stamps: list[int]) -> list[int]:
    due = []
    for index, stamp in enumerate(stamps):
        if cadence.due(stamp):
            cadence.matched(stamp)
            due.append(index)
    return due


# The stride the module documents for 0.1 s: n = ⌊0.1 s × rate + ¼⌋, at least 1.
@pytest.mark.parametrize(("rate", "stride"), [(40, 4), (30, 3), (25, 2), (20, 2), (15, 1), (10, 1), (5, 1)])
def test_a_steady_laser_is_matched_every_nth_scan_whatever_its_jitter(rate: int, stride: int) -> None:
    # The first 15 scans, before 15 intervals tell the laser's rate, are all matched.
    expected = list(range(15)) + list(range(14 + stride, 200, stride))
    assert due_indices(MatchCadence(0.1), jittered_stamps(rate, 200)) == expected


def test_the_scan_after_a_gap_is_matched_and_the_stride_starts_again_from_it() -> None:
    stamps = jittered_stamps(40, 60)
    stamps = stamps[:30] + [s + 300_000_000 for s in stamps[30:]]  # 0.3 s without scans after scan 29
    due = due_indices(MatchCadence(0.1), stamps)
    # The first 15 scans, then every 4th. Scan 30 comes 0.3 s after scan 29: matched at once. While the gap
    # is one of the 15 recent intervals (up to scan 44) the laser's mean interval is (14 × 25 + 325) / 15 =
    # 45 ms, a stride of ⌊100 / 45 + ¼⌋ = 2: matched more often, never less. Then every 4th again.
    assert due == [*range(15), 18, 22, 26, 30, 32, 34, 36, 38, 40, 42, 44, 48, 52, 56]


def test_a_slow_laser_stamped_in_bursts_has_every_scan_matched() -> None:
    # A logger that stamps a 5 Hz laser's scans in pairs 1 ms apart, 0.4 s between pairs (the Intel
    # Research Lab log): half the intervals are 1 ms, but the laser scans 5 times a second.
    stamps = [START_NS + pair * 400_000_000 + second * 1_000_000 for pair in range(50) for second in (0, 1)]
    assert due_indices(MatchCadence(0.1), stamps) == list(range(100))


def test_no_interval_matches_every_scan() -> None:
    stamps = jittered_stamps(40, 50)
    assert due_indices(MatchCadence(0.0), stamps) == list(range(50))


def test_a_fraction_of_a_motion_lies_on_its_arc() -> None:
    # A quarter turn on a circle of radius 2 about (0, 2): a third of the way is the point at 30°.
    motion = np.array([2.0, 2.0, math.pi / 2])
    third = along_motion(motion, np.array([0.0, 1 / 3, 1.0]))
    np.testing.assert_allclose(third[0], 0.0, atol=1e-12)
    thirty = math.pi / 6
    np.testing.assert_allclose(third[1], [2 * math.sin(thirty), 2 - 2 * math.cos(thirty), thirty])
    np.testing.assert_allclose(third[2], motion, atol=1e-12)


@functools.cache
def fast_laser_drive() -> Run:
    """A 40 Hz, 270° laser driving the square loop at 1 m/s (3 052 scans: simulated once, 7 s, for the four
    runs that read it)."""
    return simulate_swept_run(square_loop(), speed=1.0, scan_rate=40.0, sweep=0.0, beams=541,
                              fov=math.radians(270.0), max_range=30.0, seed=3)


def fast_run(with_odometry: bool, interval: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The first 400 scans (10 s, 10 m and a corner) of `fast_laser_drive`: every scan's error against the
    truth (m), the online estimates' errors, which scans were between, and the graph's count of them."""
    run = fast_laser_drive()
    count = 400
    base = Slam2DConfig()
    slam = LaserSlam2D(dataclasses.replace(
        base, matching=dataclasses.replace(base.matching, min_match_interval=interval)))
    estimates = [slam.add_scan(int(run.stamps_ns[k]), run.scans[k],
                               run.odometry[k] if with_odometry else None, 0.0) for k in range(count)]
    graph = slam.finish()
    truth = run.truth[:count]
    final = align_to_first(graph.scan_poses(graph.graph.poses), truth)
    online = align_to_first(np.array([e.pose for e in estimates]), truth)
    errors = np.hypot(*(final[:, :2] - truth[:, :2]).T)
    online_errors = np.hypot(*(online[:, :2] - truth[:, :2]).T)
    between = np.array([e.between for e in estimates])
    assert not np.any(between & np.array([e.matched for e in estimates]))
    assert np.all(np.abs(wrap(final[:, 2] - truth[:, 2])) < math.radians(1.0))
    return errors, online_errors, between, graph.scans_between


@pytest.mark.parametrize("with_odometry", [True, False], ids=["odometry", "lidar-only"])
def test_a_fast_laser_has_every_fourth_scan_matched_and_the_others_posed_as_well(with_odometry: bool) -> None:
    errors, online_errors, between, counted = fast_run(with_odometry, 0.1)
    # The first 15 of 400 scans matched (the laser's rate is not known yet), then every 4th: 289 between.
    matched = np.r_[np.arange(15), np.arange(18, 400, 4)]
    assert counted == between.sum() == 400 - len(matched) == 289
    assert not between[matched].any() and np.delete(between, matched).all()
    # The scans between lie on the track as closely as the matched ones around them.
    assert np.median(errors[between]) <= np.median(errors[~between]) + 0.003
    assert errors.max() < 0.05
    # Online, before the next match, a scan between is the prediction from the last matched one (lidar-only,
    # the velocity is known from the second matched scan on).
    assert np.max(online_errors[4:][between[4:]]) < 0.02
    # Matching every scan instead does no better.
    every_scan, _, none_between, none_counted = fast_run(with_odometry, 0.0)
    assert none_counted == 0 and not none_between.any()
    assert np.median(errors) <= np.median(every_scan) + 0.005


def test_a_fast_log_replays_with_every_scan_in_the_trajectory(tmp_path: Path) -> None:
    log = tmp_path / "fast.mcap"
    truth = write_drive(log, scans=320, scan_period_ns=FAST_PERIOD_NS)  # 8 s of a 40 Hz laser
    result = CliRunner().invoke(app, [str(log), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "out" / "fast.json").read_text())
    assert summary["counts"]["scans_between"] == 320 - 15 - len(range(18, 320, 4)) == 229
    assert summary["odometry_topic"] == "/odom"
    assert "  229 scans posed between matched ones" in result.stderr.splitlines()[1]
    trajectory = read_tum(tmp_path / "out" / "fast.tum")
    np.testing.assert_array_equal(trajectory.stamps_ns, START_NS + np.arange(320) * FAST_PERIOD_NS)
    poses = trajectory.planar()
    aligned = align_to_first(poses, truth)
    assert np.max(np.hypot(*(aligned[:, :2] - truth[:, :2]).T)) < 0.05
    assert se2.relative(poses[0], poses[-1])[0] == pytest.approx(7.975, abs=0.05)  # 319 × 2.5 cm ahead
    # The playback plays the matched scans only: the recording of a 40 Hz laser is a 10 Hz one's size.
    played = read_recording(tmp_path / "out" / "fast.rrd", timeline="scan")
    assert played["/world/scan"].steps == played["/world/robot"].steps == [*range(15), *range(18, 320, 4)]


def test_a_fast_log_localized_in_a_saved_map_has_every_scan_placed(tmp_path: Path) -> None:
    mapped = tmp_path / "mapped.mcap"
    write_drive(mapped, scans=320, scan_period_ns=FAST_PERIOD_NS)
    runner = CliRunner()
    assert runner.invoke(app, [str(mapped), "--out", str(tmp_path / "map"), "--quiet"]).exit_code == 0
    log = tmp_path / "again.mcap"
    truth = write_drive(log, scans=320, scan_period_ns=FAST_PERIOD_NS, seed=11)  # other noise, same drive
    result = runner.invoke(app, [str(log), "--map", str(tmp_path / "map" / "mapped.session"),
                                 "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "out" / "again.json").read_text())
    found = summary["localization"]
    assert found["with_pose"] == 320 and found["never_localized"] == 0
    states = summary["per_scan"]["state"]
    # Once placed (at the first scan, which fits one place only) and the laser's rate known
    # (`cadence.RECENT_INTERVALS`), every 4th scan goes to the localizer and the three after it are posed
    # between.
    placed, strided = states.index("m"), states.index("b") - 1
    assert placed == 0 and strided <= RECENT_INTERVALS + 1
    assert set(states[placed + 1:]) <= {"m", "b"} and found["between_localized_scans"] == states.count("b")
    assert all(states[k] == "b" for k in range(strided + 1, 316) if (k - strided) % 4)
    trajectory = read_tum(tmp_path / "out" / "again.tum")
    np.testing.assert_array_equal(trajectory.stamps_ns, START_NS + np.arange(320) * FAST_PERIOD_NS)
    # The map's frame is the first log's first pose, where this log starts too.
    errors = np.hypot(*(trajectory.planar()[:, :2] - se2.relative(truth[0], truth)[:, :2]).T)
    assert errors[placed:].max() < 0.05


def test_a_fast_log_continued_from_a_session_has_every_scan_of_both_runs(tmp_path: Path) -> None:
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    first_truth = write_drive(first, scans=240, scan_period_ns=FAST_PERIOD_NS)
    # An hour later, from 2 m before where the first stopped, its odometry from its own origin.
    second_truth = write_drive(second, scans=480, part=slice(160, 480), later_ns=3_600_000_000_000,
                               scan_period_ns=FAST_PERIOD_NS)
    runner = CliRunner()
    assert runner.invoke(app, [str(first), "--out", str(tmp_path / "a"), "--quiet"]).exit_code == 0
    result = runner.invoke(app, [str(second), "--continue", str(tmp_path / "a" / "first.session"),
                                 "--out", str(tmp_path / "b"), "--quiet", "--allow-unconverged"])
    assert result.exit_code == 0, result.output
    counts = json.loads((tmp_path / "b" / "second.json").read_text())["counts"]
    # The new run is matched every 4th scan once placed in the saved map (the scans before wait for it).
    assert counts["scans"] == 320 and counts["scans_between"] >= 0.7 * 320
    trajectory = read_tum(tmp_path / "b" / "second.tum")
    assert len(trajectory.stamps_ns) == 240 + 320 - counts["scans_unplaced"]
    truth = np.concatenate([first_truth, second_truth[-(320 - counts["scans_unplaced"]):]])
    errors = np.hypot(*(trajectory.planar()[:, :2] - se2.relative(first_truth[0], truth)[:, :2]).T)
    assert errors.max() < 0.05
