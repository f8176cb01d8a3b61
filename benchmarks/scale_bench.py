"""End to end at the paper's scale: `replay` of a 10⁶-pose grid world written as a g2o file.

Generates `generate_grid_world(N, seed=0)`, writes it with `write_g2o` into a temporary folder, and runs
each replay in a fresh process under `/usr/bin/time -v` (peak RSS of the whole process, wall time). The
process calls `pipeline.replay_graph.replay_graph` (what the `replay` command runs) with a progress
callback that reads VmHWM when the first iteration arrives (peak of reading the file and building the
graph) and resets it, so the table can split the peak between reading and the rest. Time per stage
comes from the replay's own JSON summary. The written outputs are checked: the .g2o has one line per
pose and constraint, the JSON's final χ² is finite and the .rrd is not empty.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python benchmarks/scale_bench.py [--poses 1000000] [--runs sgd:5 sgd+gn] [--keep DIR]

A run is METHOD or METHOD:ITERATIONS (`--iterations` of `replay`; none: the method's default).

`--sgd-probe K` instead times K paper-SGD iterations on the generated graph in this process, wall and CPU
(time.process_time) side by side, split into the kernel's pass over the constraints (which sums the χ² of
the poses it starts from), the stiffness M (recomputed at iterations 1, 2, 4, 8, …) and the last
iteration's separate χ²: CPU time is steadier than wall time on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:  # run as a script: import this checkout's packages
    sys.path.insert(0, str(REPO))

from benchmarks.optimizer_bench import markdown_table  # noqa: E402

GRID_WORLD_SEED = 0
TARGET_SECONDS = 180.0
TARGET_PEAK_MB = 3 * 1024.0
_HWM_READ_KEY = "hwm_read_kib"
_HWM_REST_KEY = "hwm_rest_kib"


def _vm_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def run_replay(graph_path: str, out_dir: str, method: str, iterations: int | None) -> dict:
    """In the child process: the replay, with VmHWM split at the first iteration."""
    from pipeline.replay_graph import replay_graph

    marks: dict[str, int] = {}
    cpu: dict[str, float] = {}

    def progress(iteration: object) -> None:
        if _HWM_READ_KEY not in marks:
            marks[_HWM_READ_KEY] = _vm_kib("VmHWM")
            cpu["read"] = time.process_time()
            try:
                Path("/proc/self/clear_refs").write_text("5")  # peak RSS := current RSS
            except OSError:
                marks["hwm_reset_failed"] = 1

    started = time.perf_counter()
    result = replay_graph(graph_path, out_dir=out_dir, method=method, iterations=iterations,
                          progress=progress)
    marks[_HWM_REST_KEY] = _vm_kib("VmHWM")
    # CPU seconds of the process (imports included in "read"): steadier than wall time on a busy machine
    cpu_read = cpu.get("read", float("nan"))
    return {"seconds": time.perf_counter() - started, **marks, "json": str(result.outputs.json),
            "cpu_read": cpu_read, "cpu_rest": time.process_time() - cpu_read}


def generate(num_poses: int, folder: Path) -> tuple[Path, int, int, float]:
    from optimizer.graph_files import write_g2o
    from optimizer.gridworld import generate_grid_world

    started = time.perf_counter()
    graph = generate_grid_world(num_poses, seed=GRID_WORLD_SEED).graph
    path = folder / f"grid{num_poses}.g2o"
    write_g2o(path, graph)
    return path, graph.num_poses, graph.num_edges, time.perf_counter() - started


def _parse_time_v(stderr: str) -> tuple[float, float]:
    """(wall seconds, peak RSS MB) from GNU time -v."""
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", stderr)
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", stderr)
    seconds = float("nan")
    if wall:
        seconds = 0.0
        for part in wall.group(1).split(":"):
            seconds = 60.0 * seconds + float(part)
    return seconds, int(peak.group(1)) / 1024 if peak else float("nan")


def bench_run(graph_path: Path, out_dir: Path, method: str, iterations: int | None,
              num_poses: int, num_edges: int) -> dict:
    command = [sys.executable, str(Path(__file__).resolve()), "--child", str(graph_path), str(out_dir),
               method, "" if iterations is None else str(iterations)]
    if Path("/usr/bin/time").exists():
        command = ["/usr/bin/time", "-v", *command]
    completed = subprocess.run(command, capture_output=True, text=True, check=False, cwd=REPO)
    if completed.returncode != 0:
        raise RuntimeError(f"replay {method} failed:\n{completed.stdout}\n{completed.stderr}")
    child = json.loads(completed.stdout.strip().splitlines()[-1])
    process_seconds, peak_mb = _parse_time_v(completed.stderr)
    summary = json.loads(Path(child["json"]).read_text())
    outputs = {kind: Path(name) for kind, name in summary["outputs"].items()}
    with outputs["g2o"].open("rb") as file:
        g2o_lines = sum(chunk.count(b"\n") for chunk in iter(lambda: file.read(1 << 24), b""))
    checks = {
        "g2o lines = N + M": g2o_lines == num_poses + num_edges,
        "χ² final finite": math.isfinite(summary["chi2_final"]),
        "rrd written": outputs["rrd"].stat().st_size > 0,
    }
    return {
        "method": method,
        "iterations": summary["iterations"],
        "wall": summary["wall_time_s"],
        "optimize": summary["optimize_time_s"],
        "process_seconds": process_seconds,
        "peak_mb": peak_mb,
        "cpu_read": child["cpu_read"],
        "cpu_rest": child["cpu_rest"],
        "read_peak_mb": child.get(_HWM_READ_KEY, float("nan")) / 1024,
        "rest_peak_mb": child.get(_HWM_REST_KEY, float("nan")) / 1024,
        "rrd_mb": outputs["rrd"].stat().st_size / 2**20,
        "chi2": (summary["chi2_initial"], summary["chi2_final"]),
        "checks": checks,
    }


def report(results: list[dict], num_poses: int, num_edges: int, file_mb: float) -> str:
    rows = []
    for result in results:
        wall, optimize = result["wall"], result["optimize"]
        stages = ", ".join(f"{stage} {count}" for stage, count in result["iterations"].items())
        per_stage = ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in optimize.items())
        rows.append([
            result["method"], stages, f"{wall['load']:.1f}", f"{wall['optimize']:.1f} ({per_stage})",
            f"{wall['record']:.1f}", f"{wall['write']:.1f}", f"{result['process_seconds']:.1f}",
            f"{result['cpu_read']:.1f} + {result['cpu_rest']:.1f}",
            f"{result['read_peak_mb']:.0f}", f"{result['rest_peak_mb']:.0f}", f"{result['peak_mb']:.0f}",
            f"{result['rrd_mb']:.0f}", f"{result['chi2'][0]:.4g} → {result['chi2'][1]:.4g}",
            "yes" if all(result["checks"].values()) else
            "NO: " + ", ".join(name for name, ok in result["checks"].items() if not ok),
        ])
    table = markdown_table(
        ["method", "iterations", "read s", "optimize s (per stage)", "record s", "write s", "process s",
         "CPU s read + rest",
         "peak RSS read MB", "peak RSS rest MB", "peak RSS MB", ".rrd MB", "χ²", "outputs ok"], rows)
    note = (f"Grid world N = {num_poses:,}, M = {num_edges:,} (seed {GRID_WORLD_SEED}), g2o file "
            f"{file_mb:.0f} MB. Stage times from the replay's JSON (read = `load`; record = logging to the "
            "recording between iterations). 'process s' and 'peak RSS MB' are the whole process under "
            "/usr/bin/time -v (interpreter start and imports included); 'peak RSS read' is VmHWM at the "
            "first iteration (file read, graph built), 'rest' the peak after it (optimize, record, write); "
            "'CPU s' splits the process's CPU time at the same point (imports count as read). "
            "Targets "
            f"for the default method: ≤ {TARGET_SECONDS:.0f} s and ≤ {TARGET_PEAK_MB / 1024:.0f} GB.")
    return f"{table}\n\n{note}\n"


def sgd_probe(num_poses: int, iterations: int) -> str:
    """Per-iteration wall and CPU seconds of the paper's SGD, split into its parts (see the module doc)."""
    import numpy as np

    from optimizer.cost import chi2
    from optimizer.gridworld import generate_grid_world
    from optimizer.sgd import recomputes_stiffness
    from optimizer.sgd_kernels import (
        TREE_BLOCK,
        sgd_iteration_tree,
        spanning_count,
        stiffness_tree,
        tree_size,
    )

    small = generate_grid_world(300, seed=1).graph
    graph = generate_grid_world(num_poses, seed=GRID_WORLD_SEED).graph
    rows = []
    for target, count in ((small, 2), (graph, iterations)):  # the small graph compiles the kernels
        n = target.num_poses
        gamma, weights = np.empty(3), np.empty((n, 3))
        tree = np.empty((2 * tree_size(n, TREE_BLOCK), 3, 3))
        spans = np.empty((spanning_count(target.edge_from, target.edge_to, TREE_BLOCK), 3))
        base = target.poses
        for t in range(1, count + 2):
            # Pass t + 1 sums the χ² of iteration t's poses (as `optimizer.sgd` does); the last one's χ² is
            # computed on its own.
            clocks = [(time.perf_counter(), time.process_time())]
            poses = np.empty_like(base)  # also the kernels' `amounts` scratch, as in `optimizer.sgd`
            if t <= count and (t == 1 or recomputes_stiffness(t)):
                stiffness_tree(base, target.edge_from, target.edge_to, target.information, weights, poses,
                               tree, gamma, TREE_BLOCK, spans)
            clocks.append((time.perf_counter(), time.process_time()))
            if t <= count:
                value = sgd_iteration_tree(base, target.edge_from, target.edge_to, target.measurements,
                                           target.information, weights, poses, tree, gamma, t, TREE_BLOCK,
                                           poses, t > 1, spans)
            clocks.append((time.perf_counter(), time.process_time()))
            if t > count:
                value = chi2(target, base)
            clocks.append((time.perf_counter(), time.process_time()))
            base = poses
            if target is graph:
                parts = [(clocks[k + 1][0] - clocks[k][0], clocks[k + 1][1] - clocks[k][1]) for k in range(3)]
                total = (clocks[3][0] - clocks[0][0], clocks[3][1] - clocks[0][1])
                cells = [f"{wall:.3f} / {cpu:.3f}" for wall, cpu in (*parts, total)]
                chi2_cell = "" if t == 1 else f"{value:.6g} (iteration {t - 1})"
                rows.append([t if t <= count else "(end)", *cells, chi2_cell])
    table = markdown_table(["pass", "stiffness s (wall / CPU)", "pass s (with χ² of its start)",
                            "separate χ² s", "total s", "χ²"], rows)
    return (f"{table}\n\nPaper SGD (tree implementation, {TREE_BLOCK} increments per leaf) on the grid world "
            f"N = {graph.num_poses:,}, M = {graph.num_edges:,} (seed {GRID_WORLD_SEED}); one process. "
            "Pass t > 1 also sums the χ² of iteration t − 1 (its starting poses); the last iteration's χ² "
            "is separate.\n")


