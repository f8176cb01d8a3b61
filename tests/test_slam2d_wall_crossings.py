"""`frontends.slam2d.wall_crossings`: a localized run driving through the saved map's walls, counted on a
hand-made occupancy grid."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from frontends.errors import LogWarning
from frontends.slam2d.occupancy import OccupancyGrid
from frontends.slam2d.wall_crossings import (
    MAX_STEP,
    MIN_WALL_CROSSINGS,
    WallCrossings,
    checked_wall_crossings,
    wall_crossings,
)

RESOLUTION = 0.05


@pytest.fixture(scope="module")
def room_with_a_wall() -> OccupancyGrid:
    """A 20 × 10 m free room (origin −1, −1) cut in two by a 10 cm wall along x = 9 m, unknown beyond
    y = 7 m."""
    log_odds = np.full((200, 400), -2.0, dtype=np.float32)
    log_odds[160:, :] = 0.0
    log_odds[:, 200:202] = 2.0
    return OccupancyGrid(np.array([-1.0, -1.0]), RESOLUTION, log_odds)


def zigzag(crossings: int, step: float = 0.1) -> np.ndarray:
    """A path from x = 8 to 10 m and back, `crossings` times, y rising 0.5 m a leg."""
    legs = []
    for leg in range(crossings):
        xs = np.arange(8.0, 10.0 + 1e-9, step)
        xs = xs if leg % 2 == 0 else xs[::-1]
        legs.append(np.column_stack([xs, np.full(len(xs), 0.5 * leg)]))
    return np.concatenate(legs)


def test_each_passage_through_a_wall_counts_once(room_with_a_wall: OccupancyGrid) -> None:
    along = np.column_stack([np.linspace(0.0, 8.0, 81), np.full(81, 2.0)])
    assert wall_crossings(along, room_with_a_wall) == WallCrossings(0, pytest.approx(8.0))
    # 1 cm steps: five of them inside the 10 cm wall at each passage, one crossing.
    found = wall_crossings(zigzag(3, step=0.01), room_with_a_wall)
    assert found.crossings == 3
    assert not found.suspect
    assert wall_crossings(zigzag(MIN_WALL_CROSSINGS), room_with_a_wall).suspect


def test_jumps_and_unknown_cells_are_not_a_path(room_with_a_wall: OccupancyGrid) -> None:
    # A global fix moving the run across the wall in one step is no crossing.
    jump = np.array([[8.0, 1.0], [8.0 + 2 * MAX_STEP, 1.0], [8.0 + 2 * MAX_STEP, 2.0]])
    assert wall_crossings(jump, room_with_a_wall) == WallCrossings(0, pytest.approx(1.0))
    # Beyond the mapped place nothing is counted, not even its length; NaN rows (no pose) are left out.
    unknown = np.array([[2.0, 8.5], [2.0, 9.5], [np.nan, np.nan], [3.0, 9.5]])
    assert wall_crossings(unknown, room_with_a_wall) == WallCrossings(0, 0.0)
    assert wall_crossings(np.zeros((1, 2)), room_with_a_wall) == WallCrossings(0, 0.0)


def test_a_run_crossing_walls_often_for_its_length_is_warned_of(room_with_a_wall: OccupancyGrid) -> None:
    often = zigzag(MIN_WALL_CROSSINGS)
    with pytest.warns(LogWarning, match=r"b\.mcap: the scans placed in the saved map cross its walls 10 "):
        found = checked_wall_crossings("b.mcap", "scans", often, room_with_a_wall)
    assert found.crossings == MIN_WALL_CROSSINGS
    # As many crossings over a long walk through the room (more than 10 m each): a few doors, not suspect.
    walk = np.concatenate([often, np.column_stack([np.linspace(8.0, 0.0, 800), np.full(800, 5.0)])]
                          + [np.column_stack([np.linspace(0.0, 8.0, 800), np.full(800, y)]) for y in
                             np.linspace(0.1, 7.5, 12)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not checked_wall_crossings("b.mcap", "scans", walk, room_with_a_wall).suspect
