"""2D map files other tools read: the ROS `map_server` pair (`.pgm` + `.yaml`) and a PNG with a scale bar.

The pair follows what `map_saver` (ROS 1 map_server, ROS 2 nav2_map_server) writes, so `map_server`,
`nav2_map_server`, slam_toolbox and RViz load it unchanged: a binary PGM in "trinary" mode, occupied 0,
free 254, unknown 205, north up (the image's first row is the map's top), and a YAML whose `origin` is the
world pose of the image's lower-left pixel. With `negate: 0` a pixel's occupancy is p = (255 − v) / 255;
the loader calls p > `occupied_thresh` occupied, p < `free_thresh` free, anything between unknown. 205 gives
p = 0.19608, so `free_thresh` is map_saver's 0.196, just below it.
"""

from __future__ import annotations

import io
import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from frontends.slam2d import OccupancyGrid

OCCUPIED_VALUE = 0
FREE_VALUE = 254
UNKNOWN_VALUE = 205
OCCUPIED_THRESHOLD = 0.65
FREE_THRESHOLD = 0.196
SCALE_BAR_LENGTHS_M = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)
"""A scale bar is the longest of these that fits in a fifth of the picture's width."""


def map_server_pgm(grid: OccupancyGrid) -> bytes:
    """The grid as map_saver's trinary picture, a binary (P5) PGM: rows top to bottom (north up)."""
    from PIL import Image

    picture = np.full(grid.log_odds.shape, UNKNOWN_VALUE, dtype=np.uint8)
    picture[grid.free_cells()] = FREE_VALUE
    picture[grid.occupied_cells()] = OCCUPIED_VALUE
    buffer = io.BytesIO()
    Image.fromarray(picture[::-1], mode="L").save(buffer, format="PPM")  # mode L → P5
    return buffer.getvalue()


def map_server_yaml(grid: OccupancyGrid, image_name: str) -> str:
    """The YAML map_server reads beside `image_name` (a path relative to the YAML file)."""
    x, y = (float(value) for value in grid.origin[:2])
    return (
        f"image: {image_name}\n"
        "mode: trinary\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{x!r}, {y!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESHOLD}\n"
        f"free_thresh: {FREE_THRESHOLD}\n"
    )


def picture_with_scale_bar(grid: OccupancyGrid) -> NDArray[np.uint8]:
    """The map picture (`OccupancyGrid.image`) with a black scale bar in its lower-left corner, labelled
    with its length, on a white box so that it reads on any map."""
    from PIL import Image, ImageDraw

    picture = grid.image()
    height, width = picture.shape
    fitting = [length for length in SCALE_BAR_LENGTHS_M if length / grid.resolution <= width / 5]
    if not fitting or height < 24:
        return picture
    length_m = fitting[-1]
    bar_pixels = max(int(round(length_m / grid.resolution)), 1)
    image = Image.fromarray(picture, mode="L")
    draw = ImageDraw.Draw(image)
    draw.fontmode = "1"  # no anti-aliasing: the picture keeps its three values (occupied, unknown, free)
    label = f"{length_m:g} m"
    margin = 4
    text_width = int(math.ceil(draw.textlength(label)))
    box_right = margin + max(bar_pixels, text_width) + 2 * margin
    draw.rectangle((margin, height - 24 - margin, box_right, height - margin), fill=255)
    bar_bottom = height - 2 * margin
    draw.rectangle((2 * margin, bar_bottom - 3, 2 * margin + bar_pixels, bar_bottom), fill=0)
    draw.text((2 * margin, height - 22 - margin), label, fill=0)
    return np.asarray(image, dtype=np.uint8)
