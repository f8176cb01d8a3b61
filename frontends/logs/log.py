"""`open_log(path)`: any supported log as one typed stream in sensor-time order.

    with open_log("run.mcap") as log:
        print(log.info())                  # from the summary / index, instant
        for scan in log.scans():           # the LaserScan topic, found by type
            ...
        tree = log.transform_tree()        # /tf and /tf_static

Each iterator is one streaming pass over the file (memory does not grow with the log). Topics are picked
by message type: when a log has several candidates the error lists them and names the CLI option that
chooses one.
"""

from __future__ import annotations

import math
from array import array
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from frontends.errors import TopicSelectionError
from frontends.logs.containers.base import Channel, Container
from frontends.logs.containers.detect import open_container
from frontends.logs.converters import RangeLimits
from frontends.logs.dispatch import DecodeOptions, Item, Kind, build_decoders, decode, message_kind
from frontends.logs.guard import guarded_call, guarded_iter
from frontends.logs.ordering import (
    DEFAULT_MAX_ITEMS,
    DEFAULT_WINDOW_NS,
    by_stamp,
    first_of_each_stamp,
    log_time_where_unstamped,
)
from frontends.logs.transforms import TransformTree
from frontends.logs.types import Cloud3D, LogInfo, OdometryPose, Scan2D, Transform

ODOMETRY_FRAME = "odom"
"""Without an odometry topic, the odometry is tf's dynamic edge out of this frame (REP 105's odom → base)."""

SCAN_TOPIC_OPTION = "--scan-topic"
ODOMETRY_TOPIC_OPTION = "--odom-topic"
_KIND_NAMES = {
    "scan": "LaserScan",
    "cloud": "PointCloud",
    "odometry": "odometry",
    "transform": "transform",
}


def _article(word: str) -> str:
    return "an" if word[:1].lower() in "aeiou" else "a"


def open_log(path: str | Path) -> LogReader:
    """Open a log: an MCAP file, a ROS 1 bag (a split set by any of its files or their directory), or a
    ROS 2 bag directory (or its metadata.yaml / .db3). Raises `LogFileError` for anything else."""
    return LogReader(open_container(path))


