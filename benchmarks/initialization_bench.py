"""Initialisation benchmark: from which start Gauss–Newton reaches the lowest χ²; the chordal start's cost.

    python benchmarks/initialization_bench.py [--seeds 3] [--scale 100000 ...]

For every graph in ../shared/data/posegraphs/2d and for M3500-shaped grid worlds
`generate_grid_world(3500, seed=s, odometry_sigma=(0.02, 0.02, σθ))`, σθ ∈ {0.1, 0.2, 0.3}, prints the χ²
that `gauss_newton(graph, poses, max_iterations=1000)` ends at (its last iteration) from
(a) the file / dead-reckoning estimate, (b) paper SGD (100 iterations), (c) the chordal initialisation,
(d) chordal then SGD (100), (e) the ground truth (generated worlds only), and the chordal start's time.
`--scale N` also times the chordal start alone on `generate_grid_world(N, seed=0)` in a fresh process
(peak resident memory above the loaded graph). Timings exclude numba compilation.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable from a checkout without installing the package
    sys.path.insert(0, str(REPO))

from optimizer.cost import chi2  # noqa: E402
from optimizer.errors import OptimizerError  # noqa: E402
from optimizer.graph import PoseGraph  # noqa: E402
from optimizer.graph_files import read_graph  # noqa: E402
from optimizer.gridworld import generate_grid_world  # noqa: E402
from optimizer.initialization import chordal_initialization  # noqa: E402
from optimizer.polish import gauss_newton  # noqa: E402
from optimizer.sgd import sgd  # noqa: E402

POSEGRAPHS = REPO.parent / "shared" / "data" / "posegraphs" / "2d"
HEADING_SIGMAS = (0.1, 0.2, 0.3)
GN_ITERATIONS = 1000
SGD_ITERATIONS = 100
FloatArray = NDArray[np.float64]


def polished_chi2(graph: PoseGraph, poses: FloatArray) -> float:
    value = chi2(graph, poses)
    for step in gauss_newton(graph, poses, max_iterations=GN_ITERATIONS):
        value = step.chi2
    return value


def after_sgd(graph: PoseGraph, poses: FloatArray) -> FloatArray:
    for step in sgd(graph, SGD_ITERATIONS, poses):
        poses = step.poses
    return poses


def timed_chordal(graph: PoseGraph) -> tuple[FloatArray, float]:
    start = time.perf_counter()
    poses = chordal_initialization(graph)
    return poses, time.perf_counter() - start


def row(name: str, graph: PoseGraph, truth: FloatArray | None) -> list[str]:
    chordal, seconds = timed_chordal(graph)
    values = [polished_chi2(graph, graph.poses), polished_chi2(graph, after_sgd(graph, graph.poses)),
              polished_chi2(graph, chordal), polished_chi2(graph, after_sgd(graph, chordal))]
    values.append(polished_chi2(graph, truth) if truth is not None else float("nan"))
    cells = [f"{value:.6g}" if np.isfinite(value) else "–" for value in values]
    best = np.nanmin(values)
    lowest = [bool(value <= best * (1 + 1e-4)) for value in values]
    cells = [f"**{cell}**" if low else cell for cell, low in zip(cells, lowest, strict=True)]
    return [name, *cells, f"{seconds * 1e3:.1f}"]


def print_header() -> None:
    headers = ["graph", "(a) file/DR→GN", "(b) SGD→GN", "(c) chordal→GN", "(d) chordal→SGD→GN",
               "(e) truth→GN", "chordal ms"]
    print("| " + " | ".join(headers) + " |")
    print("|" + "|".join("---" for _ in headers) + "|", flush=True)


def print_row(cells: list[str]) -> None:
    print("| " + " | ".join(cells) + " |", flush=True)


def scale(num_poses: int) -> None:
    """Time and memory of the chordal start alone (run in a fresh process by `main`)."""
    chordal_initialization(generate_grid_world(2_000, seed=0).graph)  # compile the kernels
    graph = generate_grid_world(num_poses, seed=0).graph
    resident = _status_kb("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak resident set to the current one
    _, seconds = timed_chordal(graph)
    peak = _status_kb("VmHWM")
    print(f"| {num_poses} | {graph.num_edges} | {seconds:.2f} | {(peak - resident) / 1024:.0f} |", flush=True)


def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/self/status")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--scale", type=int, nargs="*", default=[])
    parser.add_argument("--only-scale", type=int, help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    if arguments.only_scale is not None:
        scale(arguments.only_scale)
        return

    # Compile every kernel first so that the chordal timings do not include numba's compilation.
    warm = generate_grid_world(300, seed=0)
    polished_chi2(warm.graph, after_sgd(warm.graph, chordal_initialization(warm.graph)))

    print_header()
    for path in sorted(POSEGRAPHS.iterdir()) if POSEGRAPHS.is_dir() else []:
        try:
            graph = read_graph(path, repair_information=True).graph
        except OptimizerError as error:
            print_row([path.name, f"unreadable: {error}", "", "", "", "", ""])
            continue
        print_row(row(path.name, graph, None))
    for sigma in HEADING_SIGMAS:
        for seed in range(arguments.seeds):
            world = generate_grid_world(3500, seed=seed, odometry_sigma=(0.02, 0.02, sigma))
            print_row(row(f"grid 3500 σθ={sigma} seed {seed}", world.graph, world.ground_truth))

    if arguments.scale:
        print("\n| poses | constraints | chordal s | peak RSS Δ MB |\n|---|---|---|---|", flush=True)
        for num_poses in arguments.scale:
            subprocess.run([sys.executable, __file__, "--only-scale", str(num_poses)], check=True)


if __name__ == "__main__":
    main()
