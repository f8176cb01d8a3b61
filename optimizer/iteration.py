"""What every optimizer yields after each iteration, so callers can record the whole optimization."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

ESTIMATE = "estimate"
"""The name of the graph's own estimate as a start."""


@dataclass(frozen=True, eq=False)
class Iteration:
    """The state after one iteration of one stage.

    `stage` is one of "initial" (index 0, a starting estimate), "sgd" (the paper's), "sgd-tree" (the
    tree-parameterised SGD), "gauss-newton" (the polish, Levenberg–Marquardt-damped Gauss–Newton),
    "gauss-seidel", "gnc" (a round of graduated non-convexity, `optimizer.robust_gnc`), or
    "selected" (index 0: the winning candidate's result, repeated when several starts were optimized);
    `index` counts from 1 within the stage. `start` names the starting estimate the run began from
    ("estimate": the graph's own; see `optimizer.solve`). `poses` is (N, 3) with θ wrapped to [-π, π)
    and must not be modified by the receiver.
    """

    stage: str
    index: int
    poses: NDArray[np.float64]
    chi2: float
    start: str = ESTIMATE
