"""Robust kernels against false loop closures: M3500 with 0 / 100 / 500 added random false loops.

    python benchmarks/robust_bench.py [--counts 0 100 500] [--seed 1] [--skip-clean]

Prints markdown tables: for every count of false loops, the paper's SGD (100 iterations), the default
SGD→polish, the robust SGD alone and the robust SGD→robust polish (`optimizer.robust.robust_optimize`) for
both kernels, each scored by the χ² of M3500's TRUE edges at the result (and its ratio to the optimum
137.913), the number of false and of true loop closures whose final weight is below 0.1, and the seconds
taken (numba compiled beforehand). Then the robust chain on the clean real graphs, scored by plain χ².
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable from a checkout without installing the package
    sys.path.insert(0, str(REPO))

from optimizer.cost import chi2  # noqa: E402
from optimizer.graph import PoseGraph  # noqa: E402
from optimizer.graph_files import read_graph  # noqa: E402
from optimizer.gridworld import generate_grid_world  # noqa: E402
from optimizer.iteration import Iteration  # noqa: E402
from optimizer.polish import gauss_newton  # noqa: E402
from optimizer.robust import KERNELS, robust_optimize, robust_sgd, robust_weights  # noqa: E402
from optimizer.sgd import sgd  # noqa: E402

POSEGRAPHS = REPO.parent / "shared" / "data" / "posegraphs" / "2d"
M3500_OPTIMUM = 137.913
TARGET_RATIO = 1.01
SGD_ITERATIONS = 100
POLISH_ITERATIONS = 300
CLEAN_GRAPHS = ("M3500.g2o", "INTEL.g2o", "FR079.g2o", "CSAIL.g2o")
FloatArray = NDArray[np.float64]


def with_false_loops(graph: PoseGraph, count: int, seed: int) -> PoseGraph:
    """`graph` plus `count` false loop closures appended after its own constraints.

    Random pairs of distinct non-consecutive poses; the measured translation uniform over the map's
    extent (±the bounding box of the estimate), θ uniform in [−π, π); the information of a randomly drawn
    true loop closure of the graph.
    """
    rng = np.random.default_rng(seed)
    n = graph.num_poses
    first = np.empty(0, dtype=np.int64)
    second = np.empty(0, dtype=np.int64)
    while len(first) < count:
        a = rng.integers(0, n, 2 * count)
        b = rng.integers(0, n, 2 * count)
        keep = np.abs(a - b) > 1
        first = np.concatenate([first, a[keep]])[:count]
        second = np.concatenate([second, b[keep]])[:count]
    extent = graph.poses[:, :2].max(axis=0) - graph.poses[:, :2].min(axis=0)
    measurements = np.column_stack([rng.uniform(-extent[0], extent[0], count),
                                    rng.uniform(-extent[1], extent[1], count),
                                    rng.uniform(-np.pi, np.pi, count)])
    true_loops = np.flatnonzero(~graph.is_odometry)
    information = graph.information[rng.choice(true_loops, count)]
    return PoseGraph(graph.poses, np.concatenate([graph.edge_from, first]),
                     np.concatenate([graph.edge_to, second]),
                     np.concatenate([graph.measurements, measurements]),
                     np.concatenate([graph.information, information]), graph.vertex_ids)


def run(stages: Iterator[Iteration]) -> tuple[FloatArray, str]:
    """Final poses of an optimizer's iterations, and its return value (a status) as text."""
    last = None
    while True:
        try:
            last = next(stages)
        except StopIteration as stop:
            status = _status_text(stop.value)
            break
    if last is None:
        raise RuntimeError("the optimizer yielded nothing")
    return last.poses, status


def _status_text(status: object) -> str:
    if status is None:
        return ""
    return "converged" if getattr(status, "converged", False) else "NOT converged"


def default_chain(graph: PoseGraph) -> Iterator[Iteration]:
    poses = graph.poses
    for step in sgd(graph, SGD_ITERATIONS):
        poses = step.poses
        yield step
    return (yield from gauss_newton(graph, poses, max_iterations=POLISH_ITERATIONS))


