"""The map of a 2D log replay in the recording: walls that move with the optimizer, over the final grid.

- `world/keyframes/kNNNNNN/scan`: each keyframe's scan, logged once (at the first recorded iteration), in
  the keyframe's own frame, thinned to one point per `SCAN_CELL`;
- `world/keyframes/kNNNNNN`: the keyframe's pose as a `Transform3D` on `iteration`, sent in columns: the
  walls straighten as the optimizer iterates while an iteration costs 28 bytes per keyframe instead of the
  whole map, and only for keyframes that moved by more than `SHOWN_MOVE` / `SHOWN_TURN` since their last
  row (the viewer keeps the latest row; late SGD iterations move most keyframes by far less than a
  pixel). The final iteration is sent whole, so its transforms are the written poses exactly;
- `world/occupancy/grid` (static): the occupancy grid of the final map, an image placed in world metres by
  the static transform of `world/occupancy` (north up, like `<stem>_map.png`), in dark tones under the
  walls: free space dark grey, walls mid grey, unknown the view's background.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np
import rerun as rr
from numba import njit
from numpy.typing import NDArray

from frontends.logs.rotations import from_yaw
from frontends.slam2d import one_per_cell, place
from optimizer.iteration import Iteration
from pipeline.recording import (
    ITERATION_TIMELINE,
    KEYFRAMES_ENTITY,
    MAP_COLOR,
    MAP_DRAW_ORDER,
    MAP_POINT_RADIUS,
    OCCUPANCY_DRAW_ORDER,
    VIEWER_BACKGROUND,
    Bounds,
    FloatArray,
    IntArray,
    PoseBatches,
    transform3d_columns,
    world_bounds,
)

OCCUPANCY_ENTITY = "world/occupancy"
OCCUPANCY_IMAGE_ENTITY = "world/occupancy/grid"

SCAN_CELL = 0.05
"""Each keyframe scan keeps one point per cell of this size (m) of its own frame."""

# The grey levels of `frontends.slam2d.OccupancyGrid.image` and what the viewer draws for them (RGBA).
GRID_OCCUPIED, GRID_FREE, GRID_UNKNOWN = 0, 255, 205
OCCUPANCY_VIEW_COLORS = {
    GRID_OCCUPIED: (120, 120, 120, 255),
    GRID_FREE: (40, 40, 48, 255),
    GRID_UNKNOWN: (*VIEWER_BACKGROUND, 255),  # the viewer draws transparent image pixels black
}

SHOWN_MOVE = 0.05
"""A keyframe's transform gets a new row once it moved this far (m) from its last row …"""
SHOWN_TURN = 0.0025
"""… or turned this much (rad: 5 cm at 20 m range): about a pixel of a building-sized map framed whole."""


def keyframe_entity(index: int) -> str:
    return f"{KEYFRAMES_ENTITY}/k{index:06d}"


