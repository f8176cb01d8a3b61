"""Our 3D SLAM against kiss-slam (the 3D anchor, PyPI `kiss-slam`) on the same frames (issue 12, item 4).

    python benchmarks/kiss_slam_compare.py [--kiss-slam-python /path/to/venv/bin/python] \
        [--shared ../shared] [--out benchmarks/results] [--splitting-distance 100 --splitting-distance 25]

kiss-slam runs in its own interpreter (`benchmarks/kiss_slam_runner.py`; its map_closures pins
numpy < 2.3): make one with `python -m venv V && V/bin/pip install kiss-slam==0.0.2` (open3d, which it
imports, needs the system's libusb-1.0: `apt-get install libusb-1.0-0`).

1. `kitti_city.mcap` (154 real KITTI frames, read in place, never copied; no ground truth in the log):
   the final position of ours (`replay_log`: SGD, then the SE(3) polish), of kiss-slam and of KISS-ICP's
   odometry alone, each against the others, as m and % of the path; the final height of each (the
   start is 0: the street is nearly level); frames/s.
2. The synthetic town loop of the tests (`tests.lidar_world.loop_drive`: 163 sweeps once around the
   block and 12 m further, 32 × 720 LiDAR pitched 2° on a 1.8 m mount, per-point times) with ground
   truth: ATE RMSE of both (positions rigidly aligned to the truth, Kabsch, no scale), the height error
   before and after the SE(3) polish, loop closures found by both, frames/s.
3. Height drift: the same town loop with KISS-ICP's poses made to climb 1 cm per metre driven (1.25 m
   over the loop; the street is level), ours only: heights before and after the SE(3) polish.

Every run gets the same frames and the same per-point times: KITTI's from the azimuths (clockwise from
behind, KISS-ICP's KITTI rule, which our default `azimuth_times=True` applies), the town's from its time
field. kiss-slam's poses are the sensor's at each sweep's end (KISS-ICP's convention): on the town they
are moved to the base with the mount and compared with the truth at that time. Frames/s: ours end to end
(reading, odometry, loop closures, SGD, SE(3) polish, recording, map, files) and our frontend alone;
kiss-slam's processing loop alone (frames in memory, no outputs). Timings depend on the machine's load;
frames per CPU second (process CPU time, every thread: ours end to end, kiss-slam's loop, KISS-ICP alone)
depend on it less, and are what to compare on a shared machine.

Neither figure counts starting up (the interpreter and the imports: rerun, numba's cached kernels, scipy
for ours; open3d, map_closures for kiss-slam): `startup` measures it apart, as a fresh interpreter's CPU
and wall seconds importing what each run imports (for ours what a replay of clouds imports, the 3D
frontend included), and `frames_per_cpu_second_with_startup` adds it. What a user waits for is a whole
process, so `fresh_process_fps` and `frames_per_cpu_second_fresh_process` time one: ours the `replay`
command on the log (interpreter, imports, numba kernels loaded from their cache, reading, everything
written), kiss-slam its runner (interpreter, imports, the frames loaded from their `.npz`, the loop).
`startup` is a plain `python -c`, with the cyclic collector on: the `replay` command pauses it while
importing and freezes what the imports built (`pipeline.launcher`), so ours counts collections (0.1–0.5
CPU s with the machine's load) that the whole process no longer pays.
Start-ups and whole processes alternate `--repeats` times and the fastest of each counts: on a shared
machine the load comes and goes within a run, and the minimum is the figure it disturbs least.

Both start from byte-compiled modules: kiss-slam's were compiled by pip when it was installed, and ours are
compiled first (`compile_bytecode`, into the git-ignored `__pycache__` folders, as installing a wheel does).
Without that, with PYTHONDONTWRITEBYTECODE set (as on the machines this ran on) or a read-only checkout,
every process of ours compiles our ~85 modules from source again (0.2–0.3 CPU s); `--no-bytecode` measures
that case.
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from kiss_icp.config import load_config  # noqa: E402
from kiss_icp.kiss_icp import KissICP  # noqa: E402

from frontends.logs import Cloud3D, open_log  # noqa: E402
from frontends.slam3d import LidarSlam3D, Slam3DConfig, planar, se3  # noqa: E402
from frontends.slam3d.odometry import (  # noqa: E402
    azimuth_point_times,
    normalized_point_times,
)
from pipeline.replay_log import LogReplayResult, replay_log  # noqa: E402
from tests.lidar_world import (  # noqa: E402
    LOOP_STEP,
    LOOP_SWEEPS,
    START_NS,
    SWEEP_PERIOD,
    DistortedOdometry,
    Drive,
    Lidar,
    drive,
    loop_drive,
    planar_to_matrix,
    town_loop,
    write_cloud_log,
)

KITTI = "data/logs/kitti/kitti_city.mcap"
RUNNER = REPO / "benchmarks" / "kiss_slam_runner.py"
OURS_RUNNER = REPO / "benchmarks" / "ours_runner.py"
KISS_SLAM_RESULT = "kiss_slam.npz"
"""What kiss-slam's runner writes into the run's folder (read after every run of it)."""
HEIGHT_DRIFT_RATE = 0.01


@dataclass
class Ours:
    result: LogReplayResult
    lifted: np.ndarray
    """(S, 4, 4) every cloud's pose from the planar optimum (height, roll, pitch from odometry)."""
    polished: np.ndarray
    """(S, 4, 4) after the SE(3) polish."""
    seconds: float
    cpu_seconds: float
    polish_seconds: float


