"""The tree-parameterised SGD (`optimizer.sgd_tree`) against the paper's SGD (`optimizer.sgd`).

    python benchmarks/strong_sgd_bench.py [--quick] [--skip-scale] [--only SECTION ...]

Prints markdown tables: χ² after 10/30/100 iterations of both SGDs on every graph of
../shared/data/posegraphs/2d and on generated grid worlds (from the file's / generated estimate;
"sgd-tree" is the default, `tree="auto"`, with the tree it chose; "uncoupled" is sgd-tree without the
coupled heading step once the descent settles (`coupled_headings=False`, what sgd-tree was before it);
"breadth-first" is what sgd-tree was before TORO's incremental tree was added; "incremental" is TORO's
tree forced); for
M3500-shaped worlds with heavy heading noise, the χ² that Levenberg–Marquardt (`optimizer.polish`) reaches
after each SGD next to the one it reaches from the ground truth; and the time per iteration of both
SGDs on M3500 and a 10⁵-pose grid world (numba compilation excluded). `--quick` drops the 10 000-pose
world and the 10⁵-pose timing.

Two diagnostic sections: "limits", both SGDs after 10⁴ iterations on the small shared graphs (where they
end, not how fast); "basin", on σθ = 0.3 worlds, Levenberg–Marquardt from the ground truth's headings with
positions solved for them (`optimizer.initialization.positions_given_headings`) against LM from the chordal
start (rotation-only headings, positions solved the same way) and LM from the planar SE-Sync headings
(`optimizer.planar_sync`, headings that use the translations; positions solved the same way): which basin
the polish reaches is decided by the headings alone.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable from a checkout without installing the package
    sys.path.insert(0, str(REPO))

from optimizer.benchmark_graphs import gtsam_bundled_graphs  # noqa: E402
from optimizer.cost import chi2  # noqa: E402
from optimizer.errors import OptimizerError  # noqa: E402
from optimizer.graph import PoseGraph  # noqa: E402
from optimizer.graph_files import read_graph  # noqa: E402
from optimizer.gridworld import generate_grid_world  # noqa: E402
from optimizer.initialization import chordal_initialization, positions_given_headings  # noqa: E402
from optimizer.iteration import Iteration  # noqa: E402
from optimizer.planar_sync import planar_sync  # noqa: E402
from optimizer.polish import gauss_newton  # noqa: E402
from optimizer.sgd import sgd  # noqa: E402
from optimizer.sgd_tree import sgd_tree, spanning_tree  # noqa: E402

POSEGRAPHS = REPO.parent / "shared" / "data" / "posegraphs" / "2d"
CHECKPOINTS = (10, 30, 100)
TIMED = ("paper SGD", "sgd-tree")
HEADING_SIGMAS = (0.1, 0.2, 0.3)
LIMIT_ITERATIONS = 10_000
LIMIT_GRAPHS = ("pg1.g2o", "pose2example.txt", "w100.graph")
BASIN_SIGMA = 0.3
BASIN_SEEDS = (0, 1, 2)
SECTIONS = ("chi2", "noisy", "limits", "basin", "timing")
TORO_M3500_AFTER_100 = 248.8
EQUAL_LOOP_SIGMA = (0.02, 0.02, 0.01)
"""The generator's odometry noise: loop closures then weigh like odometry, as in M3500 and city10000."""
FloatArray = NDArray[np.float64]
Optimizer = Callable[[PoseGraph, int], Iterator[Iteration]]
OPTIMIZERS: dict[str, Optimizer] = {"paper SGD": lambda g, n: sgd(g, n),
                                    "sgd-tree": lambda g, n: sgd_tree(g, n),
                                    "uncoupled": lambda g, n: sgd_tree(g, n, coupled_headings=False),
                                    "breadth-first": lambda g, n: sgd_tree(g, n, tree="breadth-first"),
                                    "incremental": lambda g, n: _incremental_or_nothing(g, n)}


def _incremental_or_nothing(graph: PoseGraph, iterations: int) -> Iterator[Iteration]:
    """TORO's tree forced; nothing where it does not exist (a pose without a lower-numbered neighbour)."""
    try:
        spanning_tree(graph, "incremental")
    except OptimizerError:
        return iter(())
    return sgd_tree(graph, iterations, tree="incremental")


def _checkpoints(optimizer: Optimizer, graph: PoseGraph) -> tuple[dict[int, float], FloatArray]:
    values: dict[int, float] = dict.fromkeys(CHECKPOINTS, float("nan"))
    poses = graph.poses
    for step in optimizer(graph, max(CHECKPOINTS)):
        if step.index in CHECKPOINTS:
            values[step.index] = step.chi2
        poses = step.poses
    return values, poses


