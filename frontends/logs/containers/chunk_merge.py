"""Log-time order across chunks, loading a chunk only when its messages are due.

MCAP files and ROS 1 bags store messages in compressed chunks whose time ranges may overlap (one chunk per
topic is common). Reading them in log-time order with bounded memory: sort the chunks by their first
message time, keep a heap of the loaded chunks keyed by their next message, and load the next chunk only
once the earliest pending message is not earlier than that chunk's start. Memory is the set of chunks that
overlap in time, not the log.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

# A loaded message: (log_time_ns, channel_id, payload); chunks return them sorted by log time.
ChunkMessage = tuple[int, int, Any]


class Unpacked(NamedTuple):
    """The complete records at the start of a (possibly cut-off) run of chunk records."""

    messages: list[ChunkMessage]  # of the wanted channels
    consumed: int  # bytes of complete records
    message_count: int  # message records of every channel
    message_bytes: int  # their total size


def lost_in_cut_chunk(declared_size: int, unpacked: Unpacked) -> int:
    """Messages estimated lost in a cut-off chunk: its missing bytes over the mean size of its messages
    that were read (0 when none was)."""
    if not unpacked.message_count:
        return 0
    mean = unpacked.message_bytes / unpacked.message_count
    return math.ceil(max(0, declared_size - unpacked.consumed) / mean)


@dataclass(frozen=True, slots=True)
class ChunkRef:
    """An unloaded chunk: its message time range, its file order, and how to load its messages."""

    start_ns: int
    end_ns: int
    order: int
    load: Callable[[], list[ChunkMessage]]


def merge_chunks(chunks: Sequence[ChunkRef]) -> Iterator[ChunkMessage]:
    """Messages of all chunks in log-time order (ties: earlier chunk in the file first, then stored order)."""
    pending = sorted(chunks, key=lambda c: (c.start_ns, c.order))
    next_pending = 0
    # Heap entries: (next message time, chunk order, messages, index of the next message).
    heap: list[tuple[int, int, list[ChunkMessage], int]] = []

    def load(chunk: ChunkRef) -> None:
        messages = chunk.load()
        if messages:
            heapq.heappush(heap, (messages[0][0], chunk.order, messages, 0))

    while heap or next_pending < len(pending):
        if not heap:
            load(pending[next_pending])
            next_pending += 1
            continue
        while next_pending < len(pending) and pending[next_pending].start_ns <= heap[0][0]:
            load(pending[next_pending])
            next_pending += 1
        if not heap:
            continue
        _, order, messages, index = heap[0]
        if len(heap) == 1:
            # One chunk in play: stream it directly up to where the next chunk could interleave.
            limit = pending[next_pending].start_ns if next_pending < len(pending) else None
            end = len(messages)
            while index < end and (limit is None or messages[index][0] < limit):
                yield messages[index]
                index += 1
        else:
            yield messages[index]
            index += 1
        if index < len(messages):
            heapq.heapreplace(heap, (messages[index][0], order, messages, index))
        else:
            heapq.heappop(heap)
