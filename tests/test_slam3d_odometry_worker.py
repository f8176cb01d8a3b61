"""KISS-ICP in a worker process (`frontends.slam3d.odometry_worker`): the same steps as in this process, bit
for bit, and a worker that never outlives its replay (errors, a stream stopped early, signals)."""

from __future__ import annotations

import dataclasses
import gc
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from frontends.errors import FrontendError
from frontends.logs import Cloud3D, open_log
from frontends.slam3d import LidarFrontend
from frontends.slam3d.config import OdometryConfig, Slam3DConfig
from frontends.slam3d.odometry import InlineOdometry, KissOdometry
from frontends.slam3d.odometry_worker import STOP_GRACE_S, OdometryWorker, OdometryWorkerError, start_odometry
from frontends.slam3d.slam import CloudEstimate, LidarSlam3D, Slam3DGraph
from pipeline.replay_log import replay_log
from tests.lidar_world import Drive, Lidar, drive, planar_to_matrix, town_loop, write_cloud_log
from tests.pipeline_fixtures import modules_a_fresh_replay_loads

REPO = Path(__file__).resolve().parents[1]
ONE_THREAD = Slam3DConfig(odometry=OdometryConfig(max_threads=1))
"""KISS-ICP sums its normal equations over threads in whatever order they finish: bit-for-bit comparisons
need one thread (its results with several differ in the last digits from run to run, in either process)."""
MULTI_CORE = len(os.sched_getaffinity(0)) > 1
WORKER_MODULE = "frontends.slam3d.kiss_registration"


@pytest.fixture(scope="module")
def short_drive() -> Drive:
    return drive(town_loop(), sweeps=16, step=0.6, lidar=Lidar(columns=360))


@pytest.fixture(scope="module")
def cloud_log(short_drive: Drive, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("clouds") / "short.mcap"
    write_cloud_log(path, short_drive)
    return path


def _clouds(run: Drive) -> list[Cloud3D]:
    """The drive's clouds, one of them cut below `min_points` (the odometry declines it)."""
    clouds = [Cloud3D(k, k, "lidar", points, times.astype(np.float64))
              for k, (points, times) in enumerate(zip(run.clouds, run.times, strict=True))]
    cut = clouds[7]
    clouds[7] = dataclasses.replace(cut, points=cut.points[:50], point_times=cut.point_times[:50])
    return clouds


def _vehicle_odometry(run: Drive) -> list[np.ndarray | None]:
    """Wheel odometry for most clouds (the registration's motion guess), none for a few."""
    poses: list[np.ndarray | None] = list(planar_to_matrix(run.base_poses + np.array([0.01, -0.02, 0.003])))
    poses[3] = poses[11] = None
    return poses


def _same_estimates(ours: list[CloudEstimate], theirs: list[CloudEstimate]) -> None:
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs, strict=True):
        assert (a.tracked, a.keyframe, a.new_loop_closures) == (b.tracked, b.keyframe, b.new_loop_closures)
        np.testing.assert_array_equal(a.pose, b.pose)