def _polished(graph: PoseGraph, poses: FloatArray) -> float:
    result = chi2(graph, poses)
    for step in gauss_newton(graph, poses, max_iterations=1000):
        result = step.chi2
    return result


def _graphs(quick: bool, extra: Sequence[Path] = ()) -> list[tuple[str, PoseGraph]]:
    # Repair clamps only singular information (pg1.g2o's first edge); every other file is read as is.
    graphs = [(path.name, read_graph(path, repair_information=True).graph)
              for path in sorted(POSEGRAPHS.glob("*")) if path.suffix in (".g2o", ".graph", ".txt")]
    graphs += [(f"{path.name} (--graph)", read_graph(path).graph) for path in extra]
    graphs.append(("grid world 3500 (seed 0)", generate_grid_world(3500, seed=0).graph))
    graphs.append(("grid world 3500 (seed 0), loops as certain as odometry",
                   generate_grid_world(3500, seed=0, loop_sigma=EQUAL_LOOP_SIGMA).graph))
    if not quick:
        graphs += [(f"{path.name} (GTSAM's data)", read_graph(path).graph) for path in gtsam_bundled_graphs()]
        graphs.append(("grid world 10000 (seed 0)", generate_grid_world(10000, seed=0).graph))
        graphs.append(("grid world 10000 (seed 0), loops as certain as odometry",
                       generate_grid_world(10000, seed=0, loop_sigma=EQUAL_LOOP_SIGMA).graph))
    return graphs


def chi2_table(quick: bool, extra: Sequence[Path] = ()) -> None:
    print("## χ² after 10 / 30 / 100 iterations from the file's estimate\n")
    print("| graph | N | M | initial χ² | sgd-tree's tree | " + " | ".join(
        f"{name} {k}" for name in OPTIMIZERS for k in CHECKPOINTS) + " |")
    print("|---|---:|---:|---:|---|" + "---:|" * (len(OPTIMIZERS) * len(CHECKPOINTS)))
    for label, graph in _graphs(quick, extra):
        cells = []
        for optimizer in OPTIMIZERS.values():
            values, _ = _checkpoints(optimizer, graph)
            cells += [f"{values[k]:.6g}" for k in CHECKPOINTS]
        print(f"| {label} | {graph.num_poses} | {graph.num_edges} | {chi2(graph):.4g} | "
              f"{spanning_tree(graph).kind} | " + " | ".join(cells) + " |", flush=True)
    print(f"\nTORO (Grisetti et al. 2007) reports {TORO_M3500_AFTER_100} on M3500 after 100 iterations.\n")


def noisy_heading_table() -> None:
    print("## M3500-shaped worlds with heavy heading noise: SGD, then Levenberg–Marquardt (≤ 1000 steps)\n")
    print("`generate_grid_world(3500, seed=s, odometry_sigma=(0.02, 0.02, σθ))`; 'LM from truth' is the "
          "best basin known.\n")
    print("| σθ | seed | LM from truth | " + " | ".join(
        f"{name} {k}" for name in OPTIMIZERS for k in CHECKPOINTS) + " | " + " | ".join(
        f"{name} → LM" for name in OPTIMIZERS) + " |")
    print("|---:|---:|---:|" + "---:|" * (len(OPTIMIZERS) * (len(CHECKPOINTS) + 1)))
    for sigma in HEADING_SIGMAS:
        for seed in (0, 1):
            world = generate_grid_world(3500, seed=seed, odometry_sigma=(0.02, 0.02, sigma))
            graph = world.graph
            cells, polished = [], []
            for optimizer in OPTIMIZERS.values():
                values, poses = _checkpoints(optimizer, graph)
                cells += [f"{values[k]:.4g}" for k in CHECKPOINTS]
                polished.append(f"{_polished(graph, poses):.6g}")
            print(f"| {sigma} | {seed} | {_polished(graph, world.ground_truth):.6g} | " + " | ".join(cells)
                  + " | " + " | ".join(polished) + " |", flush=True)
    print()


