"""Polish benchmark: how many Levenberg–Marquardt steps each graph needs, whether it converged, time, memory.

    python benchmarks/polish_bench.py [--sizes 10000,100000,1000000] [--skip-real] [--polish-cap N]

Real graphs (M3500, CSAIL, FR079, INTEL) are polished from their file estimate and from the paper's SGD after
10, 30 and 100 iterations; grid worlds (`generate_grid_world(N, seed=0)`) from SGD after 100 iterations, the
default method. Every case runs in a fresh process, so its memory is measured alone: "polish peak RSS Δ" is
the peak resident set while the polish runs (VmHWM, reset through /proc/self/clear_refs once the start is
computed) minus the resident set before it; "process peak" is the whole process's. Numba kernels are
compiled before timing. Timings on a shared machine are noisy: re-run to compare.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable from a checkout without installing the package
    sys.path.insert(0, str(REPO))

from optimizer.graph import PoseGraph  # noqa: E402
from optimizer.graph_files import read_graph  # noqa: E402
from optimizer.gridworld import generate_grid_world  # noqa: E402
from optimizer.polish import PolishStatus, gauss_newton  # noqa: E402
from optimizer.sgd import sgd  # noqa: E402

POSEGRAPHS = REPO.parent / "shared" / "data" / "posegraphs" / "2d"
REAL_GRAPHS = {"M3500.g2o": 137.913, "CSAIL.g2o": 40.5551, "FR079.g2o": 37.5985, "INTEL.g2o": 215.83}
REAL_STARTS = (0, 10, 30, 100)
GRID_SIZES = (10_000, 100_000, 1_000_000)


def _status_kib(field_name: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field_name + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field_name} not in /proc/self/status")


def _release_free_heap() -> None:
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def _warm_up() -> None:
    graph = generate_grid_world(200, seed=1).graph
    for solver in ("direct", "multigrid", "cg"):
        for _ in gauss_newton(graph, linear_solver=solver, max_iterations=2):
            pass
    for _ in sgd(graph, 2):
        pass


def polish_case(graph: PoseGraph, start: np.ndarray, cap: int | None) -> dict:
    """Polish `graph` from `start` in this process, measuring its time and resident-memory peak."""
    _release_free_heap()
    before_kib = _status_kib("VmRSS")
    try:
        Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS to the current RSS
        hwm_reset = True
    except OSError:
        hwm_reset = False
    kwargs = {} if cap is None else {"max_iterations": cap}
    started = time.perf_counter()
    polish = gauss_newton(graph, start, **kwargs)
    final_chi2 = float("nan")
    while True:
        try:
            final_chi2 = next(polish).chi2
        except StopIteration as stop:
            status: PolishStatus = stop.value
            break
    seconds = time.perf_counter() - started
    peak_kib = _status_kib("VmHWM")
    return {
        "iterations": status.iterations, "converged": status.converged, "reason": status.reason,
        "chi2": final_chi2, "seconds": seconds,
        "polish_peak_above_mb": (peak_kib - before_kib) / 1024 if hwm_reset else float("nan"),
        "process_peak_mb": peak_kib / 1024,
    }


def run_case(spec: str, cap: int | None) -> list[dict]:
    """`real:NAME` (every start of REAL_STARTS) or `grid:N` (SGD 100, then the polish)."""
    _warm_up()
    kind, name = spec.split(":", 1)
    results = []
    if kind == "real":
        graph = read_graph(POSEGRAPHS / name).graph
        for sgd_iterations in REAL_STARTS:
            start = graph.poses if sgd_iterations == 0 else list(sgd(graph, sgd_iterations))[-1].poses
            result = polish_case(graph, start, cap)
            results.append({"graph": name, "start": f"SGD {sgd_iterations}" if sgd_iterations else "file",
                            "poses": graph.num_poses, "edges": graph.num_edges, **result})
    else:
        num_poses = int(name)
        started = time.perf_counter()
        graph = generate_grid_world(num_poses, seed=0).graph
        generate_seconds = time.perf_counter() - started
        started = time.perf_counter()
        last = None
        for step in sgd(graph, 100):
            last = step
        assert last is not None
        sgd_seconds = time.perf_counter() - started
        start = last.poses
        del last
        result = polish_case(graph, start, cap)
        results.append({"graph": f"grid world {num_poses:,}", "start": "SGD 100", "poses": graph.num_poses,
                        "edges": graph.num_edges, "generate_seconds": generate_seconds,
                        "sgd_seconds": sgd_seconds, **result})
    return results


def in_subprocess(spec: str, cap: int | None) -> list[dict]:
    command = [sys.executable, str(Path(__file__).resolve()), "--case", spec]
    if cap is not None:
        command += ["--polish-cap", str(cap)]
    completed = subprocess.run(command, capture_output=True, text=True, check=False)
    if completed.returncode != 0:
        raise RuntimeError(f"case {spec} failed:\n{completed.stderr}")
    return json.loads(completed.stdout.strip().splitlines()[-1])


def markdown(results: list[dict]) -> str:
    headers = ["graph", "start", "poses", "edges", "iterations", "χ²", "target", "converged", "polish s",
               "SGD s", "polish peak RSS Δ MB", "process peak MB", "reason"]
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for r in results:
        target = REAL_GRAPHS.get(r["graph"])
        cells = [r["graph"], r["start"], f"{r['poses']:,}", f"{r['edges']:,}", str(r["iterations"]),
                 f"{r['chi2']:.6g}", "" if target is None else f"{target}", "yes" if r["converged"] else "NO",
                 f"{r['seconds']:.1f}", f"{r['sgd_seconds']:.1f}" if "sgd_seconds" in r else "",
                 f"{r['polish_peak_above_mb']:.0f}", f"{r['process_peak_mb']:.0f}", r["reason"]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default=",".join(str(n) for n in GRID_SIZES),
                        help="grid-world sizes, comma-separated (empty: none)")
    parser.add_argument("--skip-real", action="store_true", help="leave out the real graphs")
    parser.add_argument("--polish-cap", type=int, default=None, help="cap on polish iterations (default: "
                        "the polish's own, far above what these graphs need)")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # one case, in this process, as JSON
    args = parser.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(args.case, args.polish_cap)))
        return 0
    specs = [] if args.skip_real else [f"real:{name}" for name in REAL_GRAPHS
                                       if (POSEGRAPHS / name).exists()]
    specs += [f"grid:{int(size)}" for size in args.sizes.split(",") if size.strip()]
    results = []
    for spec in specs:
        results += in_subprocess(spec, args.polish_cap)
        print(f"done {spec}", file=sys.stderr, flush=True)
    print(markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