class _StageClock:
    """CPU seconds (time.process_time) and calls per named stage, gathered by wrapping functions."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.wall: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.peak_mb: dict[str, float] = {}
        self.raised_mb: dict[str, float] = {}
        """How far VmHWM rose during the stage's calls: where the process's peak was set."""

    def wrap(self, owner: object, name: str, stage: str,
             count: Callable[[Any], int] | None = None) -> None:
        function = getattr(owner, name)

        def timed(*args: object, **kwargs: object) -> object:
            started, started_wall = time.process_time(), time.perf_counter()
            peak_before = _vm_kib("VmHWM")
            result = function(*args, **kwargs)
            self.raised_mb[stage] = self.raised_mb.get(stage, 0.0) + (_vm_kib("VmHWM") - peak_before) / 1024
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.process_time() - started
            self.wall[stage] = self.wall.get(stage, 0.0) + time.perf_counter() - started_wall
            self.calls[stage] = self.calls.get(stage, 0) + (count(result) if count else 1)
            self.peak_mb[stage] = max(self.peak_mb.get(stage, 0.0), _vm_kib("VmHWM") / 1024)
            return result

        setattr(owner, name, timed)


def stage_probe(graph_path: Path, out_dir: Path) -> str:
    """The default replay of `graph_path` in this process, CPU seconds split by stage (see `main`)."""
    from optimizer import graph_files, multigrid_solver, polish
    from pipeline import recording, replay_graph

    clock = _StageClock()
    clock.wrap(replay_graph, "read_graph", "read (parse + graph build)")
    clock.wrap(replay_graph, "write_g2o", "write .g2o")
    clock.wrap(polish, "_linearise", "polish: linearise (H, g)")
    clock.wrap(multigrid_solver, "_hierarchy", "polish: AMG hierarchy builds")
    clock.wrap(multigrid_solver, "preconditioned_cg", "polish: CG (iterations)",
               count=lambda result: result[1])
    clock.wrap(polish, "_trial", "polish: trial (update, realignment, χ²)")
    clock.wrap(polish, "aligned_to_anchor", "polish: anchor realignment (within trial)")
    clock.wrap(recording.IterationRecorder, "add", "record: iterations")
    clock.wrap(recording.IterationRecorder, "flush", "record: flush (final whole)")
    del graph_files
    stages: dict[str, list[float]] = {}
    marks = {"cpu": time.process_time(), "wall": time.perf_counter(), "hwm": float(_vm_kib("VmHWM"))}

    def progress(iteration: Any) -> None:
        now, now_wall, hwm = time.process_time(), time.perf_counter(), float(_vm_kib("VmHWM"))
        stage = iteration.stage
        entry = stages.setdefault(stage, [0.0, 0.0, 0, 0.0])
        entry[0] += now - marks["cpu"]
        entry[1] += now_wall - marks["wall"]
        entry[2] += 1
        entry[3] += (hwm - marks["hwm"]) / 1024
        print(f"{stage} {iteration.index}: χ² {iteration.chi2:.10g}, {now - marks['cpu']:.1f} CPU s, "
              f"{now_wall - marks['wall']:.1f} wall s, VmHWM {hwm / 1024:.0f} MB", file=sys.stderr,
              flush=True)
        marks["cpu"], marks["wall"], marks["hwm"] = now, now_wall, hwm

    started_cpu, started = time.process_time(), time.perf_counter()
    result = replay_graph.replay_graph(graph_path, out_dir=out_dir, progress=progress)
    total_cpu, total_wall = time.process_time() - started_cpu, time.perf_counter() - started
    rows = [[stage, f"{seconds:.1f}", f"{clock.wall[stage]:.1f}", str(clock.calls[stage]),
             f"{clock.peak_mb[stage]:.0f}", f"{clock.raised_mb[stage]:.0f}"]
            for stage, seconds in clock.seconds.items()]
    rows += [[f"between yields: {stage} (optimizer + recording)", f"{seconds:.1f}", f"{wall:.1f}", str(count),
              "", f"{raised:.0f}"] for stage, (seconds, wall, count, raised) in stages.items()]
    rows.append(["whole replay_graph", f"{total_cpu:.1f}", f"{total_wall:.1f}", "",
                 f"{_vm_kib('VmHWM') / 1024:.0f}", ""])
    table = markdown_table(["stage", "CPU s", "wall s", "calls", "peak RSS MB so far", "peak raised MB"],
                           rows)
    summary = json.loads(Path(result.outputs.json).read_text())
    return (f"{table}\n\nN = {result.graph.num_poses:,}, M = {result.graph.num_edges:,}; iterations "
            f"{summary['iterations']}; χ² {summary['chi2_initial']:.6g} → {summary['chi2_final']:.10g}; "
            f"converged {summary['converged']} ({summary['stop_reason']}). One process; CPU seconds by "
            "time.process_time; 'so far' is VmHWM after the stage's last call, 'raised' how far VmHWM rose "
            "during its calls (where the peak was set).\n")


def _parse_run(text: str) -> tuple[str, int | None]:
    method, _, iterations = text.partition(":")
    return method, int(iterations) if iterations else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=1_000_000)
    parser.add_argument("--runs", nargs="+", default=["sgd:5", "sgd+gn"],
                        help="METHOD or METHOD:ITERATIONS, each replayed in its own process")
    parser.add_argument("--keep", type=Path, help="keep the generated file and outputs in this folder")
    parser.add_argument("--sgd-probe", type=int, metavar="K",
                        help="time K paper-SGD iterations (wall and CPU, by part) instead of replays")
    parser.add_argument("--stage-probe", action="store_true",
                        help="run the default replay in this process and split its CPU time by stage")
    parser.add_argument("--graph", type=Path, help="use this g2o file instead of generating one")
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.sgd_probe:
        print(sgd_probe(args.poses, args.sgd_probe))
        return 0
    if args.child:
        graph_path, out_dir, method, iterations = args.child
        print(json.dumps(run_replay(graph_path, out_dir, method, int(iterations) if iterations else None)))
        return 0

    folder = Path(tempfile.mkdtemp(prefix="scale_bench_")) if args.keep is None else args.keep
    folder.mkdir(parents=True, exist_ok=True)
    try:
        if args.graph is not None and args.stage_probe:
            # Not read here: the probe's peak RSS is that of one replay in this process.
            print(stage_probe(args.graph, folder / "out_stage_probe"))
            return 0
        if args.graph is not None:
            from optimizer.graph_files import read_graph

            graph_path, seconds = args.graph, 0.0
            counted = read_graph(graph_path).graph
            num_poses, num_edges = counted.num_poses, counted.num_edges
            del counted
        else:
            graph_path, num_poses, num_edges, seconds = generate(args.poses, folder)
        file_mb = graph_path.stat().st_size / 2**20
        print(f"graph {graph_path} ({file_mb:.0f} MB), {seconds:.1f} s to generate", file=sys.stderr)
        if args.stage_probe:
            print(stage_probe(graph_path, folder / "out_stage_probe"))
            return 0
        results = []
        for run in args.runs:
            method, iterations = _parse_run(run)
            out_dir = folder / f"out_{method}_{'default' if iterations is None else iterations}"
            results.append(bench_run(graph_path, out_dir, method, iterations, num_poses, num_edges))
            print(f"{run}: {results[-1]['process_seconds']:.1f} s", file=sys.stderr)
        print(report(results, num_poses, num_edges, file_mb))
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
