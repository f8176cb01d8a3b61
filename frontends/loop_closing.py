"""What the 2D and 3D SLAM frontends share about their keyframe graphs and loop closures.

- `Constraints`: the growing list of keyframe-graph constraints (odometry and loop closures), with
  removal for the loop closures an optimization finds inconsistent.
- `HypothesisPool`: a loop closure that would move the map by more than a small correction is only a
  hypothesis until another one agrees with it (a false match seldom finds an agreeing second one).
- `optimize_and_prune`: re-optimize the keyframe graph and remove the loop closures whose error stays large
  at the optimum (inconsistent with the rest), one at a time, worst first.
- `path_lengths`: the length of the shortest path between keyframes through the constraints, which the
  loop-closure search radius grows with (drift accumulates along the path that links two places).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

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

    def add(self, a: int, b: int, measurement: FloatArray, information: FloatArray, is_loop: bool) -> None:
        self.first.append(a)
        self.second.append(b)
        self.measurement.append(np.asarray(measurement, dtype=np.float64))
        self.information.append(0.5 * (information + information.T))
        self.is_loop.append(is_loop)
        planar = self.measurement_shape == (3,)
        self.planar_length.append(float(np.hypot(measurement[0], measurement[1])) if planar else math.nan)

    def remove(self, index: int) -> None:
        for column in (self.first, self.second, self.measurement, self.information, self.is_loop,
                       self.planar_length):
            del column[index]

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
    current: int
    """The keyframe that found the loop closure."""
    correction: FloatArray
    """Planar (x, y, θ): matched pose ∘ estimated pose⁻¹ of `current`, how far the match moves the map."""


def is_small(transform: FloatArray, linear: float, angular: float) -> bool:
    return bool(np.hypot(transform[0], transform[1]) <= linear and abs(transform[2]) <= angular)


@dataclass
class HypothesisPool:
    """Loop closures waiting for a second one that agrees with their correction."""

    small_linear: float
    small_angular: float
    pending: list[Hypothesis] = field(default_factory=list)
    dropped: int = 0
    """Hypotheses forgotten unconfirmed so far (expired, or void after the map moved)."""

    def confirm(self, hypothesis: Hypothesis) -> list[Hypothesis]:
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


def optimize_and_prune(
    edges: Constraints,
    graph_at: Callable[[FloatArray], PoseGraph],
    poses: FloatArray,
    chi2_threshold: float,
    iterations: int,
) -> tuple[FloatArray, int]:
    """Gauss–Newton from `poses` on `graph_at(poses)` (the SE(2) graph of `edges`); while the worst loop
    closure's χ² at the optimum exceeds `chi2_threshold`, remove it from `edges` and optimize again.
    Returns the optimized poses and how many loop closures were removed."""
    removed = 0
    while True:
        graph = graph_at(poses)
        for step in gauss_newton(graph, poses, max_iterations=iterations):
            poses = step.poses
        loops = np.flatnonzero(edges.is_loop)
        if len(loops) == 0:
            return poses, removed
        errors = edge_chi2(graph, poses)[loops]
        worst = int(np.argmax(errors))
        if errors[worst] <= chi2_threshold:
            return poses, removed
        edges.remove(int(loops[worst]))
        removed += 1