class LogReader:
    """One opened log. Iterators are independent streaming passes; `close()` frees temporary files."""

    def __init__(self, container: Container) -> None:
        self._container = container
        self.path: Path = container.path
        self.channels: tuple[Channel, ...] = guarded_call(self.path, container.channels)
        self._info: LogInfo | None = None
        self.counts: Counter[str] = Counter()
        """What reading dropped or repaired, summed over every pass (e.g. `messages_late`); for the
        caller's summary."""
        self._odometry_from_tree: _TfOdometry | None = None
        """The odometry on tf, kept by the last `transform_tree` of a log without an odometry topic for the
        next `odometry()` (see there)."""

    def __enter__(self) -> LogReader:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self._container.close()

    # --- what the log holds -------------------------------------------------------------------------

    def info(self) -> LogInfo:
        """Path, container, time span and topics, from the summary / index (not from the messages)."""
        if self._info is None:
            self._info = guarded_call(self.path, self._container.info)
        return self._info

    def topics_of_kind(self, kind: Kind) -> tuple[str, ...]:
        """Topics whose messages we read as `kind` ("scan", "cloud", "odometry", "transform"), sorted."""
        return tuple(sorted({c.topic for c in self.channels if message_kind(c) == kind}))

    @property
    def transform_topics(self) -> tuple[str, ...]:
        """The tf topics (tf2_msgs/TFMessage, foxglove.FrameTransform(s))."""
        return self.topics_of_kind("transform")

    def select_topic(
        self, kinds: Iterable[Kind], topic: str | None = None, option: str = SCAN_TOPIC_OPTION
    ) -> str:
        """The one topic of these kinds (or check `topic` is one of them); `TopicSelectionError` listing
        the candidates when there are none or several."""
        kinds = tuple(kinds)
        wanted = " or ".join(_KIND_NAMES[k] for k in kinds)
        candidates = sorted({c.topic for c in self.channels if message_kind(c) in kinds})
        if topic is not None:
            if topic in candidates:
                return topic
            types = sorted({c.type for c in self.channels if c.topic == topic})
            if types:
                raise TopicSelectionError(
                    self.path,
                    f"topic {topic} carries {', '.join(types)}, not {_article(wanted)} {wanted} type we can "
                    "read",
                    candidates,
                    option,
                )
            if candidates:
                raise TopicSelectionError(self.path, f"no topic {topic}; {wanted} topics", candidates, option)
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            present = [f"{c.topic} ({c.type})" for c in sorted(self.channels, key=lambda c: c.topic)]
            missing = (f"no {wanted} topic" if topic is None
                       else f"no topic {topic} ({option}), and no {wanted} topic")
            raise TopicSelectionError(self.path, f"{missing}; the log has", present or ["no topics"])
        described = [
            f"{t} ({', '.join(sorted({c.type for c in self.channels if c.topic == t}))})" for t in candidates
        ]
        raise TopicSelectionError(self.path, f"several {wanted} topics", described, option)

    def sensor_topic(self, topic: str | None = None) -> tuple[str, Kind]:
        """The scan or cloud topic (the one the pipeline matches), and which of the two it is."""
        chosen = self.select_topic(("scan", "cloud"), topic)
        kind = next(
            message_kind(c) for c in self.channels if c.topic == chosen and message_kind(c) is not None
        )
        return chosen, kind  # type: ignore[return-value]

    def odometry_topic(self, topic: str | None = None) -> str | None:
        """The odometry topic (nav_msgs/Odometry, foxglove.PoseInFrame(s)), None when the log has none."""
        if topic is None and not self.topics_of_kind("odometry"):
            return None
        return self.select_topic(("odometry",), topic, ODOMETRY_TOPIC_OPTION)

    # --- streams --------------------------------------------------------------------------------------

    def messages(
        self,
        topics: Iterable[str],
        *,
        range_limits: tuple[float, float] = (0.0, math.inf),
        window_ns: int = DEFAULT_WINDOW_NS,
        max_items: int = DEFAULT_MAX_ITEMS,
    ) -> Iterator[Item]:
        """Everything on these topics as Scan2D / Cloud3D / OdometryPose / Transform, merged in one pass,
        sorted by sensor stamp (static transforms first come when read). `range_limits` narrows every
        scan's valid ranges (Foxglove scans have none of their own)."""
        topics = set(topics)
        channels = [c for c in self.channels if c.topic in topics and message_kind(c) is not None]
        if not channels:  # nothing to read: do not decompress the whole log to find that out
            return iter(())
        decoders = build_decoders(self.path, channels, DecodeOptions(RangeLimits(*range_limits)))
        raw = guarded_iter(self.path, self._container.messages({c.id for c in channels}))
        items = log_time_where_unstamped(decode(self.path, raw, decoders), self.path, self.counts)
        return by_stamp(items, self.path, window_ns, max_items, counts=self.counts)

    def scans(
        self,
        topic: str | None = None,
        *,
        range_limits: tuple[float, float] = (0.0, math.inf),
        window_ns: int = DEFAULT_WINDOW_NS,
        max_items: int = DEFAULT_MAX_ITEMS,
    ) -> Iterator[Scan2D]:
        """The scans of the LaserScan topic (found by type unless given), the first of each stamp
        (`first_of_each_stamp`); options as for `messages`."""
        chosen = self.select_topic(("scan",), topic)
        scans = self.messages([chosen], range_limits=range_limits, window_ns=window_ns, max_items=max_items)
        return first_of_each_stamp(scans, self.path, "scans", self.counts)  # type: ignore[arg-type]

    def clouds(
        self,
        topic: str | None = None,
        *,
        window_ns: int = DEFAULT_WINDOW_NS,
        max_items: int = DEFAULT_MAX_ITEMS,
    ) -> Iterator[Cloud3D]:
        """The clouds of the PointCloud topic (found by type unless given), the first of each stamp."""
        chosen = self.select_topic(("cloud",), topic)
        clouds = self.messages([chosen], window_ns=window_ns, max_items=max_items)
        return first_of_each_stamp(clouds, self.path, "clouds", self.counts)  # type: ignore[arg-type]

    def transforms(
        self, *, window_ns: int = DEFAULT_WINDOW_NS, max_items: int = DEFAULT_MAX_ITEMS
    ) -> Iterator[Transform]:
        """Every transform of every tf topic, static ones included."""
        return self.messages(self.transform_topics, window_ns=window_ns, max_items=max_items)  # type: ignore[return-value]

    def transform_tree(self, cache_ns: int | None = None) -> TransformTree:
        """A transform tree of the whole log's tf (small: tf messages are a few dozen bytes each).

        A log without an odometry topic has its odometry on tf, which the next `odometry()` would read in a
        second pass over the whole log (every chunk decompressed again for the tf among the scans: 2–3 % of
        the replays of UAL, Intel and a simulated 40 Hz laser): its edge out of `ODOMETRY_FRAME` is kept
        from this pass instead, the poses the second pass would give, in 72 bytes each."""
        if self.topics_of_kind("odometry"):
            return TransformTree(cache_ns).extend(self.transforms())
        odometry = _TfOdometry()
        tree = TransformTree(cache_ns).extend(odometry.noting(self.transforms()))
        self._odometry_from_tree = odometry
        return tree

    def odometry(
        self,
        topic: str | None = None,
        *,
        odom_frame: str = ODOMETRY_FRAME,
        window_ns: int = DEFAULT_WINDOW_NS,
        max_items: int = DEFAULT_MAX_ITEMS,
    ) -> Iterator[OdometryPose]:
        """Odometry poses: from the odometry topic when the log has one; otherwise from the dynamic tf
        edge out of `odom_frame` (the first child frame seen: REP 105's odom → base). Empty when neither."""
        chosen = self.odometry_topic(topic)
        if chosen is not None:
            return self.messages([chosen], window_ns=window_ns, max_items=max_items)  # type: ignore[return-value]
        return self._tf_odometry(odom_frame, window_ns, max_items).poses()

    def odometry_arrays(self, topic: str | None = None) -> OdometryArrays | None:
        """`odometry(topic)` as arrays, None when it is empty. The odometry on tf comes straight from the
        arrays it was noted in: an `OdometryPose` each, only to be taken apart again, was 0.04 s of the UAL
        log's reading (14 751 poses)."""
        if self.odometry_topic(topic) is None:
            return self._tf_odometry().arrays()
        stamps: list[int] = []
        translations: list[NDArray[np.float64]] = []
        rotations: list[NDArray[np.float64]] = []
        frames = ("", "")
        for pose in self.odometry(topic):
            stamps.append(pose.stamp_ns)
            translations.append(pose.translation)
            rotations.append(pose.rotation)
            frames = (pose.frame_id, pose.child_frame_id)
        if not stamps:
            return None
        return OdometryArrays(np.array(stamps, dtype=np.int64), np.array(translations, dtype=np.float64),
                              np.array(rotations, dtype=np.float64), *frames)

    def _tf_odometry(
        self,
        odom_frame: str = ODOMETRY_FRAME,
        window_ns: int = DEFAULT_WINDOW_NS,
        max_items: int = DEFAULT_MAX_ITEMS,
    ) -> _TfOdometry:
        """The odometry on tf: the one `transform_tree` kept when it read it with these options, else read
        in a pass of its own."""
        kept, self._odometry_from_tree = self._odometry_from_tree, None
        options = (odom_frame, window_ns, max_items)
        same_pass = options == (ODOMETRY_FRAME, DEFAULT_WINDOW_NS, DEFAULT_MAX_ITEMS)
        if kept is not None and same_pass:  # `transform_tree` read it, in a pass with these options
            return kept
        odometry = _TfOdometry(odom_frame)
        for _ in odometry.noting(self.transforms(window_ns=window_ns, max_items=max_items)):
            pass
        return odometry