def run_ours(log: Path, out_dir: Path, config: Slam3DConfig) -> Ours:
    """`replay_log` (the SE(3) polish included: `result.poses`), and the poses without the polish."""
    started, cpu_started = time.perf_counter(), time.process_time()
    result = replay_log(log, out_dir=out_dir, slam3d=config)
    seconds, cpu_seconds = time.perf_counter() - started, time.process_time() - cpu_started
    graph = result.frontend.result
    lifted = graph.lift(result.keyframe_poses)
    polish_started = time.perf_counter()  # timed again alone: the replay's total includes it once
    graph.polish_se3(lifted, config.se3_polish.max_iterations)
    polish_seconds = time.perf_counter() - polish_started
    return Ours(result, graph.cloud_poses(lifted), result.poses, seconds, cpu_seconds, polish_seconds)


@dataclass
class KissSlam:
    poses: np.ndarray
    closures: int
    seconds: float
    cpu_seconds: float
    command: list[str]
    process_seconds: float
    """Wall and CPU seconds of its whole process (interpreter, imports, frames loaded, loop, result saved)."""
    process_cpu_seconds: float


PACKAGES = ("pipeline", "frontends", "optimizer")


def ours_environment() -> dict[str, str]:
    """The environment of our processes: this one, with this tree's packages importable."""
    return {**os.environ, "PYTHONPATH": str(REPO)}


def compile_bytecode() -> None:
    """Byte-compile our packages into their `__pycache__` folders (what pip does when installing a wheel):
    Python reads the cached bytecode even when PYTHONDONTWRITEBYTECODE keeps it from writing any."""
    for package in PACKAGES:
        if not compileall.compile_dir(REPO / package, quiet=1):
            raise RuntimeError(f"byte-compiling {package} failed")