def methods(skip_default: bool = False) -> list[tuple[str, str, Callable[[PoseGraph], Iterator[Iteration]]]]:
    rows: list[tuple[str, str, Callable[[PoseGraph], Iterator[Iteration]]]] = [
        ("paper SGD", "-", lambda g: sgd(g, SGD_ITERATIONS))]
    if not skip_default:
        rows.append(("SGD→polish (default)", "-", default_chain))
    for kernel in KERNELS:
        rows.append(("robust SGD", kernel,
                     lambda g, k=kernel: robust_sgd(g, SGD_ITERATIONS, kernel=k)))
        rows.append(("robust SGD→robust polish", kernel,
                     lambda g, k=kernel: robust_optimize(g, k, SGD_ITERATIONS,
                                                         polish_iterations=POLISH_ITERATIONS)))
    return rows


def warm_up() -> None:
    small = generate_grid_world(200, seed=0).graph
    for _, _, method in methods():
        run(method(small))


def false_loop_table(counts: list[int], seed: int, skip_default: bool) -> None:
    m3500 = read_graph(POSEGRAPHS / "M3500.g2o").graph
    true_loops = int(np.count_nonzero(~m3500.is_odometry))
    print(f"\n### M3500 + false loop closures (seed {seed}); χ² on M3500's true edges, "
          f"optimum {M3500_OPTIMUM}\n")
    print("| false loops | method | kernel | χ² true edges | ratio | false w<0.1 | true loops w<0.1 "
          "| seconds | polish |")
    print("|---|---|---|---|---|---|---|---|---|")
    for count in counts:
        graph = with_false_loops(m3500, count, seed)
        for name, kernel, method in methods(skip_default):
            start = time.perf_counter()
            poses, status = run(method(graph))
            seconds = time.perf_counter() - start
            score = chi2(m3500, poses)
            weights_text = ("-", "-")
            if kernel != "-":
                weights = robust_weights(graph, poses, kernel)
                weights_text = (f"{np.count_nonzero(weights[m3500.num_edges:] < 0.1)}/{count}",
                                f"{np.count_nonzero(weights[:m3500.num_edges] < 0.1)}/{true_loops}")
            on_target = score <= TARGET_RATIO * M3500_OPTIMUM
            flag = " ✓" if kernel != "-" and "polish" in name and on_target else ""
            print(f"| {count} | {name} | {kernel} | {score:.6g} | {score / M3500_OPTIMUM:.4g}{flag} | "
                  f"{weights_text[0]} | {weights_text[1]} | {seconds:.2f} | {status or '-'} |", flush=True)


def clean_table() -> None:
    print("\n### Clean graphs (no false loops): plain χ² reached\n")
    print("| graph | default SGD→polish | robust cauchy | robust dcs | seconds (default / cauchy / dcs) |")
    print("|---|---|---|---|---|")
    for name in CLEAN_GRAPHS:
        path = POSEGRAPHS / name
        if not path.exists():
            print(f"| {name} | missing | | | |")
            continue
        graph = read_graph(path).graph
        figures = []
        seconds = []
        for method in (default_chain, *(lambda g, k=kernel: robust_optimize(
                g, k, SGD_ITERATIONS, polish_iterations=POLISH_ITERATIONS) for kernel in KERNELS)):
            start = time.perf_counter()
            poses, status = run(method(graph))
            seconds.append(time.perf_counter() - start)
            figures.append(f"{chi2(graph, poses):.6g} ({status})")
        print(f"| {name} | {' | '.join(figures)} | {' / '.join(f'{s:.1f}' for s in seconds)} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[0, 100, 500])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--skip-clean", action="store_true", help="skip the clean real graphs")
    parser.add_argument("--skip-default", action="store_true",
                        help="skip the non-robust SGD→polish on the false-loop graphs (300 slow LM steps)")
    arguments = parser.parse_args()
    warm_up()
    false_loop_table(arguments.counts, arguments.seed, arguments.skip_default)
    if not arguments.skip_clean:
        clean_table()


if __name__ == "__main__":
    main()
