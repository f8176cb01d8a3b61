"""Checks of a saved keyframe map's arrays as a session file gives them back: the frontends write them
(`session_content`), so the frontends read them (`SavedMap2D.from_arrays`, `SavedMap3D.from_arrays`). A
missing array, or one that does not fit the others, is a `SavedArraysError`; the session reader puts the
file's name in front of it."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np
from numpy.typing import DTypeLike, NDArray

from frontends.errors import FrontendError
from optimizer.errors import OptimizerError

T = TypeVar("T")


class SavedArraysError(FrontendError):
    """A saved map's arrays are missing or do not fit one another: `str()` is "damaged session file (…)"."""


def checked(label: str, arrays: Mapping[str, NDArray[Any]], shape: tuple[int, ...], kind: DTypeLike, *,
            name: str | None = None) -> NDArray[Any]:
    """`arrays[name]` (default: `label`) if it has `shape` (−1: any length), a dtype of `kind` and only
    finite values (floats, returned as float64)."""
    array = arrays[label if name is None else name]
    fits = array.ndim == len(shape) and all(want in (-1, got) for want, got in zip(shape, array.shape,
                                                                                      strict=True))
    if not fits or not np.issubdtype(array.dtype, kind):
        raise SavedArraysError(f"damaged session file ({label}: {array.dtype} {array.shape})")
    if kind is np.floating:
        if not np.all(np.isfinite(array)):
            raise SavedArraysError(f"damaged session file ({label}: values not finite)")
        return array.astype(np.float64)
    return array


def checked_keyframes(
    arrays: Mapping[str, NDArray[Any]], keyframe_points: Sequence[NDArray[Any]], required: Sequence[str],
    pose_shape: tuple[int, ...], point_dims: int, what: str,
) -> tuple[NDArray[np.float64], tuple[NDArray[np.float64], ...]]:
    """The keyframe poses, (K, *pose_shape), and each keyframe's points, (n, point_dims), once every
    `required` array is there and there are as many point sets as poses."""
    missing = [name for name in required if name not in arrays]
    if missing:
        raise SavedArraysError(f"damaged session file (no {', '.join(missing)})")
    poses = checked("keyframe_poses", arrays, (-1, *pose_shape), np.floating)
    if len(keyframe_points) != len(poses):
        raise SavedArraysError(f"damaged session file ({len(keyframe_points)} keyframe {what} for "
                               f"{len(poses)} keyframe poses)")
    points = tuple(checked(f"keyframe_points[{index}]", {"": each}, (-1, point_dims), np.floating, name="")
                   for index, each in enumerate(keyframe_points))
    return poses, points


def checked_edges(arrays: Mapping[str, NDArray[Any]], keyframes: int) -> tuple[NDArray[Any], NDArray[Any]]:
    """`edge_from`, `edge_to`: equally long, between keyframes that exist."""
    edge_from = checked("edge_from", arrays, (-1,), np.integer)
    edge_to = checked("edge_to", arrays, (len(edge_from),), np.integer)
    ends = np.concatenate([edge_from, edge_to])
    if len(ends) and (ends.min() < 0 or ends.max() >= keyframes):
        raise SavedArraysError("damaged session file (constraints between keyframes that do not exist)")
    return edge_from, edge_to


def checked_members(arrays: Mapping[str, NDArray[Any]], sensor: str,
                    keyframes: int) -> tuple[NDArray[Any], NDArray[Any]]:
    """`<sensor>_stamps_ns` and `<sensor>_keyframes` (which keyframe each scan or cloud hangs off): equally
    long, of keyframes that exist."""
    stamps = checked(f"{sensor}_stamps_ns", arrays, (-1,), np.integer)
    owners = checked(f"{sensor}_keyframes", arrays, (len(stamps),), np.integer)
    if len(stamps) and (owners.min() < 0 or owners.max() >= keyframes):
        raise SavedArraysError(f"damaged session file ({sensor}s of keyframes that do not exist)")
    return stamps, owners


def checked_graph(build: Callable[[], T]) -> T:
    """What `build` makes of the saved constraints (a `PoseGraph`), which checks them as a graph file's
    are (information positive definite, no constraint from a keyframe to itself): its `OptimizerError`
    as a `SavedArraysError`, so that the session reader names the file."""
    try:
        return build()
    except OptimizerError as error:
        raise SavedArraysError(f"damaged session file ({error})") from error
