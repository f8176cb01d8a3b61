"""Hard pose graphs for the optimizer benchmark and its tests, made reproducibly from real or generated ones.

- `reversed_anisotropic_variant`: every loop closure stored reversed (b → a) with the exact inverse
  measurement and a strongly anisotropic information, the paper's other hard case;
- `with_false_loops`: random false loop closures added to a graph, scored afterwards on the true edges only
  (`true_edges_chi2`);
- `noisy_manhattan`: M3500-sized grid worlds with heavy odometry-angle noise, i.e. very poor starts;
- `odometry_chain`: the start obtained by composing the odometry constraints from pose 0;
- `gtsam_bundled_graphs`: real 2D graphs that are not in `../shared` but ship inside GTSAM's Python wheel
  (the benchmarks' extra), found by path without importing it.

Edges are kept as stored (a > b allowed), as `PoseGraph.build` keeps them; building through it also
validates the result (positive definite information, a connected graph).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from optimizer import se2
from optimizer.cost import chi2
from optimizer.errors import GraphError
from optimizer.graph import PoseGraph, reverse_constraints
from optimizer.gridworld import GridWorld, generate_grid_world

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

ANISOTROPY_RANGE = (1e3, 1e4)
"""Ratio between the largest and smallest translation information of a variant's loop closure, drawn
log-uniformly in this range."""
M3500_POSES = 3500
MANHATTAN_ODOMETRY_SIGMA_XY = 0.02
GTSAM_BUNDLED_GRAPHS = ("w10000.graph",)
"""TORO's 10 000-pose Manhattan world (64 311 constraints; its 5 875 EQUIV lines are skipped, as GTSAM's
and g2o's readers skip them), in GTSAM's `Data` folder."""


def gtsam_bundled_graphs() -> list[Path]:
    """The `GTSAM_BUNDLED_GRAPHS` that the installed GTSAM wheel carries (none without GTSAM)."""
    spec = importlib.util.find_spec("gtsam")
    if spec is None or spec.origin is None:
        return []
    folder = Path(spec.origin).parent / "Data"
    return [folder / name for name in GTSAM_BUNDLED_GRAPHS if (folder / name).is_file()]


def loop_closures(graph: PoseGraph) -> BoolArray:
    """Mask of the constraints that are not between consecutive poses (|b − a| > 1), in either direction."""
    return ~graph.is_odometry


def reversed_anisotropic_variant(graph: PoseGraph, seed: int) -> PoseGraph:
    """`graph` with every loop closure a → b stored as b → a, anisotropic; odometry kept as it is.

    Each loop closure first gets a forward information D in a's frame: its translation block has the
    eigenvalues s·√r and s/√r along a random direction (r log-uniform in `ANISOTROPY_RANGE`, s the
    square root of the determinant of the original translation block, so the volume is kept), its θθ entry
    is the original's and its cross terms are zero. The edge is then stored reversed with z' = z⁻¹ and
    Ω' = Ad(z⁻¹)ᵀ·D·Ad(z⁻¹), the information under which the reversed error e' ≈ −Ad(z)·e costs, to first
    order, what e costs under D. Edges already stored reversed are reversed back the same way.
    """
    loops = np.flatnonzero(loop_closures(graph))
    if len(loops) == 0:
        raise GraphError("the graph has no loop closures to reverse")
    rng = np.random.default_rng(seed)
    low, high = np.log10(ANISOTROPY_RANGE)
    ratio = 10.0 ** rng.uniform(low, high, size=len(loops))
    direction = rng.uniform(0.0, np.pi, size=len(loops))
    forward_information = _anisotropic_information(graph.information[loops], ratio, direction)

    measurements = graph.measurements.copy()
    information = graph.information.copy()
    edge_from = graph.edge_from.copy()
    edge_to = graph.edge_to.copy()
    measurements[loops], information[loops] = reverse_constraints(graph.measurements[loops],
                                                                   forward_information)
    edge_from[loops], edge_to[loops] = graph.edge_to[loops], graph.edge_from[loops]
    return _graph_with_edges(graph, edge_from, edge_to, measurements, information)


def _anisotropic_information(original: FloatArray, ratio: FloatArray, direction: FloatArray) -> FloatArray:
    translation = original[:, :2, :2]
    scale = np.sqrt(np.linalg.det(translation))
    c, s = np.cos(direction), np.sin(direction)
    rotation = np.stack([np.stack([c, -s], axis=-1), np.stack([s, c], axis=-1)], axis=-2)
    eigenvalues = np.stack([scale * np.sqrt(ratio), scale / np.sqrt(ratio)], axis=-1)
    information = np.zeros_like(original)
    information[:, :2, :2] = np.einsum("mij,mj,mkj->mik", rotation, eigenvalues, rotation)
    information[:, 2, 2] = original[:, 2, 2]
    return information


def with_false_loops(graph: PoseGraph, count: int, seed: int) -> PoseGraph:
    """`graph` with `count` random false loop closures appended after its own constraints.

    Each joins a random pair of distinct, non-consecutive poses (earlier → later; pairs distinct from each
    other); its measurement has x, y uniform in ±half the larger side of the estimate's bounding box and θ
    uniform in [−π, π); its information is that of a randomly chosen true loop closure of `graph`.
    """
    if count < 0:
        raise GraphError(f"count must be >= 0, got {count}")
    true_loops = np.flatnonzero(loop_closures(graph))
    if len(true_loops) == 0:
        raise GraphError("the graph has no loop closures whose information false ones could copy")
    num_poses = graph.num_poses
    # Pairs (a, b) with b − a ≥ 2: a from 0..N−3; their number must cover `count`.
    if count > (num_poses - 1) * (num_poses - 2) // 2:
        raise GraphError(f"{num_poses} poses have fewer than {count} non-consecutive pairs")
    rng = np.random.default_rng(seed)
    earlier, later = _distinct_non_consecutive_pairs(rng, num_poses, count)

    half_extent = 0.5 * float(np.max(np.ptp(graph.poses[:, :2], axis=0)))
    false_measurements = np.empty((count, 3))
    false_measurements[:, :2] = rng.uniform(-half_extent, half_extent, size=(count, 2))
    false_measurements[:, 2] = rng.uniform(-np.pi, np.pi, size=count)
    false_information = graph.information[rng.choice(true_loops, size=count)]
    return _graph_with_edges(
        graph,
        np.concatenate([graph.edge_from, earlier]),
        np.concatenate([graph.edge_to, later]),
        np.concatenate([graph.measurements, false_measurements]),
        np.concatenate([graph.information, false_information]),
    )


def _distinct_non_consecutive_pairs(rng: np.random.Generator, num_poses: int,
                                    count: int) -> tuple[IntArray, IntArray]:
    earlier = np.empty(0, dtype=np.int64)
    later = np.empty(0, dtype=np.int64)
    while len(earlier) < count:
        # Rejection in bulk: draw more than needed, drop consecutive or repeated pairs, keep draw order.
        draws = rng.integers(0, num_poses, size=(2 * (count - len(earlier)) + 8, 2))
        first, second = draws.min(axis=1), draws.max(axis=1)
        keep = second - first > 1
        earlier = np.concatenate([earlier, first[keep]])
        later = np.concatenate([later, second[keep]])
        _, first_seen = np.unique(earlier * num_poses + later, return_index=True)
        first_seen.sort()
        earlier, later = earlier[first_seen], later[first_seen]
    return earlier[:count], later[:count]


def true_edges_chi2(original: PoseGraph, poses: FloatArray) -> float:
    """χ² of `poses` (solved on a graph with added false loops) on the constraints of `original` only."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != original.poses.shape:
        raise GraphError(f"expected poses of shape {original.poses.shape}, got {poses.shape}")
    return chi2(original, poses)


