"""What every optimizer yields after each iteration, so callers can record the whole optimization."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, eq=False)
class Iteration:
    """The state after one iteration of one stage.

    `stage` is one of "initial" (index 0, the starting estimate), "sgd", "gauss-newton" (the polish,
    Levenberg–Marquardt-damped Gauss–Newton) or "gauss-seidel"; `index` counts from 1 within the stage.
    `poses` is (N, 3) with θ wrapped to [-π, π) and must not be modified by the receiver.
    """

    stage: str
    index: int
    poses: NDArray[np.float64]
    chi2: float
