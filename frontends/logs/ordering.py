"""Sensor-time order from log-time order, with bounded memory.

Logs are written in the order messages arrived; each source's stamps lag (a scan is stamped when its
sweep began) or lead (AMCL post-dates its map → odom transform) its log time by its own amount. So each
source (a sensor frame, or a tf edge) keeps its own newest stamp, and an item is released once it is
`window_ns` older than the newest stamp of the slowest source still active (one that produced something
within `idle_ns` of log time: a topic that ended must not hold everything back). At most `max_items`
are held. An item whose stamp is earlier than one already released cannot be placed any more: it is
dropped, counted, and a `LogWarning` says how many at the end. Static transforms hold at all times and
pass straight through.
"""

from __future__ import annotations

import dataclasses
import heapq
import warnings
from collections.abc import Iterable, Iterator, MutableMapping
from pathlib import Path
from typing import Protocol, TypeVar

from frontends.errors import LogWarning
from frontends.logs.types import Cloud3D, OdometryPose, Scan2D, Transform

DEFAULT_WINDOW_NS = 2_000_000_000
DEFAULT_IDLE_NS = 5_000_000_000
DEFAULT_MAX_ITEMS = 10_000


class Stamped(Protocol):
    @property
    def stamp_ns(self) -> int: ...

    @property
    def log_time_ns(self) -> int: ...


T = TypeVar("T", bound=Stamped)


_SOURCE_NAMES = {Scan2D: "scans", Cloud3D: "clouds", OdometryPose: "odometry poses", Transform: "transforms"}


Source = tuple[type, str | None]


def _source(item: Stamped) -> Source:
    """What keeps its own stamps: one tf edge, or one sensor / odometry frame of one type."""
    if isinstance(item, Transform):
        return (Transform, item.child_frame)
    return (type(item), getattr(item, "frame_id", None))


def _at_log_time(item: T) -> T:
    return dataclasses.replace(item, stamp_ns=item.log_time_ns)  # type: ignore[type-var]


def log_time_where_unstamped(items: Iterable[T], path: Path,
                             counts: MutableMapping[str, int] | None = None) -> Iterator[T]:
    """The items, those of a source whose stamps are unset (0, ROS's "no time": a driver or converter
    that never filled the header) given their log time as stamp. Otherwise every scan after the first
    would share its stamp, and the run would be one scan long. A source is unset when its first two
    stamps are both 0; a first stamp of 0 followed by another (a simulator's clock starting at 0) is a
    real stamp, so the first item of each source is held until its second comes (one item per source).
    Items given their log time are counted in `counts["messages_stamped_by_log_time"]`, and a
    `LogWarning` per source says so at the end."""
    held: dict[Source, T] = {}
    unset: dict[Source, int] = {}  # per unset source: items given their log time
    decided: set[Source] = set()  # stamped sources (the common case, tested first)
    for item in items:
        if isinstance(item, Transform) and item.is_static:
            yield item
            continue
        source = _source(item)
        if source in decided:
            yield item
        elif source in unset:
            if item.stamp_ns == 0:
                unset[source] += 1
                item = _at_log_time(item)
            yield item
        elif source in held:
            first = held.pop(source)
            if item.stamp_ns == 0:
                unset[source] = 2
                first, item = _at_log_time(first), _at_log_time(item)
            else:
                decided.add(source)
            yield first
            yield item
        elif item.stamp_ns == 0:
            held[source] = item
        else:
            decided.add(source)
            yield item
    yield from held.values()  # a source of one item stamped 0: nothing says it is unset
    for (kind, frame), number in unset.items():
        if counts is not None:
            counts["messages_stamped_by_log_time"] = counts.get("messages_stamped_by_log_time", 0) + number
        warnings.warn(f"{path}: {number} {_SOURCE_NAMES.get(kind, 'messages')} in frame {frame!r} had no "
                      "stamp (0): their log times were used instead", LogWarning, stacklevel=2)


def by_stamp(
    items: Iterable[T],
    path: Path,
    window_ns: int = DEFAULT_WINDOW_NS,
    max_items: int = DEFAULT_MAX_ITEMS,
    idle_ns: int = DEFAULT_IDLE_NS,
    counts: MutableMapping[str, int] | None = None,
) -> Iterator[T]:
    """The items sorted by `stamp_ns` (ties keep arrival order), as long as none is more than `window_ns`
    of sensor time late within its own source. Dropped items are added to `counts["messages_late"]`."""
    heap: list[tuple[int, int, T]] = []
    newest: dict[Source, int] = {}  # per source: newest stamp
    last_seen: dict[Source, int] = {}  # per source: log time of its latest item
    released = -(2**63)
    now = -(2**63)
    late = 0
    arrival = 0
    push, pop = heapq.heappush, heapq.heappop
    for item in items:
        if isinstance(item, Transform) and item.is_static:
            yield item
            continue
        source = _source(item)
        stamp = item.stamp_ns
        if stamp < released:
            late += 1
            continue
        push(heap, (stamp, arrival, item))
        arrival += 1
        if stamp > newest.get(source, -(2**63)):
            newest[source] = stamp
        last_seen[source] = item.log_time_ns
        if item.log_time_ns > now:
            now = item.log_time_ns
        if len(newest) == 1:  # one source (a single topic): no need to look for the slowest
            threshold = newest[source] - window_ns
        else:
            active = [newest[s] for s, seen in last_seen.items() if seen >= now - idle_ns]
            threshold = (min(active) if active else stamp) - window_ns
        while heap and (heap[0][0] < threshold or len(heap) > max_items):
            released, _, ready = pop(heap)
            yield ready
    while heap:
        yield pop(heap)[2]
    if late and counts is not None:
        counts["messages_late"] = counts.get("messages_late", 0) + late
    if late:
        warnings.warn(
            f"{path}: {late} messages dropped: their stamps were more than {window_ns / 1e9:g} s older than "
            "messages already read (raise the reorder window to keep them)",
            LogWarning,
            stacklevel=2,
        )


def first_of_each_stamp(items: Iterable[T], path: Path, what: str,
                        counts: MutableMapping[str, int] | None = None) -> Iterator[T]:
    """Of stamp-sorted items (`by_stamp`), the first of each stamp: the outputs hold one pose per sensor
    stamp (a TUM or KITTI file with a stamp twice is refused by the tools that read it), and a second
    scan or cloud stamped alike (a driver that did not stamp it anew, a message recorded twice) says
    nothing of when it was taken. The rest are counted in `counts["<what>_repeated_stamp"]` and a
    `LogWarning` says how many at the end."""
    last: int | None = None
    repeated = 0
    for item in items:
        if item.stamp_ns == last:
            repeated += 1
            continue
        last = item.stamp_ns
        yield item
    if repeated and counts is not None:
        counts[f"{what}_repeated_stamp"] = counts.get(f"{what}_repeated_stamp", 0) + repeated
    if repeated:
        warnings.warn(f"{path}: {repeated} {what} skipped: each was stamped the same as the one before it "
                      "(the first of each stamp kept)", LogWarning, stacklevel=2)
