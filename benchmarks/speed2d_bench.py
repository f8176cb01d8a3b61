"""Benchmark of the 2D path's speed (issue 12, item 6): every 2D log end to end, × real time, per stage.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/speed2d_bench.py [--shared ../shared] [--out benchmarks/results] [--logs ACES CSAIL]
        [--extra LOG ...] [--json speed2d.json] [--repeats 3]

Runs `pipeline.replay_log.replay_log` (what `replay LOG` runs) on every 2D log of the shared data and
prints, per log: the log's duration (first to last scan), the wall and process CPU time of the replay,
× real time (duration / wall time, and duration / CPU time: on a machine shared with other work the CPU
figure is the one that says what the code costs), scans per second, keyframes and loop closures; then the
per-stage profile in CPU seconds (wall seconds in the JSON):

- matching, keyframes (normals and local map), loop search (candidates), verification (branch and bound,
  ICP), online optimization: the frontend's own `StageTimes`;
- reading (decoding the log, scans into the base frame, odometry and tf), final optimization, recording
  (scans, iterations, maps, closing the file), outputs (occupancy grid and files): this benchmark wraps the
  functions the replay calls for them in the same kind of timers while it runs (nothing is changed in
  the library); "other" is the rest (the replay's per-scan loop). The map is made on a thread beside the
  replay from the final poses on, and its files (PNG, PGM, YAML) are written there
  (`replay_log._WrittenBeside`): their time is no stage's, and what the replay still waits for them is in
  "other".

NUMBA_NUM_THREADS is left as `replay` finds it (one thread per core): the wide branch-and-bound searches
(loop closures, scan matching without odometry) share their rotations among those threads. The CPU figures
count every thread's time; the wall figures are what a user waits.

On ACES the relations error against its Freiburg ground truth is printed too (accuracy must not change).

The figures above are measured in one process after a warm-up replay: they leave out what every `replay`
process pays once before its first scan (imports of numba, scipy and rerun, numba's start-up, loading the
compiled kernels from numba's cache). `--repeats N` replays every log N times, round after round over the
logs, prints every run's wall time, and fills the tables with each log's fastest run: on a machine whose
speed swings by a third within minutes (a shared virtual machine) the fastest run is the one that says
what the code costs; the median and the slowest are printed beside it. `--whole-process` also runs
`replay LOG` in a fresh process on every log chosen (`--repeats` times, the fastest kept) and prints that
process's CPU and wall time, start-up included: what a user timing the command sees, where a short log is
mostly start-up (imports, numba's first use; about 1.5 s).
"""

from __future__ import annotations

import argparse
import inspect
import json
import resource
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from frontends.logs import LogReader  # noqa: E402
from frontends.slam2d import frontend as laser_frontend  # noqa: E402
from frontends.slam2d.stage_times import StageTimes  # noqa: E402
from pipeline import recording  # noqa: E402
from pipeline import replay_log as replay_module  # noqa: E402
from pipeline.evaluation import evaluate_files  # noqa: E402
from pipeline.recording import scans as scan_recording  # noqa: E402
from pipeline.replay_log import LogReplayResult, replay_log  # noqa: E402

LOGS = {
    "ACES": "data/logs/aces/aces.mcap",
    "CSAIL mcap": "data/logs/csail/csail.mcap",
    "CSAIL ros1": "data/logs/csail/csail.bag",
    "CSAIL ros2": "data/logs/csail/csail_ros2",
    "CSAIL foxglove": "data/logs/csail/csail_foxglove.mcap",
    "mumble loop": "data/logs/mumble/hallway_room_loop",
    "mumble straight": "data/logs/mumble/straight",
}
BUNDLED_SAMPLE = REPO / "pipeline" / "samples" / "csail_sample.mcap"
ACES_RELATIONS = "data/logs/aces/aces.relations"
TARGET_REAL_TIME = 60.0

STAGES = ("reading", "matching", "keyframes", "loop_search", "verification", "online_optimization",
          "final_optimization", "recording", "outputs", "other")


@dataclass(frozen=True)
class LogRun:
    name: str
    scans: int
    duration_s: float
    wall_s: float
    cpu_s: float
    keyframes: int
    loops_accepted: int
    loops_rejected: int
    stages_cpu_s: dict[str, float]
    stages_wall_s: dict[str, float]

    @property
    def real_time(self) -> float:
        return self.duration_s / self.wall_s

    @property
    def real_time_cpu(self) -> float:
        return self.duration_s / self.cpu_s


class _Timed:
    """`owner.name` replaced by the same callable running inside `times.stage(stage)` (generators: every
    step of the iteration), restored by `restore`."""

    def __init__(self, owner: Any, name: str, stage: str, times: StageTimes) -> None:
        self.owner, self.name = owner, name
        self.original = getattr(owner, name)
        original = self.original

        if inspect.isgeneratorfunction(original):
            def timed(*args: Any, **kwargs: Any) -> Any:
                iterator = original(*args, **kwargs)
                while True:
                    with times.stage(stage):
                        try:
                            item = next(iterator)
                        except StopIteration:
                            return
                    yield item
        else:
            def timed(*args: Any, **kwargs: Any) -> Any:
                if threading.current_thread() is not threading.main_thread():
                    return original(*args, **kwargs)  # the map made and written beside: not a stage
                with times.stage(stage):
                    return original(*args, **kwargs)

        setattr(owner, name, timed)

    def restore(self) -> None:
        setattr(self.owner, self.name, self.original)