def noisy_manhattan(num_poses: int = M3500_POSES, sigma_theta: float = 0.1, seed: int = 0) -> GridWorld:
    """An M3500-sized grid world whose odometry heading noise is `sigma_theta` (rad): a poor start."""
    return generate_grid_world(num_poses, seed=seed, odometry_sigma=(MANHATTAN_ODOMETRY_SIGMA_XY,
                                                                     MANHATTAN_ODOMETRY_SIGMA_XY,
                                                                     sigma_theta))


def odometry_chain(graph: PoseGraph) -> FloatArray:
    """Poses composed from pose 0's estimate along the odometry constraints (the first stored between each
    consecutive pair, inverted when stored k+1 → k). Raises GraphError if a consecutive pair has none."""
    odometry = np.flatnonzero(graph.is_odometry)
    steps_from, first = np.unique(graph.edge_low[odometry], return_index=True)
    if len(steps_from) != graph.num_poses - 1:
        missing = np.setdiff1d(np.arange(graph.num_poses - 1), steps_from)
        raise GraphError(f"no odometry constraint between poses {int(missing[0])} and {int(missing[0]) + 1}")
    chosen = odometry[first]
    steps = graph.measurements[chosen].copy()
    backward = graph.is_reversed[chosen]
    steps[backward] = se2.inverse(steps[backward])
    return se2.compose_chain(steps, start=graph.poses[0])


def _graph_with_edges(graph: PoseGraph, edge_from: IntArray, edge_to: IntArray, measurements: FloatArray,
                      information: FloatArray) -> PoseGraph:
    ids = graph.vertex_ids
    return PoseGraph.build(ids, graph.poses, ids[edge_from], ids[edge_to], measurements, information)