def _same_graphs(ours: Slam3DGraph, theirs: Slam3DGraph) -> None:
    for name in ("keyframe_poses", "keyframe_odometry", "relative", "information", "cloud_offsets",
                 "cloud_keyframes", "edge_from", "edge_to"):
        np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), err_msg=name)
    for a, b in zip(ours.keyframe_clouds, theirs.keyframe_clouds, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_worker_registers_as_kiss_icp_in_this_process_bit_for_bit(short_drive: Drive) -> None:
    clouds, odometry = _clouds(short_drive), _vehicle_odometry(short_drive)
    inline = LidarSlam3D(ONE_THREAD, sensor_to_base=short_drive.mount)
    expected = [inline.add_cloud(cloud, pose) for cloud, pose in zip(clouds, odometry, strict=True)]
    assert not expected[7].tracked and all(e.tracked for k, e in enumerate(expected) if k != 7)
    with OdometryWorker(ONE_THREAD.odometry) as worker:
        ahead = LidarSlam3D(ONE_THREAD, sensor_to_base=short_drive.mount, odometry=worker)
        found = []
        for k, (cloud, pose) in enumerate(zip(clouds, odometry, strict=True)):
            upcoming = (clouds[k + 1], odometry[k + 1]) if k + 1 < len(clouds) else (None, None)
            found.append(ahead.add_cloud(cloud, pose, *upcoming))
    _same_estimates(found, expected)
    _same_graphs(ahead.finish(), inline.finish())


def test_a_replay_gives_the_poses_of_the_slam_in_this_process(cloud_log: Path, tmp_path: Path) -> None:
    result = replay_log(cloud_log, out_dir=tmp_path / "out", slam3d=ONE_THREAD, iterations=5)
    frontend = result.frontend
    assert isinstance(frontend, LidarFrontend)
    inline = LidarSlam3D(ONE_THREAD, sensor_to_base=frontend.sensor_to_base)
    with open_log(cloud_log) as log:
        for cloud in log.clouds():
            inline.add_cloud(cloud)
    _same_graphs(frontend.result, inline.finish())


@pytest.mark.skipif(not MULTI_CORE, reason="on one core KISS-ICP runs in the replay's own process")
def test_a_cloud_replay_leaves_kiss_icp_s_settings_to_its_worker(cloud_log: Path, tmp_path: Path) -> None:
    # Start-up: KISS-ICP's settings (pydantic-settings, 0.2 s of imports) and registration modules load in
    # the worker process, beside the replay's own imports.
    loaded = modules_a_fresh_replay_loads(cloud_log, tmp_path / "out", (
        "kiss_icp.config", "kiss_icp.kiss_icp", "kiss_icp.registration", "pydantic_settings"))
    assert loaded == []


def test_on_one_core_kiss_icp_runs_in_this_process(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: {0})
    assert isinstance(start_odometry(OdometryConfig()), InlineOdometry)


# --- the worker stops ----------------------------------------------------------------------------------


def _workers_of(pid: int) -> list[int]:
    """The running (not zombie) odometry workers whose parent is `pid`."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes()
        except (OSError, NotADirectoryError):
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == pid and fields[0] != "Z" and WORKER_MODULE.encode() in command:
            found.append(int(entry.name))
    return found


def _gone(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat[stat.rindex(")") + 2:].split()[0] == "Z"


def _wait_for(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def test_a_closed_or_dropped_worker_stops(short_drive: Drive) -> None:
    busy = OdometryWorker(OdometryConfig())
    busy.submit(short_drive.clouds[0], None, None)  # closed while it registers a cloud
    busy.close()
    assert busy._process.returncode is not None
    with pytest.raises(OdometryWorkerError, match="closed"):
        busy.receive()
    dropped = OdometryWorker(OdometryConfig())
    pid = dropped.pid
    del dropped
    gc.collect()
    _wait_for(lambda: _gone(pid), STOP_GRACE_S + 5, "the dropped worker to stop")


def test_a_worker_that_dies_is_an_error_not_a_hang(short_drive: Drive) -> None:
    worker = OdometryWorker(OdometryConfig())
    worker.submit(short_drive.clouds[0], None, None)
    os.kill(worker.pid, signal.SIGKILL)
    with pytest.raises(OdometryWorkerError, match=r"stopped \(exit code -9\)"):
        worker.receive()
    with pytest.raises(OdometryWorkerError):
        worker.submit(short_drive.clouds[1], None, None)


def test_kiss_icp_s_errors_come_back_as_the_frontend_s(short_drive: Drive) -> None:
    with OdometryWorker(OdometryConfig(deskew=False)) as worker:
        worker.submit(short_drive.clouds[0][:, :2], None, None)  # no third coordinate
        with pytest.raises(OdometryWorkerError, match="the odometry failed"):
            worker.receive()
        _wait_for(lambda: _gone(worker.pid), STOP_GRACE_S + 5, "the failed worker to exit")


def test_the_queue_takes_one_cloud_at_a_time(short_drive: Drive) -> None:
    for queue in (InlineOdometry(KissOdometry()), OdometryWorker(OdometryConfig())):
        with pytest.raises(FrontendError, match="no cloud was submitted"):
            queue.receive()
        queue.submit(short_drive.clouds[0], None, None)
        with pytest.raises(FrontendError, match="before the last one was received"):
            queue.submit(short_drive.clouds[1], None, None)
        assert queue.receive() is not None
        queue.close()


def test_a_stream_stopped_early_stops_the_worker(cloud_log: Path, tmp_path: Path) -> None:
    with open_log(cloud_log) as log:
        frontend = LidarFrontend(log, "/points")
        for count, cloud in enumerate(frontend.measurements()):
            frontend.add(cloud)  # submits the next cloud too: one is in flight when the stream stops
            if count == 2:
                break
        assert len(_workers_of(os.getpid())) == 1
        frontend.close()
    assert _workers_of(os.getpid()) == []

    def fail_at_the_third(estimate: object) -> None:
        if getattr(estimate, "index", 0) == 2:
            raise RuntimeError("the consumer stopped")

    with pytest.raises(RuntimeError, match="the consumer stopped"):
        replay_log(cloud_log, out_dir=tmp_path / "out", on_measurement=fail_at_the_third)
    assert _workers_of(os.getpid()) == []


@pytest.mark.skipif(not MULTI_CORE, reason="on one core KISS-ICP runs in the replay's own process")
@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_a_replay_stopped_by_a_signal_leaves_no_worker(cloud_log: Path, tmp_path: Path,
                                                       signal_number: int) -> None:
    replay = subprocess.Popen(
        [sys.executable, "-m", "pipeline.launcher", str(cloud_log), "--out", str(tmp_path / "out"),
         "--quiet"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: bool(_workers_of(replay.pid)) or replay.poll() is not None, 120,
                  "the replay's worker to start")
        workers = _workers_of(replay.pid)
        assert len(workers) == 1, replay.stderr.read() if replay.poll() is not None and replay.stderr else ""
        replay.send_signal(signal_number)
        code = replay.wait(timeout=60)
    finally:
        if replay.poll() is None:
            replay.kill()
    stderr = replay.stderr.read() if replay.stderr else ""
    if signal_number == signal.SIGKILL:
        assert code == -signal.SIGKILL
    else:
        # 0: it had finished before the signal came
        assert code in (0, 128 + signal_number), stderr
        assert "Traceback" not in stderr
    # after SIGKILL the worker sees its requests end and exits by itself
    _wait_for(lambda: _gone(workers[0]), STOP_GRACE_S + 10, "the worker to stop")