REPLAY_STAGES: tuple[tuple[Any, tuple[str, ...], str], ...] = (
    (replay_module, ("open_log",), "reading"),
    (laser_frontend, ("read_odometry", "scans_in_base_frame"), "reading"),
    (LogReader, ("transform_tree", "sensor_topic", "odometry_topic"), "reading"),
    (replay_module, ("optimize_keyframes",), "final_optimization"),
    (recording, ("create_recording", "close_recording", "log_final_map", "log_styles",
                 "log_initial_trajectory", "log_run_properties"), "recording"),
    (recording.IterationRecorder, ("add", "flush"), "recording"),
    (scan_recording.ScanReplayRecording, ("measurement", "frontend_done", "final"), "recording"),
    (laser_frontend, ("occupancy_grid",), "outputs"),
    (replay_module, ("write_tum", "write_g2o", "write_text", "write_png", "map_server_pgm",
                     "map_server_yaml", "picture_with_scale_bar"), "outputs"),
)
"""What the replay calls for each of its own stages (names the replay module does not have are skipped)."""


def timed_replay(path: Path, out: Path) -> tuple[LogReplayResult, StageTimes]:
    times = StageTimes()
    patches = [
        _Timed(owner, name, stage, times)
        for owner, names, stage in REPLAY_STAGES
        for name in names
        if hasattr(owner, name)
    ]
    try:
        result = replay_log(path, out_dir=out)
    finally:
        for patch in reversed(patches):
            patch.restore()
    return result, times


def run_log(name: str, path: Path, out: Path) -> tuple[LogRun, LogReplayResult]:
    wall_started, cpu_started = time.perf_counter(), time.process_time()
    result, replay_times = timed_replay(path, out)
    wall, cpu = time.perf_counter() - wall_started, time.process_time() - cpu_started
    frontend_times = result.frontend.result.stage_times
    stages_cpu: dict[str, float] = {}
    stages_wall: dict[str, float] = {}
    for stage in STAGES[:-1]:
        for times in (frontend_times, replay_times):
            stages_cpu[stage] = stages_cpu.get(stage, 0.0) + times.cpu.get(stage, 0.0)
            stages_wall[stage] = stages_wall.get(stage, 0.0) + times.wall.get(stage, 0.0)
    stages_cpu["other"] = cpu - sum(stages_cpu.values())
    stages_wall["other"] = wall - sum(stages_wall.values())
    stamps = result.stamps_ns
    run = LogRun(
        name=name,
        scans=int(result.counts["scans"]),
        duration_s=float(stamps[-1] - stamps[0]) * 1e-9,
        wall_s=wall,
        cpu_s=cpu,
        keyframes=int(result.counts["keyframes"]),
        loops_accepted=int(result.loop_closures["accepted"]),
        loops_rejected=int(result.loop_closures["rejected"]),
        stages_cpu_s=stages_cpu,
        stages_wall_s=stages_wall,
    )
    return run, result


def print_rounds(every: dict[str, list[LogRun]]) -> None:
    """Every run's wall seconds, and × real time of the fastest, median and slowest run of each log."""
    rounds = len(next(iter(every.values())))
    print(f"## Every run ({rounds} rounds over the logs; the tables below are each log's fastest run)\n")
    print("| log | " + " | ".join(f"round {k + 1} wall (s)" for k in range(rounds))
          + " | × real time: fastest / median / slowest |")
    print("|---|" + "---|" * (rounds + 1))
    for name, log_runs in every.items():
        speeds = sorted((r.real_time for r in log_runs), reverse=True)
        print(f"| {name} | " + " | ".join(f"{r.wall_s:.2f}" for r in log_runs)
              + f" | {speeds[0]:.0f} / {statistics.median(speeds):.0f} / {speeds[-1]:.0f} |")
    print()