def thin_scan(points: NDArray[np.floating], cell: float = SCAN_CELL) -> NDArray[np.float32]:
    """One point (the first) per `cell` × `cell` square, in the scan's order."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    points = points[np.all(np.isfinite(points), axis=1)]
    return points[one_per_cell(points, cell)].astype(np.float32)


def placed_bounds(scans: Sequence[FloatArray], poses: FloatArray, *more: FloatArray) -> Bounds:
    """The extent of all `scans` (keyframe-frame points) placed at `poses`, of the poses and of `more`."""
    placed = [place(np.asarray(scan).reshape(-1, 2), pose) for scan, pose in zip(scans, poses, strict=True)]
    return world_bounds(poses, *placed, *more)


def log_occupancy(recording: rr.RecordingStream, image: NDArray[np.uint8], origin: FloatArray,
                  resolution: float) -> None:
    """The grey occupancy picture (north up, row 0 the northern edge; cell (0, 0) of the grid starts at
    `origin`, cells of `resolution` m) as a static image in world metres under the walls."""
    from PIL import Image  # as pipeline.outputs.write_png: only when a map is recorded

    height = image.shape[0]
    colors = np.zeros((256, 4), dtype=np.uint8)  # the palette: every grey not drawn is transparent
    colors[list(OCCUPANCY_VIEW_COLORS)] = list(OCCUPANCY_VIEW_COLORS.values())
    png = io.BytesIO()
    # One byte a pixel, the colours a palette (alpha in its tRNS chunk): the viewer decodes it to the same
    # RGBA, and deflating a quarter of the bytes took UAL's map (14 M pixels) 0.03 s instead of 0.5 s.
    # zlib's fastest level: still a few % of the raw pixels, in half the time of the default.
    picture = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8), mode="P")
    picture.putpalette(colors[:, :3].tobytes())
    picture.save(png, format="PNG", compress_level=1, transparency=colors[:, 3].tobytes())
    # Pixel (u, v) covers x = origin_x + u·res, y = top − v·res: image rows run south.
    recording.log(
        OCCUPANCY_ENTITY,
        rr.Transform3D(translation=[float(origin[0]), float(origin[1]) + height * resolution, 0.0],
                       scale=[resolution, -resolution, 1.0]),
        static=True,
    )
    recording.log(OCCUPANCY_IMAGE_ENTITY, rr.EncodedImage(contents=png.getvalue(), media_type="image/png",
                                                          draw_order=OCCUPANCY_DRAW_ORDER), static=True)


class KeyframeMapRecorder(PoseBatches):
    """The walls that move: each keyframe's scan once, then every iteration's keyframe poses as one
    `Transform3D` per keyframe entity, in column batches (the last iteration whole).

    Used as the `IterationSink` of `pipeline.keyframe_optimization.optimize_keyframes`."""

    def __init__(self, recording: rr.RecordingStream, scans: Sequence[FloatArray],
                 color: tuple[int, ...] = MAP_COLOR) -> None:
        super().__init__(recording)
        self._scans = scans
        self._color = color
        self._scans_logged = False
        self._last_sent: NDArray[np.float64] = np.full((len(scans), 3), np.nan)

    def add(self, step: int, iteration: Iteration) -> None:
        if not self._scans_logged:  # each keyframe's scan, at the first iteration
            # On `iteration` (not static): on the `scan` and `time` timelines the keyframes have no pose,
            # and static points would be drawn piled up at the origin there.
            self._recording.set_time(ITERATION_TIMELINE, sequence=step)
            # `rr.Points2D`'s components, the style's built once: the archetype validated every field of
            # each of a thousand keyframes' scans.
            style = rr.Points2D.from_fields(colors=[self._color], radii=[MAP_POINT_RADIUS],
                                            draw_order=MAP_DRAW_ORDER)
            for index, scan in enumerate(self._scans):
                positions = rr.components.Position2DBatch(thin_scan(scan)).described(
                    rr.Points2D.descriptor_positions())
                self._recording.log(f"{keyframe_entity(index)}/scan", [positions], style)
            self._recording.reset_time()
            self._scans_logged = True
        super().add(step, iteration)

    def _send_batch(self, steps: IntArray, poses: NDArray[np.float32], *, final: bool) -> None:
        sent = rows_to_send(poses.astype(np.float64), self._last_sent, SHOWN_MOVE, SHOWN_TURN, final)
        # Keyframe by keyframe, the rows sent: a few % of all (CSAIL: 35 k of 526 k), so only their
        # quaternions are computed.
        keyframes, rows = np.nonzero(sent.T)
        chosen = poses[rows, keyframes]
        translations = np.pad(chosen[:, :2], ((0, 0), (0, 1)))  # z = 0
        quaternions = from_yaw(chosen[:, 2]).astype(np.float32)
        starts = np.searchsorted(keyframes, np.arange(poses.shape[1] + 1))
        for index in np.flatnonzero(np.diff(starts)):
            block = slice(starts[index], starts[index + 1])
            self._recording.send_columns(
                keyframe_entity(int(index)),
                indexes=[rr.TimeColumn(ITERATION_TIMELINE, sequence=steps[rows[block]])],
                columns=transform3d_columns(translations[block], quaternions[block]),
            )


@njit(cache=True)
def rows_to_send(poses: FloatArray, last_sent: FloatArray, move: float, turn: float,
                 keep_last: bool) -> NDArray[np.bool_]:
    """(T, K) which of the (T, K, 3) poses differ from their keyframe's last sent pose by more than
    `move` (m) or `turn` (rad); `last_sent` (K, 3, NaN for never) is updated. With `keep_last` the last
    row is sent whole."""
    count, keyframes = poses.shape[0], poses.shape[1]
    sent = np.zeros((count, keyframes), dtype=np.bool_)
    for k in range(keyframes):
        for t in range(count):
            turned = (poses[t, k, 2] - last_sent[k, 2] + math.pi) % (2.0 * math.pi) - math.pi
            moved = math.hypot(poses[t, k, 0] - last_sent[k, 0], poses[t, k, 1] - last_sent[k, 1])
            # NaN compares false: a keyframe never sent is sent.
            if not (moved <= move and abs(turned) <= turn) or (keep_last and t == count - 1):
                sent[t, k] = True
                for axis in range(3):
                    last_sent[k, axis] = poses[t, k, axis]
    return sent
