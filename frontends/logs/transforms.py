"""A tf-like transform tree: static and time-stamped transforms, queried between any two frames at a time.

Each frame has one parent. Static edges hold at all times; a dynamic edge keeps its samples in growable
numpy arrays and is interpolated between the two samples around the query time (linear translation,
spherical rotation). Asking outside an edge's samples is an error unless within `tolerance_ns` of the
nearest one (then that sample is used). With `cache_ns`, samples older than that much before an edge's
newest are dropped, so a tree fed from a long log stays small.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.errors import TransformLookupError
from frontends.logs import rotations
from frontends.logs.types import Transform

FloatArray = NDArray[np.float64]


class _Series:
    """The samples of one dynamic edge (child → parent), sorted by stamp when queried."""

    __slots__ = ("parent", "rotations", "size", "sorted", "stamps", "translations")

    def __init__(self, parent: str) -> None:
        self.parent = parent
        self.stamps = np.empty(16, np.int64)
        self.translations = np.empty((16, 3))
        self.rotations = np.empty((16, 4))
        self.size = 0
        self.sorted = True

    def append(
        self, stamp_ns: int, translation: FloatArray, rotation: FloatArray, cache_ns: int | None
    ) -> None:
        if self.size == self.stamps.shape[0]:
            if cache_ns is not None:
                self.prune(int(self.stamps[: self.size].max()) - cache_ns)
            if self.size > self.stamps.shape[0] // 2:
                capacity = 2 * self.stamps.shape[0]
                self.stamps = np.resize(self.stamps, capacity)
                self.translations = np.resize(self.translations, (capacity, 3))
                self.rotations = np.resize(self.rotations, (capacity, 4))
        i = self.size
        if i and stamp_ns < self.stamps[i - 1]:
            self.sorted = False
        self.stamps[i] = stamp_ns
        self.translations[i] = translation
        self.rotations[i] = rotation
        self.size = i + 1

    def prune(self, oldest_ns: int) -> None:
        self._sort()
        keep = int(np.searchsorted(self.stamps[: self.size], oldest_ns, "left"))
        if keep:
            n = self.size - keep
            self.stamps[:n] = self.stamps[keep : self.size]
            self.translations[:n] = self.translations[keep : self.size]
            self.rotations[:n] = self.rotations[keep : self.size]
            self.size = n

    def _sort(self) -> None:
        if not self.sorted:
            order = np.argsort(self.stamps[: self.size], kind="stable")
            self.stamps[: self.size] = self.stamps[order]
            self.translations[: self.size] = self.translations[order]
            self.rotations[: self.size] = self.rotations[order]
            self.sorted = True

    def at(self, child: str, stamps: NDArray[np.int64], tolerance_ns: int) -> tuple[FloatArray, FloatArray]:
        """(translations (K, 3), rotations (K, 4)) at the stamps, interpolated."""
        self._sort()
        known = self.stamps[: self.size]
        after = np.searchsorted(known, stamps, "left")  # first sample at or after each query
        before = np.clip(after - 1, 0, self.size - 1)
        after_clipped = np.clip(after, 0, self.size - 1)
        exact = known[after_clipped] == stamps
        inside = (after > 0) & (after < self.size)
        near_start = (after == 0) & (known[0] - stamps <= tolerance_ns)
        near_end = (after == self.size) & (stamps - known[-1] <= tolerance_ns)
        answerable = exact | inside | near_start | near_end
        if not answerable.all():
            bad = int(stamps[np.argmin(answerable)])
            raise TransformLookupError(
                f"no transform {self.parent} → {child} at {bad} ns: "
                f"its data spans {known[0]} … {known[-1]} ns"
            )
        low = np.where(near_start, 0, np.where(exact, after_clipped, before))
        high = np.where(near_end, self.size - 1, np.where(exact, after_clipped, after_clipped))
        span = (known[high] - known[low]).astype(np.float64)
        fraction = np.where(span > 0, (stamps - known[low]) / np.where(span > 0, span, 1.0), 0.0)
        fraction = np.clip(fraction, 0.0, 1.0)
        translations = self.translations[low] + fraction[:, None] * (
            self.translations[high] - self.translations[low]
        )
        return translations, rotations.slerp(self.rotations[low], self.rotations[high], fraction)


class TransformTree:
    """Static and dynamic transforms between named frames."""

    def __init__(self, cache_ns: int | None = None) -> None:
        self.cache_ns = cache_ns
        self._static: dict[str, tuple[str, FloatArray, FloatArray]] = {}
        self._dynamic: dict[str, _Series] = {}

    def add(self, transform: Transform) -> None:
        """Add one transform. A frame given a new parent keeps only the new parent's data."""
        child = transform.child_frame
        if transform.is_static:
            self._dynamic.pop(child, None)
            self._static[child] = (transform.parent_frame, transform.translation, transform.rotation)
            return
        self._static.pop(child, None)
        series = self._dynamic.get(child)
        if series is None or series.parent != transform.parent_frame:
            series = self._dynamic[child] = _Series(transform.parent_frame)
        series.append(transform.stamp_ns, transform.translation, transform.rotation, self.cache_ns)

    def extend(self, transforms: Iterable[Transform]) -> TransformTree:
        """Add every transform; returns the tree."""
        for transform in transforms:
            self.add(transform)
        return self

    @property
    def frames(self) -> frozenset[str]:
        """Every frame named as a parent or child."""
        edges = [(child, parent) for child, (parent, _, _) in self._static.items()]
        edges += [(child, series.parent) for child, series in self._dynamic.items()]
        return frozenset(frame for edge in edges for frame in edge)

    def parent(self, frame: str) -> str | None:
        """The parent of a frame, None for a root or unknown frame."""
        if frame in self._dynamic:
            return self._dynamic[frame].parent
        if frame in self._static:
            return self._static[frame][0]
        return None

    def is_static(self, frame: str) -> bool:
        """Whether the edge from `frame` to its parent is static."""
        return frame in self._static

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        seen = {frame}
        parent = self.parent(frame)
        while parent is not None:
            if parent in seen:
                raise TransformLookupError(f"transform tree has a cycle through {parent!r}")
            chain.append(parent)
            seen.add(parent)
            parent = self.parent(parent)
        return chain

    def _to_ancestor(
        self, chain: list[str], ancestor: str, stamps: NDArray[np.int64], tolerance_ns: int
    ) -> tuple[FloatArray, FloatArray, bool]:
        """Transforms from chain[0] into `ancestor` (an element of the chain) at the stamps."""
        count = stamps.shape[0]
        translation = np.zeros((count, 3))
        rotation = np.zeros((count, 4))
        rotation[:, 3] = 1.0
        static = True
        for child in chain[: chain.index(ancestor)]:
            if child in self._dynamic:
                edge_t, edge_q = self._dynamic[child].at(child, stamps, tolerance_ns)
                static = False
            else:
                _, t, q = self._static[child]
                edge_t = np.broadcast_to(t, (count, 3))
                edge_q = np.broadcast_to(q, (count, 4))
            # parent←chain[0] = (parent←child) ∘ (child←chain[0])
            translation = edge_t + rotations.rotate(edge_q, translation)
            rotation = rotations.multiply(edge_q, rotation)
        return translation, rotation, static

    def lookup_many(
        self, target_frame: str, source_frame: str, stamps_ns: ArrayLike, *, tolerance_ns: int = 0
    ) -> tuple[FloatArray, FloatArray]:
        """(translations (K, 3), rotations (K, 4)) mapping `source_frame` coordinates into `target_frame`
        at each stamp."""
        stamps = np.atleast_1d(np.asarray(stamps_ns, dtype=np.int64))
        translation, rotation, _ = self._lookup(target_frame, source_frame, stamps, tolerance_ns)
        return translation, rotation

    def lookup(
        self, target_frame: str, source_frame: str, stamp_ns: int, *, tolerance_ns: int = 0
    ) -> Transform:
        """The transform mapping `source_frame` coordinates into `target_frame` at `stamp_ns` (as a
        Transform with parent `target_frame`, child `source_frame`; static when every edge on the way is)."""
        stamps = np.array([stamp_ns], dtype=np.int64)
        translation, rotation, static = self._lookup(target_frame, source_frame, stamps, tolerance_ns)
        return Transform(target_frame, source_frame, stamp_ns, stamp_ns, translation[0], rotation[0], static)

    def sensor_mount(self, base_frame: str, sensor_frame: str, stamp_ns: int) -> Transform | None:
        """The transform placing a sensor's points in the base frame, None when tf does not link the two
        frames (the sensor is then taken to sit at the base's origin)."""
        if not sensor_frame or sensor_frame == base_frame:
            return None
        try:
            return self.lookup(base_frame, sensor_frame, stamp_ns)
        except TransformLookupError:
            return None

    def can_transform(
        self, target_frame: str, source_frame: str, stamp_ns: int, *, tolerance_ns: int = 0
    ) -> bool:
        try:
            self.lookup(target_frame, source_frame, stamp_ns, tolerance_ns=tolerance_ns)
        except TransformLookupError:
            return False
        return True

    def _lookup(
        self, target: str, source: str, stamps: NDArray[np.int64], tolerance_ns: int
    ) -> tuple[FloatArray, FloatArray, bool]:
        known = self.frames
        for frame in (target, source):
            if frame not in known:
                raise TransformLookupError(
                    f"unknown frame {frame!r} (frames: {', '.join(sorted(known)) or 'none'})"
                )
        source_chain = self._chain(source)
        target_chain = self._chain(target)
        in_target = set(target_chain)
        ancestor = next((frame for frame in source_chain if frame in in_target), None)
        if ancestor is None:
            raise TransformLookupError(f"frames {source!r} and {target!r} are not connected")
        t_source, q_source, static_source = self._to_ancestor(source_chain, ancestor, stamps, tolerance_ns)
        t_target, q_target, static_target = self._to_ancestor(target_chain, ancestor, stamps, tolerance_ns)
        # target←source = (ancestor←target)⁻¹ ∘ (ancestor←source)
        inverse_q = rotations.conjugate(q_target)
        translation = rotations.rotate(inverse_q, t_source - t_target)
        rotation = rotations.multiply(inverse_q, q_source)
        return translation, rotation, static_source and static_target
