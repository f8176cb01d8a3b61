"""What the 2D and 3D SLAM frontends share about their keyframe graphs and loop closures.

- `Constraints`: the growing list of keyframe-graph constraints (odometry and loop closures), with
  removal for the loop closures an optimization finds inconsistent.
- `HypothesisPool`: a loop closure that would move the map by more than a small correction is only a
  hypothesis until another one agrees with it (a false match seldom finds an agreeing second one).
- `optimize_and_prune`: re-optimize the keyframe graph and remove the loop closures whose error stays large
  at the optimum (inconsistent with the rest), one at a time, worst first; then the new loop closures that
  strain the chain (two agreeing matches of a look-alike place, pinned to it while true closures pin the
  keyframes around: their own error stays small, one odometry step takes it all).
- `path_lengths`: the length of the shortest path between keyframes through the constraints, which the
  loop-closure search radius grows with (drift accumulates along the path that links two places).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import combinations
from typing import Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from frontends.growing_rows import GrowingRows
from optimizer import se2
from optimizer.cost import edge_chi2
from optimizer.graph import PoseGraph
from optimizer.polish import gauss_newton

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class Constraints:
    """Constraints a → b with measurements of `measurement_shape` and square information matrices."""

    measurement_shape: tuple[int, ...]
    information_size: int
    first: list[int] = field(default_factory=list)
    second: list[int] = field(default_factory=list)
    measurement: list[FloatArray] = field(default_factory=list)
    information: list[FloatArray] = field(default_factory=list)
    is_loop: list[bool] = field(default_factory=list)
    planar_length: list[float] = field(default_factory=list)
    """Length of each planar measurement's (x, y, θ) translation, kept as constraints are added: the path
    lengths of every loop search need them, and converting the measurements each time cost more than the
    search itself (NaN for other measurements)."""
    _paths: GrowingRows | None = field(default=None, init=False, repr=False)
    """(first, second, planar length) of every constraint, as `path_columns` gives them; None after a
    removal or a restore (a pruning may try many), made again when next read."""

    def add(self, a: int, b: int, measurement: FloatArray, information: FloatArray, is_loop: bool) -> None:
        self.first.append(a)
        self.second.append(b)
        self.measurement.append(np.asarray(measurement, dtype=np.float64))
        self.information.append(0.5 * (information + information.T))
        self.is_loop.append(is_loop)
        planar = self.measurement_shape == (3,)
        self.planar_length.append(float(np.hypot(measurement[0], measurement[1])) if planar else math.nan)
        if self._paths is not None:
            self._paths.append((a, b, self.planar_length[-1]))

    def _columns(self) -> tuple[list, ...]:
        return (self.first, self.second, self.measurement, self.information, self.is_loop, self.planar_length)

    def remove(self, index: int) -> tuple[object, ...]:
        """Remove constraint `index`; returns its row, for `restore`."""
        self._paths = None
        return tuple(column.pop(index) for column in self._columns())

    def restore(self, index: int, row: tuple[object, ...]) -> None:
        """Put a row `remove` returned back at `index`."""
        self._paths = None
        for column, value in zip(self._columns(), row, strict=True):
            column.insert(index, value)

    def path_columns(self) -> tuple[IntArray, IntArray, FloatArray]:
        """(first, second, planar length) of every constraint, without converting the lists (a loop search
        reads them at every searching keyframe)."""
        if self._paths is None:
            self._paths = GrowingRows((3,), np.float64)
            self._paths.reset(np.column_stack([self.first, self.second, self.planar_length]))
        paths = self._paths.rows()
        return paths[:, 0].astype(np.int64), paths[:, 1].astype(np.int64), paths[:, 2]

    def arrays(self) -> tuple[IntArray, IntArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """(first, second, measurements, informations, is_loop) as arrays."""
        size = self.information_size
        return (
            np.array(self.first, dtype=np.int64),
            np.array(self.second, dtype=np.int64),
            np.array(self.measurement, dtype=np.float64).reshape(-1, *self.measurement_shape),
            np.array(self.information, dtype=np.float64).reshape(-1, size, size),
            np.array(self.is_loop, dtype=bool),
        )


class Hypothesis(Protocol):
    @property
    def current(self) -> int:
        """The keyframe that found the loop closure."""

    @property
    def correction(self) -> FloatArray:
        """Planar (x, y, θ): matched pose ∘ estimated pose⁻¹ of `current`, how far the match moves the map."""


def is_small(transform: FloatArray, linear: float, angular: float) -> bool:
    return bool(np.hypot(transform[0], transform[1]) <= linear and abs(transform[2]) <= angular)


H = TypeVar("H", bound=Hypothesis)


@dataclass
class HypothesisPool(Generic[H]):
    """Loop closures waiting for a second one that agrees with their correction."""

    small_linear: float
    small_angular: float
    pending: list[H] = field(default_factory=list)
    dropped: int = 0
    """Hypotheses forgotten unconfirmed so far (expired, or void after the map moved)."""

    def confirm(self, hypothesis: H) -> list[H]:
        """The loop closures `hypothesis` makes acceptable: itself when it barely moves the map; otherwise
        it and the pending ones it agrees with, or none (it waits for a second one)."""
        if is_small(hypothesis.correction, self.small_linear, self.small_angular):
            return [hypothesis]
        agreeing = [
            h
            for h in self.pending
            if is_small(
                se2.relative(h.correction, hypothesis.correction), self.small_linear, self.small_angular
            )
        ]
        if not agreeing:
            self.pending.append(hypothesis)
            return []
        self.pending = [h for h in self.pending if all(h is not a for a in agreeing)]
        return [*agreeing, hypothesis]

    def expire(self, current: int, max_age: int) -> int:
        """Forget hypotheses found more than `max_age` keyframes before `current`; returns how many."""
        kept = [h for h in self.pending if current - h.current <= max_age]
        dropped = len(self.pending) - len(kept)
        self.pending = kept
        self.dropped += dropped
        return dropped

    def clear(self) -> int:
        """Forget every pending hypothesis (their corrections are void once the map moved); how many."""
        dropped = len(self.pending)
        self.pending = []
        self.dropped += dropped
        return dropped


def path_lengths(
    count: int, first: IntArray, second: IntArray, lengths: FloatArray, source: int
) -> FloatArray:
    """Shortest path length from keyframe `source` to every keyframe, over constraints of these lengths
    (each walked either way; of two constraints between the same keyframes, the shorter)."""
    weights = np.maximum(lengths, 1e-6)  # a zero weight would mean "no edge" to the sparse graph
    if _is_chain(count, first, second) and np.all(np.isfinite(weights)):
        # Until a loop closes, the graph is one chain: a path's length is its steps added outwards from
        # `source`, in the order the search adds them (the same floats). The sparse search at every
        # searching keyframe of a long log without loop closures was 0.11 s of UAL's 3.2 s replay.
        along = np.zeros(count)
        along[:source] = np.cumsum(weights[:source][::-1])[::-1]
        along[source + 1:] = np.cumsum(weights[source:])
        return along
    # Both directions of every constraint as rows of a CSR matrix, built directly: a COO conversion would
    # sum two constraints between the same keyframes into one longer edge, and the undirected search
    # transposes the matrix first; together they cost three times the search itself.
    tails = np.concatenate([first, second])
    order = np.argsort(tails, kind="stable")
    heads = np.concatenate([second, first])[order].astype(np.int32)
    starts = np.zeros(count + 1, dtype=np.int32)
    np.cumsum(np.bincount(tails, minlength=count), out=starts[1:])
    adjacency = csr_matrix((np.concatenate([weights, weights])[order], heads, starts), shape=(count, count))
    return dijkstra(adjacency, directed=True, indices=source)


def _is_chain(count: int, first: IntArray, second: IntArray) -> bool:
    """Whether the constraints are exactly k → k + 1 for k = 0 … `count` − 2, in that order."""
    return (len(first) == count - 1 and bool(np.all(first == np.arange(count - 1)))
            and bool(np.all(second == first + 1)))


MAX_SUSPECTS = 6
"""At most this many of the newest loop closures are suspected (every subset of them may be tried)."""
STRAIN_CHI2 = 16.27
"""A chain constraint (odometry, scan matching) whose χ² (3 dof: x, y, θ) exceeds this at the optimum is
strained: p = 0.001 if the constraints were right. The chain is not wrong, the loop closures that bend it
are. On the logs we have, every chain constraint stays under 1.5 (lidar-only as with wheel odometry) until a
false loop closure, where it reached 21 at once and 75–135 as later closures pinned the map around it."""


def optimize_and_prune(
    edges: Constraints,
    graph_at: Callable[[FloatArray], PoseGraph],
    poses: FloatArray,
    chi2_threshold: float,
    iterations: int,
    new_loops: int = 0,
) -> tuple[FloatArray, int]:
    """Gauss–Newton from `poses` on `graph_at(poses)` (the SE(2) graph of `edges`); while the worst loop
    closure's χ² at the optimum exceeds `chi2_threshold`, remove it from `edges` and optimize again. Then,
    when a chain constraint is strained (`STRAIN_CHI2`), remove the fewest of the `new_loops` newest loop
    closures (at most `MAX_SUSPECTS`) whose removal relieves it, if any do; if none do, the strain is not
    theirs and they stay.
    Returns the optimized poses and how many loop closures were removed."""
    removed = 0
    newest = min(new_loops, MAX_SUSPECTS)
    suspects = [int(k) for k in np.flatnonzero(edges.is_loop)[-newest:]] if newest > 0 else []
    while True:
        graph, poses = _optimized(graph_at, poses, iterations)
        loops = np.flatnonzero(edges.is_loop)
        if len(loops) == 0:
            return poses, removed
        chi2 = edge_chi2(graph, poses)
        errors = chi2[loops]
        worst = int(loops[np.argmax(errors)])
        if errors.max() <= chi2_threshold:
            break
        edges.remove(worst)
        removed += 1
        suspects = [k - (k > worst) for k in suspects if k != worst]
    if not suspects or _chain_strain(edges, chi2) <= STRAIN_CHI2:
        return poses, removed
    # False closures come in agreeing groups (a look-alike place matches again from the next keyframes):
    # the fewest of the new closures whose removal relieves the strain, the least strained of those.
    for size in range(1, len(suspects) + 1):
        trials = [_strain_without(edges, graph_at, poses, iterations, culprits)
                  for culprits in combinations(suspects, size)]
        relieved = [trial for trial in trials if trial[0] <= STRAIN_CHI2]
        if relieved:
            _, culprits, poses = min(relieved, key=lambda trial: trial[0])
            for index in sorted(culprits, reverse=True):
                edges.remove(index)
            return poses, removed + size
    return poses, removed


def _optimized(graph_at: Callable[[FloatArray], PoseGraph], poses: FloatArray,
               iterations: int) -> tuple[PoseGraph, FloatArray]:
    """The graph of the constraints as they are, and its Gauss–Newton optimum from `poses`."""
    graph = graph_at(poses)
    for step in gauss_newton(graph, poses, max_iterations=iterations):
        poses = step.poses
    return graph, poses


def _strain_without(edges: Constraints, graph_at: Callable[[FloatArray], PoseGraph], poses: FloatArray,
                    iterations: int, culprits: tuple[int, ...]) -> tuple[float, tuple[int, ...], FloatArray]:
    """The chain's strain at the optimum without the constraints `culprits`, and that optimum."""
    rows = [(index, edges.remove(index)) for index in sorted(culprits, reverse=True)]
    graph, optimum = _optimized(graph_at, poses, iterations)
    strain = _chain_strain(edges, edge_chi2(graph, optimum))
    for index, row in reversed(rows):
        edges.restore(index, row)
    return strain, culprits, optimum


def _chain_strain(edges: Constraints, chi2: FloatArray) -> float:
    """The largest of the constraints' `chi2` (in `edges`' order) over the chain (not the loop closures)."""
    chain = ~np.array(edges.is_loop, dtype=bool)
    return float(chi2[chain].max()) if chain.any() else 0.0