def children_cpu() -> float:
    """CPU seconds (user + system, every thread) of the waited-for child processes so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_process(command: list[str], environment: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall and CPU seconds of a fresh process running `command` (which must succeed)."""
    cpu, wall = children_cpu(), time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=environment, cwd=REPO.parent)
    wall, cpu = time.perf_counter() - wall, children_cpu() - cpu
    if done.returncode != 0:
        raise RuntimeError(f"{command[:3]} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    return wall, cpu


def replay_process(python: str, log: Path, out_dir: Path) -> tuple[float, float]:
    """Wall and CPU seconds of the `replay` command on `log` in a fresh `python` process, default settings
    (our packages from this tree, the dependencies `python` has)."""
    command = [python, "-m", "pipeline.launcher", str(log), "--out", str(out_dir)]
    return timed_process(command, ours_environment())


def run_kiss_slam(
    python: str, frames: list[np.ndarray], times: list[np.ndarray], folder: Path, splitting: float | None
) -> KissSlam:
    arrays = {"count": np.array(len(frames))}
    for k, (points, stamps) in enumerate(zip(frames, times, strict=True)):
        arrays[f"points_{k}"] = points
        arrays[f"times_{k}"] = stamps
    np.savez(folder / "frames.npz", **arrays)
    command = [python, str(RUNNER), str(folder / "frames.npz"), str(folder / KISS_SLAM_RESULT)]
    if splitting is not None:
        command += ["--splitting-distance", str(splitting)]
    process_seconds, process_cpu_seconds = timed_process(command)
    out = np.load(folder / KISS_SLAM_RESULT)
    return KissSlam(out["poses"], int(out["closures"]), float(out["seconds"]), float(out["cpu_seconds"]),
                    command, process_seconds, process_cpu_seconds)


def kiss_icp_alone(frames: list[np.ndarray], times: list[np.ndarray]) -> tuple[np.ndarray, float, float]:
    """KISS-ICP's odometry with its own defaults: poses, wall and CPU seconds (frames in memory)."""
    odometry = KissICP(load_config(None))
    poses = []
    started, cpu_started = time.perf_counter(), time.process_time()
    for points, stamps in zip(frames, times, strict=True):
        odometry.register_frame(points, stamps)
        poses.append(odometry.last_pose.copy())
    return np.array(poses), time.perf_counter() - started, time.process_time() - cpu_started


OUR_IMPORTS = (
    "import pipeline.replay_log, frontends.slam3d.session_frontends, pipeline.recording.clouds"
)
"""What `replay_log` imports for a log of clouds: the 3D modules are imported once the log turns out to
hold clouds (`pipeline.replay_log._cloud_sensor`), inside the run's time but for its first log only."""
KISS_SLAM_IMPORTS = "from kiss_slam.config import load_config; from kiss_slam.slam import KissSLAM"


def startup_seconds(python: str, statement: str) -> tuple[float, float]:
    """CPU (user + system, every thread) and wall seconds of a fresh `python -c statement`."""
    wall, cpu = timed_process([python, "-c", statement], ours_environment())
    return cpu, wall


def startup_section(python: str, repeats: int, ours_python: str) -> dict[str, dict[str, float]]:
    """Both start-ups, alternated `repeats` times: the fastest of each (CPU and wall apart)."""
    ours, theirs = [], []
    for _ in range(repeats):
        ours.append(startup_seconds(ours_python, OUR_IMPORTS))
        theirs.append(startup_seconds(python, KISS_SLAM_IMPORTS))
    return {
        "startup_cpu_s": {"ours": min(c for c, _ in ours), "kiss_slam": min(c for c, _ in theirs)},
        "startup_wall_s": {"ours": min(w for _, w in ours), "kiss_slam": min(w for _, w in theirs)},
    }


def with_startup(section: dict[str, object], startup: dict[str, dict[str, float]]) -> None:
    """Add the start-up to the frames per CPU second of both (ours end to end, kiss-slam's loop)."""
    count = int(section["frames"])  # type: ignore[arg-type]
    rates: dict[str, float] = section["frames_per_cpu_second"]  # type: ignore[assignment]
    cpu = startup["startup_cpu_s"]
    section["frames_per_cpu_second_with_startup"] = {
        "ours_end_to_end": count / (count / rates["ours_end_to_end"] + cpu["ours"]),
        "kiss_slam": count / (count / rates["kiss_slam"] + cpu["kiss_slam"]),
    }


def fresh_process_rows(
    count: int, log: Path, out_dir: Path, slam: KissSlam, repeats: int, ours_python: str
) -> dict[str, dict[str, float]]:
    """Frames per wall and CPU second of whole processes, `replay` on `log` and kiss-slam's runner,
    alternated `repeats` times (kiss-slam's first run is `slam`'s): the fastest of each."""
    ours, theirs = [], [(slam.process_seconds, slam.process_cpu_seconds)]
    for k in range(repeats):
        ours.append(replay_process(ours_python, log, out_dir / f"run{k}"))
        if k + 1 < repeats:
            theirs.append(timed_process(slam.command))
    return {
        "fresh_process_fps": {
            "ours": count / min(wall for wall, _ in ours),
            "kiss_slam": count / min(wall for wall, _ in theirs),
        },
        "frames_per_cpu_second_fresh_process": {
            "ours": count / min(cpu for _, cpu in ours),
            "kiss_slam": count / min(cpu for _, cpu in theirs),
        },
    }


def in_memory_rows(run: Drive, folder: Path, slam: KissSlam, repeats: int, ours_python: str
                   ) -> dict[str, object]:
    """Both SLAMs on the frames in memory, each in fresh processes alternated `repeats` times (kiss-slam's
    first is `slam`'s): its runner and `ours_runner.py`, each timing from after its imports and the frames
    loaded to its final poses (no reading, recording or files on either side). Frames/s of the median and
    the fastest process of each, and frames per CPU second of the median."""
    stamps = START_NS + np.arange(len(run.clouds), dtype=np.int64) * int(SWEEP_PERIOD * 1e9)
    arrays: dict[str, np.ndarray] = {"count": np.array(len(run.clouds)), "stamps_ns": stamps,
                                     "sensor_to_base": run.mount}
    for k, (points, times) in enumerate(zip(run.clouds, run.times, strict=True)):
        arrays[f"points_{k}"] = points
        arrays[f"times_{k}"] = times.astype(np.float64)
    np.savez(folder / "ours_frames.npz", **arrays)
    command = [ours_python, str(OURS_RUNNER), str(folder / "ours_frames.npz"), str(folder / "ours.npz")]
    ours, theirs = [], [(slam.seconds, slam.cpu_seconds)]
    closures = set()
    for k in range(repeats):
        timed_process(command, ours_environment())
        out = np.load(folder / "ours.npz")
        ours.append((float(out["seconds"]), float(out["cpu_seconds"])))
        closures.add(int(out["closures"]))
        if k + 1 < repeats:
            timed_process(slam.command)
            theirs_out = np.load(folder / KISS_SLAM_RESULT)
            theirs.append((float(theirs_out["seconds"]), float(theirs_out["cpu_seconds"])))
    count = len(run.clouds)
    return {
        "in_memory_processes": repeats,
        "in_memory_fps_median": {"ours": count / float(np.median([w for w, _ in ours])),
                                 "kiss_slam": count / float(np.median([w for w, _ in theirs]))},
        "in_memory_fps_fastest": {"ours": count / min(w for w, _ in ours),
                                  "kiss_slam": count / min(w for w, _ in theirs)},
        "in_memory_frames_per_cpu_second_median": {
            "ours": count / float(np.median([c for _, c in ours])),
            "kiss_slam": count / float(np.median([c for _, c in theirs]))},
        "in_memory_seconds": {"ours": ", ".join(f"{w:.2f}" for w, _ in ours),
                              "kiss_slam": ", ".join(f"{w:.2f}" for w, _ in theirs)},
        "in_memory_loop_closures_ours": ", ".join(str(c) for c in sorted(closures)),
    }


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def ate_rmse(estimated: np.ndarray, truth: np.ndarray) -> float:
    """RMSE of positions after the rigid (rotation + translation, no scale) alignment that minimises it."""
    a, b = estimated - estimated.mean(axis=0), truth - truth.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = (u @ np.diag([1.0, 1.0, d]) @ vt).T
    return float(np.sqrt(np.mean(np.sum((a @ rotation.T - b) ** 2, axis=1))))


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    return se3.relative(poses[0], poses)


# ----------------------------------------------------------------------------------------------- KITTI


def kitti_section(shared: Path, python: str, repeats: int, ours_python: str) -> dict[str, object]:
    path = shared / KITTI
    with open_log(path) as log:
        frames = [c.points.astype(np.float64) for c in log.clouds()]
    times = [normalized_point_times(azimuth_point_times(f))[0] for f in frames]  # KISS-ICP's KITTI rule
    reference, kiss_icp_seconds, kiss_icp_cpu_seconds = kiss_icp_alone(frames, times)
    config = Slam3DConfig()
    with tempfile.TemporaryDirectory() as folder:
        ours = run_ours(path, Path(folder) / "out", config)
        slam = run_kiss_slam(python, frames, times, Path(folder), None)
        fresh = fresh_process_rows(len(frames), path, Path(folder) / "fresh", slam, repeats, ours_python)
    length = path_length(reference)
    finals = {
        "ours": relative_to_first(ours.polished)[-1],
        "ours_planar_only": relative_to_first(ours.lifted)[-1],
        "kiss_slam": relative_to_first(slam.poses)[-1],
        "kiss_icp": relative_to_first(reference)[-1],
    }

    def gap(a: str, b: str) -> float:
        return float(np.linalg.norm(finals[a][:3, 3] - finals[b][:3, 3]))

    count = len(frames)
    return {
        "frames": count,
        "path_length_m": length,
        "final_position_difference_m": {
            "ours_vs_kiss_icp": gap("ours", "kiss_icp"),
            "kiss_slam_vs_kiss_icp": gap("kiss_slam", "kiss_icp"),
            "ours_vs_kiss_slam": gap("ours", "kiss_slam"),
        },
        "final_height_m": {name: float(final[2, 3]) for name, final in finals.items()},
        "loop_closures": {"ours": ours.result.loop_closures["accepted"], "kiss_slam": slam.closures},
        "fps": {
            "ours_end_to_end": count / ours.seconds,
            "ours_frontend": count / ours.result.wall_time["frontend"],
            "kiss_slam": count / slam.seconds,
            "kiss_icp_alone": count / kiss_icp_seconds,
        },
        "frames_per_cpu_second": {
            "ours_end_to_end": count / ours.cpu_seconds,
            "kiss_slam": count / slam.cpu_seconds,
            "kiss_icp_alone": count / kiss_icp_cpu_seconds,
        },
        **fresh,
    }


# ------------------------------------------------------------------------------------------ town loop


def town_drive(laps: int) -> Drive:
    """The town loop's drive (`loop_drive`), or one `laps` times around: the same start, speed and LiDAR,
    and every further lap adds the loop's perimeter of travel (and its loop closures)."""
    if laps == 1:
        return loop_drive()
    route = town_loop().route
    extra = round((laps - 1) * route.perimeter / LOOP_STEP)
    return drive(town_loop(), sweeps=LOOP_SWEEPS + extra, step=LOOP_STEP, lidar=Lidar(columns=720))


def town_section(python: str, splitting: float | None, repeats: int, ours_python: str,
                 in_memory_repeats: int, laps: int = 1) -> dict[str, object]:
    run = town_drive(laps)
    route = town_loop().route
    columns_fraction = 1.0 - 1.0 / 720  # the last column fires one column short of the full sweep
    truth_at_stamps = planar_to_matrix(run.base_poses)
    truth_at_ends = planar_to_matrix(route.pose(run.distances + columns_fraction * run.speeds))
    config = Slam3DConfig()
    with tempfile.TemporaryDirectory() as folder:
        log = Path(folder) / "town.mcap"
        write_cloud_log(log, run)
        frames = [c.astype(np.float64) for c in run.clouds]
        times = [normalized_point_times(t.astype(np.float64))[0] for t in run.times]
        ours = run_ours(log, Path(folder) / "out", config)
        slam = run_kiss_slam(python, frames, times, Path(folder), splitting)
        fresh = fresh_process_rows(len(frames), log, Path(folder) / "fresh", slam, repeats, ours_python)
        in_memory = in_memory_rows(run, Path(folder), slam, in_memory_repeats, ours_python)
    # ours: base poses at the stamps, for the clouds in the trajectory (from the first keyframe on)
    stamps = ours.result.stamps_ns
    first_index = len(run.clouds) - len(stamps)
    truth = truth_at_stamps[first_index:]
    mount = run.mount
    slam_base = mount @ slam.poses @ se3.inverse(mount)

    def heights(poses: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Height error in the first truth pose's frame (the ground is level: truth z = 0)."""
        aligned = reference[0] @ relative_to_first(poses)
        return aligned[:, 2, 3] - reference[:, 2, 3]

    count = len(run.clouds)
    return {
        "frames": count,
        "path_length_m": float(run.distances[-1] - run.distances[0]),
        "ate_rmse_m": {
            "ours": ate_rmse(ours.polished[:, :3, 3], truth[:, :3, 3]),
            "ours_planar_only": ate_rmse(ours.lifted[:, :3, 3], truth[:, :3, 3]),
            "kiss_slam": ate_rmse(slam_base[:, :3, 3], truth_at_ends[: len(slam_base), :3, 3]),
        },
        "max_height_error_m": {
            "ours": float(np.abs(heights(ours.polished, truth)).max()),
            "ours_planar_only": float(np.abs(heights(ours.lifted, truth)).max()),
            "kiss_slam": float(np.abs(heights(slam_base, truth_at_ends[: len(slam_base)])).max()),
        },
        "final_height_error_m": {
            "ours": float(heights(ours.polished, truth)[-1]),
            "ours_planar_only": float(heights(ours.lifted, truth)[-1]),
            "kiss_slam": float(heights(slam_base, truth_at_ends[: len(slam_base)])[-1]),
        },
        "loop_closures": {"ours": ours.result.loop_closures["accepted"], "kiss_slam": slam.closures},
        "kiss_slam_splitting_distance_m": splitting if splitting is not None else 100.0,
        "fps": {
            "ours_end_to_end": count / ours.seconds,
            "ours_frontend": count / ours.result.wall_time["frontend"],
            "kiss_slam": count / slam.seconds,
        },
        "frames_per_cpu_second": {
            "ours_end_to_end": count / ours.cpu_seconds,
            "kiss_slam": count / slam.cpu_seconds,
        },
        **fresh,
        **in_memory,
        "polish_seconds": ours.polish_seconds,
        "sweep_period_s": SWEEP_PERIOD,
    }


def height_climb(rate: float) -> Callable[[float], np.ndarray]:
    """The sensor climbing `rate` metres per metre driven: the height drift of a LiDAR odometry on a slightly
    mis-estimated pitch, which loop closures (and only the SE(3) polish) can take out."""

    def lift(travel: float) -> np.ndarray:
        matrix = np.eye(4)
        matrix[2, 3] = rate * travel
        return matrix

    return lift


def height_drift_section(rate: float) -> dict[str, object]:
    """The town loop with odometry climbing `rate` m/m: heights after the planar optimum (online,
    lifted) and after the SE(3) polish, against the level truth."""
    run = loop_drive()
    config = Slam3DConfig()
    odometry = DistortedOdometry(height_climb(rate), config.odometry)
    slam = LidarSlam3D(config, sensor_to_base=run.mount, odometry=odometry)
    for k, (points, times) in enumerate(zip(run.clouds, run.times, strict=True)):
        slam.add_cloud(Cloud3D(k, k, "lidar", points, times.astype(np.float64)))
    graph = slam.finish()
    lifted = graph.lift(planar.planar(graph.keyframe_poses))
    started = time.perf_counter()
    polished = graph.polish_se3(lifted, config.se3_polish.max_iterations)
    seconds = time.perf_counter() - started

    def heights(keyframe_poses: np.ndarray) -> np.ndarray:
        return relative_to_first(graph.cloud_poses(keyframe_poses))[:, 2, 3]

    before, after = heights(lifted), heights(polished.poses)
    return {
        "climb_m_per_m": rate,
        "loop_closures": {"ours": graph.loop_closures_accepted},
        "final_height_error_m": {"ours": float(after[-1]), "ours_planar_only": float(before[-1])},
        "max_height_error_m": {
            "ours": float(np.abs(after).max()),
            "ours_planar_only": float(np.abs(before).max()),
        },
        "chi2": {"before_polish": polished.chi2_before, "after_polish": polished.chi2_after},
        "polish_iterations": polished.iterations,
        "polish_seconds": seconds,
    }


def _table(name: str, section: dict[str, object]) -> None:
    print(f"### {name}\n")
    print("| measure | ours | ours, planar only | kiss-slam | KISS-ICP alone |")
    print("|---|---|---|---|---|")
    for key, values in section.items():
        if isinstance(values, dict):
            columns = ("ours", "ours_planar_only", "kiss_slam", "kiss_icp")
            cells = [values.get(k) for k in columns]
            if not set(values) <= set(columns):
                print(f"| {key} | " + ", ".join(f"{k} {_fmt(v)}" for k, v in values.items()) + " | | | |")
            else:
                print(f"| {key} | " + " | ".join(_fmt(c) for c in cells) + " |")
        else:
            print(f"| {key} | {_fmt(values)} | | | |")
    print()


def _fmt(value: object) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--kiss-slam-python",
        default=sys.executable,
        help="an interpreter with kiss-slam installed (default: this one, when the bench extra is installed)",
    )
    parser.add_argument(
        "--ours-python",
        default=sys.executable,
        help="the interpreter of our start-ups and whole processes (default: this one). A venv with only our "
        "runtime dependencies, as a user installs them (`python -m venv V && V/bin/pip install .`), is the "
        "match of kiss-slam's own venv: the test and bench extras (evo, seaborn) bring pandas, which pyarrow "
        "then imports on rerun's first encoding",
    )
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument(
        "--splitting-distance",
        type=float,
        action="append",
        help="kiss-slam local-map length on the town loop (m; repeat for several runs; default its 100)",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="whole processes of each (ours, kiss-slam), alternated; the fastest counts (default 3)",
    )
    parser.add_argument(
        "--in-memory-repeats",
        type=int,
        default=5,
        help="town loop: fresh processes of each runner on the frames in memory, alternated (default 5)",
    )
    parser.add_argument("--town-only", action="store_true", help="skip kitti_city and the height drift run")
    parser.add_argument("--laps", type=int, default=1,
                        help="drive the town loop this many times around (default once, the issue's drive)")
    parser.add_argument(
        "--no-bytecode",
        dest="bytecode",
        action="store_false",
        help="do not byte-compile our packages first (processes then compile what has no cached bytecode)",
    )
    args = parser.parse_args()
    args.shared = args.shared.resolve()  # the timed processes run in the repository's parent folder
    if args.bytecode:
        compile_bytecode()
    results: dict[str, object] = {"bytecode_compiled_first": args.bytecode}
    print("## Ours against kiss-slam\n")
    startup = startup_section(args.kiss_slam_python, args.repeats, args.ours_python)
    results["startup"] = startup
    _table("start-up (a fresh interpreter importing what the run imports)", startup)  # type: ignore[arg-type]
    if args.town_only:
        print("(kitti_city skipped: --town-only)\n")
    elif (args.shared / KITTI).is_file():
        results["kitti_city"] = kitti_section(
            args.shared, args.kiss_slam_python, args.repeats, args.ours_python
        )
        with_startup(results["kitti_city"], startup)  # type: ignore[arg-type]
        _table("kitti_city.mcap (no ground truth: against each other)", results["kitti_city"])  # type: ignore[arg-type]
    else:
        print(f"(skipped kitti_city: {args.shared / KITTI} not found)\n")
    if not args.town_only:
        results["height_drift"] = height_drift_section(HEIGHT_DRIFT_RATE)
        _table(f"town loop, odometry climbing {HEIGHT_DRIFT_RATE} m/m (ours only)", results["height_drift"])  # type: ignore[arg-type]
    for splitting in args.splitting_distance or [None]:
        key = "town_loop" if splitting is None else f"town_loop_split_{splitting:g}"
        key += "" if args.laps == 1 else f"_{args.laps}_laps"
        results[key] = town_section(args.kiss_slam_python, splitting, args.repeats, args.ours_python,
                                    args.in_memory_repeats, args.laps)
        with_startup(results[key], startup)  # type: ignore[arg-type]
        _table(f"synthetic town loop ({key})", results[key])  # type: ignore[arg-type]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "kiss_slam_compare.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