def limits_table() -> None:
    print(f"## Where both SGDs end: χ² after 100, 1 000 and {LIMIT_ITERATIONS:,} iterations\n")
    print("The paper's SGD follows an approximate gradient (a pose's heading does not turn its constraints' "
          "measured translations) and tends to where it vanishes, not to the minimum; sgd-tree takes the "
          "turn into account once its χ² all but stops changing.\n")
    marks = (100, 1000, LIMIT_ITERATIONS)
    print("| graph | optimum (LM) | " + " | ".join(f"{name} {k}" for name in TIMED for k in marks) + " |")
    print("|---|---:|" + "---:|" * (len(TIMED) * len(marks)))
    for name in LIMIT_GRAPHS:
        graph = read_graph(POSEGRAPHS / name, repair_information=True).graph
        cells = []
        for label in TIMED:
            values = {step.index: step.chi2 for step in OPTIMIZERS[label](graph, LIMIT_ITERATIONS)
                      if step.index in marks}
            cells += [f"{values[k]:.6g}" for k in marks]
        print(f"| {name} | {_polished(graph, graph.poses):.6g} | " + " | ".join(cells) + " |", flush=True)
    print()


def basin_table() -> None:
    print(f"## σθ = {BASIN_SIGMA} worlds: the headings decide the basin\n")
    print("Every start is polished by LM (≤ 1000 steps). Positions are solved for the given headings "
          "(`positions_given_headings`); the chordal start is the same with rotation-only headings.\n")
    print("| seed | LM from truth | truth headings + positions: start χ² | → LM | chordal: start χ² | → LM "
          "| sync: start χ² | → LM | sync s (loaded or not: see uptime) | Q products |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for seed in BASIN_SEEDS:
        world = generate_grid_world(3500, seed=seed, odometry_sigma=(0.02, 0.02, BASIN_SIGMA))
        graph = world.graph
        truth_headings = positions_given_headings(graph, world.ground_truth)
        chordal = chordal_initialization(graph)
        started = time.perf_counter()
        sync = planar_sync(graph)
        seconds = time.perf_counter() - started
        print(f"| {seed} | {_polished(graph, world.ground_truth):.6g} | {chi2(graph, truth_headings):.6g} | "
              f"{_polished(graph, truth_headings):.6g} | {chi2(graph, chordal):.6g} | "
              f"{_polished(graph, chordal):.6g} | {chi2(graph, sync.poses):.6g} | "
              f"{_polished(graph, sync.poses):.6g} | {seconds:.2f} | {sync.evaluations} |", flush=True)
    print()


def _seconds_per_iteration(optimizer: Optimizer, graph: PoseGraph, iterations: int) -> float:
    for _ in optimizer(graph, 2):  # compile (cached kernels still pay a first-call load)
        pass
    start = time.perf_counter()
    for _ in optimizer(graph, iterations):
        pass
    return (time.perf_counter() - start) / iterations


def timing_table(quick: bool) -> None:
    print("## Time per iteration (χ² evaluation included; measured on whatever load the machine has)\n")
    print("| graph | N | M | " + " | ".join(f"{name} s/iteration" for name in TIMED) + " |")
    print("|---|---:|---:|" + "---:|" * len(TIMED))
    cases = [("M3500.g2o", read_graph(POSEGRAPHS / "M3500.g2o").graph, 100)]
    if not quick:
        cases.append(("grid world 100000 (seed 0)", generate_grid_world(100_000, seed=0).graph, 5))
    for label, graph, iterations in cases:
        cells = [f"{_seconds_per_iteration(optimizer, graph, iterations):.4g}"
                 for name, optimizer in OPTIMIZERS.items() if name in TIMED]
        print(f"| {label} | {graph.num_poses} | {graph.num_edges} | " + " | ".join(cells) + " |", flush=True)
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="skip the 10 000-pose world and 10⁵-pose timing")
    parser.add_argument("--skip-scale", action="store_true", help="skip the timing table")
    parser.add_argument("--graph", action="append", type=Path, default=[],
                        help="a graph file to add to the χ² table (repeatable), e.g. SE-Sync's "
                             "data/city10000.g2o and data/MIT.g2o: the graphs of TORO's figures in issue 9, "
                             "not in ../shared")
    parser.add_argument("--only", action="append", choices=SECTIONS,
                        help="run only this section (repeatable); default: all but the diagnostics "
                             "'limits' and 'basin'")
    arguments = parser.parse_args()
    sections = set(arguments.only or ("chi2", "noisy", "timing"))
    if arguments.skip_scale:
        sections.discard("timing")
    if "chi2" in sections:
        chi2_table(arguments.quick, arguments.graph)
    if "noisy" in sections:
        noisy_heading_table()
    if "limits" in sections:
        limits_table()
    if "basin" in sections:
        basin_table()
    if "timing" in sections:
        timing_table(arguments.quick)


if __name__ == "__main__":
    main()
