"""The map_server pair and the PNG scale bar, read back the way ROS's map_server reads them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from frontends.slam2d import OccupancyGrid, occupancy_grid
from pipeline.map_files import (
    map_server_pgm,
    map_server_yaml,
    picture_with_scale_bar,
)
from tests.laser_world import box, simulate_scan

OCCUPIED, FREE, UNKNOWN = 100, 0, -1


def read_pgm(data: bytes) -> np.ndarray:
    """A binary (P5) 8-bit PGM, parsed from its header as the format defines it (netpbm pgm(5))."""
    fields: list[bytes] = []
    position = 0
    while len(fields) < 4:
        while data[position:position + 1].isspace():
            position += 1
        if data[position:position + 1] == b"#":
            position = data.index(b"\n", position) + 1
            continue
        end = position
        while not data[end:end + 1].isspace():
            end += 1
        fields.append(data[position:end])
        position = end
    assert fields[0] == b"P5" and int(fields[3]) == 255
    width, height = int(fields[1]), int(fields[2])
    pixels = np.frombuffer(data, dtype=np.uint8, count=width * height, offset=position + 1)
    return pixels.reshape(height, width)


def load_like_map_server(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """map_server's image loader (ROS 1 image_loader.cpp / nav2 map_io.cpp) for mode trinary, negate 0:
    p = (255 − v) / 255; p > occupied_thresh → 100, p < free_thresh → 0, else −1. Returns the occupancy
    grid with row 0 at the map's bottom (as in nav_msgs/OccupancyGrid) and the YAML."""
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["mode"] == "trinary" and meta["negate"] == 0
    image = read_pgm((yaml_path.parent / meta["image"]).read_bytes())
    p = (255.0 - image.astype(np.float64)) / 255.0
    grid = np.full(image.shape, UNKNOWN, dtype=np.int64)
    grid[p > meta["occupied_thresh"]] = OCCUPIED
    grid[p < meta["free_thresh"]] = FREE
    return grid[::-1], meta


def write_pair(grid: OccupancyGrid, folder: Path) -> Path:
    (folder / "run_map.pgm").write_bytes(map_server_pgm(grid))
    path = folder / "run_map.yaml"
    path.write_text(map_server_yaml(grid, "run_map.pgm"))
    return path


def test_each_cell_keeps_its_class_and_place(tmp_path: Path) -> None:
    log_odds = np.zeros((3, 4), dtype=np.float32)  # rows are y (south first), columns x
    log_odds[0, 0] = 3.0  # south-west corner occupied
    log_odds[2, 3] = -3.0  # north-east corner free
    log_odds[1, 2] = 0.2  # barely seen: unknown
    grid = OccupancyGrid(np.array([-1.5, 2.0]), 0.25, log_odds)
    loaded, meta = load_like_map_server(write_pair(grid, tmp_path))
    expected = np.full((3, 4), UNKNOWN)
    expected[0, 0], expected[2, 3] = OCCUPIED, FREE
    np.testing.assert_array_equal(loaded, expected)
    assert meta["resolution"] == 0.25
    assert meta["origin"] == [-1.5, 2.0, 0.0]


def test_a_wall_lands_where_the_world_has_it(tmp_path: Path) -> None:
    """Scans of a 10 m × 6 m room from two poses: map_server's cell of each wall's midpoint (from the
    YAML's origin and resolution alone) is occupied, the room's centre is free."""
    walls = box(0.0, 0.0, 10.0, 6.0)
    poses = np.array([[3.0, 3.0, 0.0], [7.0, 2.5, math.pi / 2]])
    scans = [simulate_scan(walls, pose, beams=720) for pose in poses]
    loaded, meta = load_like_map_server(write_pair(occupancy_grid(scans, poses), tmp_path))
    origin, resolution = np.array(meta["origin"][:2]), meta["resolution"]

    def cell(x: float, y: float) -> int:
        column, row = np.floor((np.array([x, y]) - origin) / resolution).astype(int)
        return int(loaded[row, column])

    for x, y in [(5.0, 0.0), (5.0, 6.0), (0.0, 3.0), (10.0, 3.0)]:
        nearby = [cell(x + dx, y + dy) for dx in (-0.03, 0.0, 0.03) for dy in (-0.03, 0.0, 0.03)]
        assert OCCUPIED in nearby, (x, y)
    assert cell(5.0, 3.0) == FREE


def test_scale_bar_is_as_long_as_it_says(tmp_path: Path) -> None:
    grid = OccupancyGrid(np.zeros(2), 0.05, np.full((200, 400), -3.0, dtype=np.float32))  # 20 m × 10 m free
    picture = picture_with_scale_bar(grid)
    assert picture.shape == grid.image().shape
    # The longest listed length within a fifth of 20 m is 2 m: 40 black pixels in one row.
    black_rows = [int((row == 0).sum()) for row in picture]
    assert max(black_rows) == 41  # both end pixels drawn
    assert np.all(picture[:100] == 255)  # the bar sits at the bottom, the map above is untouched