def print_tables(runs: list[LogRun]) -> None:
    print("## End to end (`replay_log`)\n")
    print("| log | scans | duration (s) | wall (s) | CPU (s) | × real time (wall) | × real time (CPU) "
          "| scans/s (wall) | keyframes | loops accepted / rejected |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        print(f"| {r.name} | {r.scans} | {r.duration_s:.1f} | {r.wall_s:.2f} | {r.cpu_s:.2f} "
              f"| {r.real_time:.0f} | {r.real_time_cpu:.0f} | {r.scans / r.wall_s:.0f} | {r.keyframes} "
              f"| {r.loops_accepted} / {r.loops_rejected} |")
    stages = list(runs[0].stages_cpu_s)
    # CPU counts every thread of the process (rerun's, BLAS's): the wall table is what the replay waited for.
    for clock, seconds in (("CPU", lambda r: r.stages_cpu_s), ("wall", lambda r: r.stages_wall_s)):
        print(f"\n## Per stage ({clock} s)\n")
        print("| log | " + " | ".join(s.replace("_", " ") for s in stages) + " |")
        print("|---|" + "---|" * len(stages))
        for r in runs:
            print(f"| {r.name} | " + " | ".join(f"{seconds(r)[s]:.2f}" for s in stages) + " |")
    for clock, speed in (("wall", lambda r: r.real_time), ("process CPU", lambda r: r.real_time_cpu)):
        slow = [r.name for r in runs if speed(r) < TARGET_REAL_TIME]
        print(f"\ntarget ≥ {TARGET_REAL_TIME:.0f}× real time ({clock}): "
              f"{'met on every log' if not slow else 'NOT met on ' + ', '.join(slow)}")


def print_aces_accuracy(result: LogReplayResult, relations: Path) -> dict[str, float]:
    s = evaluate_files(result.outputs.tum, relations)
    print("\n## ACES relations error (Kümmerle et al. 2009), against aces.relations\n")
    print("| relations | translation (m) | rotation (deg) |")
    print("|---|---|---|")
    print(f"| {s.count} ({s.unmatched} unmatched) | {s.translation_mean:.4f} ± {s.translation_std:.4f} "
          f"| {s.rotation_mean_deg:.3f} ± {s.rotation_std_deg:.3f} |")
    return {"translation_m": s.translation_mean, "rotation_deg": s.rotation_mean_deg}


def whole_process(path: Path, out: Path) -> tuple[float, float]:
    """Wall and CPU seconds of `replay LOG` in a fresh process (the console script's entry point), start-up
    included."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    command = [sys.executable, "-m", "pipeline.launcher", str(path), "--out", str(out)]
    subprocess.run(command, cwd=REPO, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "speed2d")
    parser.add_argument("--logs", nargs="*", default=None, help=f"a subset of: {', '.join(LOGS)}")
    parser.add_argument("--extra", type=Path, nargs="*", default=[],
                        help="other 2D logs to replay too (e.g. `fast_laser_log.py write`'s), named by file")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--repeats", type=int, default=1,
                        help="replay every log this many times, round after round; the tables show each "
                             "log's fastest run (the machine's load only ever adds time), a first table all")
    parser.add_argument("--whole-process", action="store_true",
                        help="also time `replay` on every log in a fresh process, start-up included")
    args = parser.parse_args()
    chosen = {name: relative for name, relative in LOGS.items() if args.logs is None or name in args.logs}
    chosen.update({path.name: str(path.resolve()) for path in args.extra})  # absolute: `shared /` keeps it
    aces: dict[str, float] | None = None
    with threadpool_limits(limits=1, user_api="blas"):
        # Compile (or load) the numba kernels: the sample has odometry, mumble's straight run has none
        # (the matcher then runs branch and bound on the local map).
        for warmup in (BUNDLED_SAMPLE, args.shared / LOGS["mumble straight"]):
            if warmup.exists():
                replay_log(warmup, out_dir=args.out / "warmup")
        # Round after round over the logs: a spell of a slow machine then falls on every log alike.
        every: dict[str, list[LogRun]] = {}
        for round_ in range(args.repeats):
            for name, relative in chosen.items():
                path = args.shared / relative
                if not path.exists():
                    continue
                run, result = run_log(name, path, args.out / name.replace(" ", "_"))
                every.setdefault(name, []).append(run)
                if name == "ACES" and round_ == 0:  # the replay is deterministic: one score
                    aces = print_aces_accuracy(result, args.shared / ACES_RELATIONS)
                # Not alive during the next replay, as no user's replay has another log's in memory.
                del result
    if not every:
        raise SystemExit(f"no log found under {args.shared}")
    runs = [min(log_runs, key=lambda r: r.wall_s) for log_runs in every.values()]
    print()
    if args.repeats > 1:
        print_rounds(every)
    print_tables(runs)
    if args.whole_process:
        print("\n## Whole process (`replay LOG`, start-up included; fastest of --repeats)\n")
        print("| log | log (s) | wall (s) | CPU (s) | × real time (wall) | × real time (CPU) | "
              "in process, after the warm-up: CPU (s) |")
        print("|---|---|---|---|---|---|---|")
        for run in runs:
            times = [whole_process(args.shared / chosen[run.name], args.out / "whole_process")
                     for _ in range(args.repeats)]
            wall, cpu = min(times)
            log_s = run.duration_s
            print(f"| {run.name} | {log_s:.1f} | {wall:.2f} | {cpu:.2f} | {log_s / wall:.0f} "
                  f"| {log_s / cpu:.0f} | {run.cpu_s:.2f} |")
    if args.json is not None:
        figures: dict[str, Any] = {
            "runs": [
                {**r.__dict__, "real_time": r.real_time, "real_time_cpu": r.real_time_cpu} for r in runs
            ],
            "aces_relations": aces,
        }
        args.json.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