class OdometryArrays(NamedTuple):
    """Odometry poses in arrival order: the pose of `child_frame_id` in `frame_id` (those of the last
    message) at each stamp."""

    stamps_ns: NDArray[np.int64]
    translations: NDArray[np.float64]
    """(N, 3)"""
    rotations: NDArray[np.float64]
    """(N, 4) quaternions (x, y, z, w)"""
    frame_id: str
    child_frame_id: str


class _TfOdometry:
    """The odometry on tf: the dynamic transforms out of `frame` to the first child frame seen (REP 105's
    odom → base), noted as they pass (`noting`) in flat arrays: stamps, log times, and translation +
    rotation (7 numbers) per pose."""

    def __init__(self, frame: str = ODOMETRY_FRAME) -> None:
        self.frame = frame
        self.child: str | None = None
        self.stamps = array("q")
        self.log_times = array("q")
        self.values = array("d")

    def noting(self, transforms: Iterator[Transform]) -> Iterator[Transform]:
        """The transforms, those of the odometry noted."""
        for transform in transforms:
            if not transform.is_static and transform.parent_frame == self.frame:
                if self.child is None:
                    self.child = transform.child_frame
                if transform.child_frame == self.child:
                    self.stamps.append(transform.stamp_ns)
                    self.log_times.append(transform.log_time_ns)
                    # tolist(): the same floats as iterating the arrays, at a third of the cost
                    self.values.extend(transform.translation.tolist())
                    self.values.extend(transform.rotation.tolist())
            yield transform

    def arrays(self) -> OdometryArrays | None:
        if not self.stamps:
            return None
        values = np.frombuffer(self.values, dtype=np.float64).reshape(-1, 7)
        # Copies, contiguous like the arrays stacked from `poses()`; and `self.values` stays growable.
        return OdometryArrays(np.array(self.stamps, dtype=np.int64), values[:, :3].copy(),
                              values[:, 3:].copy(), self.frame, self.child or "")

    def poses(self) -> Iterator[OdometryPose]:
        values = self.values
        for k, (stamp, log_time) in enumerate(zip(self.stamps, self.log_times, strict=True)):
            yield OdometryPose(stamp, log_time, self.frame, self.child or "",
                               np.array(values[7 * k : 7 * k + 3]), np.array(values[7 * k + 3 : 7 * k + 7]))
