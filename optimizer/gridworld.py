"""Synthetic "grid world" pose graphs like those of Olson et al. (2006), section IV.

A robot random-walks along the streets of a square city grid: it moves one `step` at a time, and at every
intersection it goes straight or turns ±90° (never back the way it came, unless the city edge leaves no other
way). Every pose is linked to the previous one by an odometry constraint, and whenever the robot stands on a
lattice point it has visited before, loop closures link it to earlier poses there. Measurements are the true
relative poses corrupted by Gaussian noise; the graph's initial estimate is the dead reckoning of the noisy
odometry, the poor starting point the paper's method is designed for.

The noise is drawn in g2o's error convention: a measurement is z = x_ab · n⁻¹ with n ~ N(0, Σ), so the error
of the ground truth, e = t2v(z⁻¹ · x_a⁻¹ x_b) = n, is exactly a draw from the declared covariance Σ = Ω⁻¹.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from optimizer import se2
from optimizer.errors import OptimizerError
from optimizer.graph import PoseGraph

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# Unit steps of the four headings east, north, west, south (heading index k ↔ θ = k·π/2).
_HEADING_DX = np.array([1, 0, -1, 0], dtype=np.int64)
_HEADING_DY = np.array([0, 1, 0, -1], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class GridWorld:
    """A generated pose graph and the truth it was generated from."""

    graph: PoseGraph
    """Poses are the dead reckoning of the noisy odometry; constraints are odometry then loop closures,
    ordered by their later pose as a robot would add them online."""
    ground_truth: FloatArray
    """(N, 3) true poses x, y, θ (θ a multiple of π/2, wrapped)."""

    def __post_init__(self) -> None:
        self.ground_truth.setflags(write=False)

    @property
    def num_loop_closures(self) -> int:
        return int(np.count_nonzero(~self.graph.is_odometry))


def generate_grid_world(
    num_poses: int,
    *,
    seed: int,
    step: float = 1.0,
    block_steps: int = 10,
    world_blocks: int | None = None,
    mean_visits: float = 4.0,
    turn_probability: float = 0.5,
    odometry_sigma: tuple[float, float, float] = (0.02, 0.02, 0.01),
    loop_sigma: tuple[float, float, float] = (0.05, 0.05, 0.02),
    loop_probability: float = 0.8,
    max_loops_per_revisit: int = 2,
    add_noise: bool = True,
) -> GridWorld:
    """Generate a seeded, deterministic grid-world pose graph.

    - `block_steps`: steps between intersections; streets run along every `block_steps`-th lattice line.
    - `world_blocks`: blocks per side of the square city; by default chosen so that each street lattice
      point is visited about `mean_visits` times, which sets how many revisits (hence loop closures) occur.
    - `turn_probability`: chance of turning (left or right, equally likely) at an intersection.
    - `odometry_sigma`, `loop_sigma`: standard deviations (x, y, θ) of the measurement noise; the
      constraints' information is the inverse of the diagonal covariance.
    - At a revisit, up to `max_loops_per_revisit` earlier poses at the same lattice point are drawn
      uniformly (repeated draws dropped), each kept as a loop closure with probability `loop_probability`.
    - `add_noise=False` gives exact measurements (information still from the sigmas): the ground truth
      then has χ² = 0 and the initial estimate is the ground truth.

    With the defaults, 10⁶ poses give about 2·10⁶ constraints.
    """
    _check_arguments(num_poses, step, block_steps, world_blocks, mean_visits, turn_probability,
                     odometry_sigma, loop_sigma, loop_probability, max_loops_per_revisit)
    if world_blocks is None:
        # A city of B×B blocks has about 2·B²·block_steps street lattice points.
        world_blocks = max(1, round(np.sqrt(num_poses / (2.0 * block_steps * mean_visits))))
    rng = np.random.default_rng(seed)

    lattice_x, lattice_y, heading = _random_walk(
        rng.random(num_poses), num_poses, block_steps, world_blocks, turn_probability
    )
    ground_truth = np.empty((num_poses, 3))
    ground_truth[:, 0] = lattice_x * step
    ground_truth[:, 1] = lattice_y * step
    ground_truth[:, 2] = se2.wrap_angle(heading * (np.pi / 2.0))

    loop_from, loop_to = _loop_closure_pairs(
        lattice_x, lattice_y, world_blocks * block_steps + 1, rng, loop_probability, max_loops_per_revisit
    )
    odometry_from = np.arange(num_poses - 1, dtype=np.int64)
    edge_from = np.concatenate([odometry_from, loop_from])
    edge_to = np.concatenate([odometry_from + 1, loop_to])
    num_odometry = num_poses - 1

    sigmas = np.empty((len(edge_from), 3))
    sigmas[:num_odometry] = odometry_sigma
    sigmas[num_odometry:] = loop_sigma
    truth = se2.relative(ground_truth[edge_from], ground_truth[edge_to])
    if add_noise:
        noise = rng.standard_normal((len(edge_from), 3)) * sigmas
        measurements = se2.compose(truth, se2.inverse(noise))
    else:
        measurements = truth

    information = np.zeros((len(edge_from), 3, 3))
    diagonal = np.arange(3)
    information[:, diagonal, diagonal] = 1.0 / sigmas**2

    dead_reckoning = se2.compose_chain(measurements[:num_odometry], start=ground_truth[0])

    # The order a robot would add them online: by later pose, odometry (largest a) before loop closures.
    order = np.lexsort((-edge_from, edge_to))
    graph = PoseGraph.build(
        np.arange(num_poses, dtype=np.int64),
        dead_reckoning,
        edge_from[order],
        edge_to[order],
        measurements[order],
        information[order],
    )
    return GridWorld(graph=graph, ground_truth=ground_truth)


def _check_arguments(
    num_poses: int,
    step: float,
    block_steps: int,
    world_blocks: int | None,
    mean_visits: float,
    turn_probability: float,
    odometry_sigma: tuple[float, float, float],
    loop_sigma: tuple[float, float, float],
    loop_probability: float,
    max_loops_per_revisit: int,
) -> None:
    if num_poses < 2:
        raise OptimizerError(f"a grid world needs at least 2 poses, got {num_poses}")
    if not step > 0.0:
        raise OptimizerError(f"step must be positive, got {step}")
    if block_steps < 1:
        raise OptimizerError(f"block_steps must be at least 1, got {block_steps}")
    if world_blocks is not None and world_blocks < 1:
        raise OptimizerError(f"world_blocks must be at least 1, got {world_blocks}")
    if not mean_visits > 0.0:
        raise OptimizerError(f"mean_visits must be positive, got {mean_visits}")
    if not 0.0 <= turn_probability <= 1.0:
        raise OptimizerError(f"turn_probability must be in [0, 1], got {turn_probability}")
    if not 0.0 <= loop_probability <= 1.0:
        raise OptimizerError(f"loop_probability must be in [0, 1], got {loop_probability}")
    if max_loops_per_revisit < 0:
        raise OptimizerError(f"max_loops_per_revisit must be >= 0, got {max_loops_per_revisit}")
    for name, sigma in (("odometry_sigma", odometry_sigma), ("loop_sigma", loop_sigma)):
        if len(sigma) != 3 or not all(np.isfinite(s) and s > 0.0 for s in sigma):
            raise OptimizerError(f"{name} must be three positive standard deviations, got {sigma}")


def _random_walk(
    uniforms: FloatArray, num_poses: int, block_steps: int, world_blocks: int, turn_probability: float
) -> tuple[IntArray, IntArray, IntArray]:
    """Lattice coordinates and heading index (0..3) of every pose of the walk, starting at the centre."""
    size = world_blocks * block_steps
    start = (world_blocks // 2) * block_steps
    return _random_walk_kernel(uniforms, num_poses, block_steps, size, start, turn_probability,
                               _HEADING_DX, _HEADING_DY)


@njit(cache=True)
def _random_walk_kernel(
    uniforms: FloatArray,
    num_poses: int,
    block_steps: int,
    size: int,
    start: int,
    turn_probability: float,
    heading_dx: IntArray,
    heading_dy: IntArray,
) -> tuple[IntArray, IntArray, IntArray]:
    # Sequential by nature: each move depends on where the walk is and which way it faces.
    xs = np.empty(num_poses, dtype=np.int64)
    ys = np.empty(num_poses, dtype=np.int64)
    headings = np.empty(num_poses, dtype=np.int64)
    x, y, heading = start, start, 0
    xs[0], ys[0], headings[0] = x, y, heading
    choices = np.empty(3, dtype=np.int64)
    weights = np.empty(3)
    for i in range(1, num_poses):
        if x % block_steps == 0 and y % block_steps == 0:
            # An intersection: straight, left or right, whichever stays inside the city.
            choices[0], choices[1], choices[2] = heading, (heading + 1) % 4, (heading + 3) % 4
            weights[0] = 1.0 - turn_probability
            weights[1] = 0.5 * turn_probability
            weights[2] = 0.5 * turn_probability
            total = 0.0
            for k in range(3):
                nx = x + heading_dx[choices[k]]
                ny = y + heading_dy[choices[k]]
                if nx < 0 or ny < 0 or nx > size or ny > size:
                    weights[k] = 0.0
                total += weights[k]
            if total > 0.0:
                threshold = uniforms[i] * total
                chosen = 2
                cumulative = 0.0
                for k in range(3):
                    if weights[k] > 0.0:
                        chosen = k
                        cumulative += weights[k]
                        if threshold < cumulative:
                            break
                heading = choices[chosen]
            else:
                # Every allowed way has zero weight (turn_probability of 0 or 1 at the city edge):
                # take the first way that stays inside, reversing only as a last resort.
                for candidate in (heading, (heading + 1) % 4, (heading + 3) % 4, (heading + 2) % 4):
                    nx = x + heading_dx[candidate]
                    ny = y + heading_dy[candidate]
                    if 0 <= nx <= size and 0 <= ny <= size:
                        heading = candidate
                        break
        x += heading_dx[heading]
        y += heading_dy[heading]
        xs[i], ys[i], headings[i] = x, y, heading
    return xs, ys, headings


def _loop_closure_pairs(
    lattice_x: IntArray,
    lattice_y: IntArray,
    side: int,
    rng: np.random.Generator,
    loop_probability: float,
    max_loops_per_revisit: int,
) -> tuple[IntArray, IntArray]:
    """(earlier, later) pose pairs on the same lattice point, drawn as described in generate_grid_world.

    Vectorized: a stable sort by lattice cell groups the visits of each point in time order, so a pose's
    rank within its group is the number of earlier visits there.
    """
    num_poses = len(lattice_x)
    cell = lattice_x * side + lattice_y
    by_cell = np.argsort(cell, kind="stable")
    sorted_cell = cell[by_cell]
    group_start = np.flatnonzero(np.r_[True, sorted_cell[1:] != sorted_cell[:-1]])
    group_length = np.diff(np.r_[group_start, num_poses])
    position = np.arange(num_poses, dtype=np.int64)
    first_of_group = np.repeat(group_start, group_length)
    rank = position - first_of_group  # earlier visits of the same point

    revisit = np.flatnonzero(rank > 0)
    later_parts: list[IntArray] = []
    earlier_parts: list[IntArray] = []
    for _ in range(max_loops_per_revisit):
        chosen_rank = np.floor(rng.random(len(revisit)) * rank[revisit]).astype(np.int64)
        keep = rng.random(len(revisit)) < loop_probability
        later_parts.append(by_cell[revisit[keep]])
        earlier_parts.append(by_cell[first_of_group[revisit[keep]] + chosen_rank[keep]])
    later = np.concatenate([np.empty(0, dtype=np.int64), *later_parts])
    earlier = np.concatenate([np.empty(0, dtype=np.int64), *earlier_parts])
    if len(later) == 0:
        return later, earlier
    # The draws are with replacement: keep each (earlier, later) pair once (a sort is much faster than
    # np.unique's hashing at millions of pairs).
    pairs = np.sort(later * num_poses + earlier)
    unique_pairs = pairs[np.r_[True, pairs[1:] != pairs[:-1]]]
    return unique_pairs % num_poses, unique_pairs // num_poses
