"""Rows appended one at a time, readable at any moment as one array without copying them all.

A loop search reads every keyframe's position and every constraint's ends and length; made into arrays
from Python lists at each search, that cost grew with the log (on the Freiburg clinic log, 3 500
keyframes: 0.85 s of a 10 s replay went into `np.array` of those lists).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray


class GrowingRows:
    """An (n, *row_shape) array grown row by row in a buffer that doubles when full."""

    def __init__(self, row_shape: tuple[int, ...], dtype: DTypeLike) -> None:
        self._buffer: NDArray = np.empty((16, *row_shape), dtype=dtype)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(self, row: ArrayLike) -> None:
        if self._count == len(self._buffer):
            grown = np.empty((2 * len(self._buffer), *self._buffer.shape[1:]), dtype=self._buffer.dtype)
            grown[: self._count] = self._buffer[: self._count]
            self._buffer = grown
        self._buffer[self._count] = row
        self._count += 1

    def reset(self, rows: ArrayLike) -> None:
        """Every row anew (after rows were changed, removed or inserted), in a new buffer: the views
        `rows` gave before keep what they held."""
        row_shape = self._buffer.shape[1:]
        given = np.asarray(rows, dtype=self._buffer.dtype).reshape(-1, *row_shape)
        self._buffer = np.empty((max(16, 2 * len(given)), *row_shape), dtype=self._buffer.dtype)
        self._buffer[: len(given)] = given
        self._count = len(given)

    def rows(self) -> NDArray:
        """The rows so far: a read-only view, which later appends and resets leave as it is."""
        view = self._buffer[: self._count]
        view.flags.writeable = False
        return view
