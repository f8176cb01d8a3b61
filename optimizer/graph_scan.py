"""The fast path of reading a graph file: one compiled pass over the raw bytes groups the lines by tag.

It handles the files that need no explanation: ASCII text whose pose-graph lines hold exactly the
expected number of plain decimal numbers. Anything else (non-ASCII or control bytes, a malformed number,
a wrong count, `nan`/`inf` spelled out) makes it give up, and `graph_files` reads the file again with its
line-by-line reader, which names what is wrong and where. So the fast path never has to explain errors.

The numbers are converted by Arrow's string-to-float cast (correctly rounded, like Python's `float`):
the scanner copies every token into one buffer with its offsets, which is an Arrow string array as it
stands.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import accumulate

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numba import config as numba_config
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_SPACE, _TAB, _CR, _NEWLINE, _HASH = 32, 9, 13, 10, 35
_PLUS, _MINUS, _DOT, _LOWER_E, _UPPER_E, _ZERO, _NINE = 43, 45, 46, 101, 69, 48, 57
_UTF8_BOM = b"\xef\xbb\xbf"


@dataclass(frozen=True)
class ScannedTag:
    """The lines of one graph tag: their 1-based line numbers and their values, (rows, fields)."""

    lines: IntArray
    values: FloatArray


@dataclass(frozen=True)
class ScannedFile:
    """What the fast path found: the graph tags' lines, and how many lines each other tag has (blank lines
    and comments excluded), in the order of their first lines."""

    tags: dict[str, ScannedTag]
    other_tags: dict[str, int]


def scan_graph_bytes(data: bytes, tags: tuple[str, ...], fields: tuple[int, ...]) -> ScannedFile | None:
    """Group the lines of `data` by tag, parsing the lines of `tags` (each with `fields` numbers after
    the tag); None when the file is not plain enough for the fast path.

    A large file is cut at line ends into one piece per thread of numba's (`NUMBA_NUM_THREADS`), and the
    pieces are scanned and converted side by side: the scanner and Arrow's cast both let go of the GIL."""
    raw = np.frombuffer(data, dtype=np.uint8)
    start = len(_UTF8_BOM) if data.startswith(_UTF8_BOM) else 0
    tag_bytes = np.frombuffer("".join(tags).encode("ascii"), dtype=np.uint8)
    tag_bounds = np.concatenate([[0], np.cumsum([len(tag) for tag in tags])]).astype(np.int64)
    expected = np.asarray(fields, dtype=np.int64)

    # The configured count, read without starting numba's thread pool (a log replay never starts it).
    bounds = _piece_bounds(data, start, numba_config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
    # Every piece but the last ends with a line end, so its line ends count its lines.
    line_ends = [data.count(b"\n", first, stop) for first, stop in bounds]
    lines_before = [0, *accumulate(line_ends[:-1])]

    def scan(piece: int) -> _Piece | None:
        return _scan_piece(raw, bounds[piece], line_ends[piece] + 1, lines_before[piece], tag_bytes,
                           tag_bounds, expected)

    if len(bounds) == 1:
        pieces = [scan(0)]
    else:
        with ThreadPoolExecutor(max_workers=len(bounds)) as pool:
            pieces = list(pool.map(scan, range(len(bounds))))
    if any(piece is None for piece in pieces):
        return None
    scanned_pieces = [piece for piece in pieces if piece is not None]

    scanned: dict[str, ScannedTag] = {}
    for index, tag in enumerate(tags):
        parts = [piece.tag_rows(index, fields[index]) for piece in scanned_pieces]
        if len(parts) == 1:
            scanned[tag] = ScannedTag(*parts[0])
        else:
            scanned[tag] = ScannedTag(np.concatenate([lines for lines, _ in parts]),
                                      np.concatenate([values for _, values in parts]))
    return ScannedFile(scanned, _other_tag_counts(raw, scanned_pieces, len(tags)))


def _other_tag_counts(raw: NDArray[np.uint8], pieces: list[_Piece], others: int) -> dict[str, int]:
    """Tag → lines of the tags that are not the graph's, in the order of their first lines: the scanner
    counts them per distinct tag (one Python string a line took 60 times a file of short unknown lines)."""
    counted: dict[str, int] = {}
    for piece in pieces:
        for k in range(int(piece.counts[others, 0])):
            tag = bytes(raw[piece.other_tags[0, k]:piece.other_tags[1, k]]).decode("ascii")
            counted[tag] = counted.get(tag, 0) + int(piece.other_tags[2, k])
    return counted


MAX_OTHER_TAGS = 256
"""Distinct tags other than the graph's that the fast path counts; a file with more goes to the
line-by-line reader."""


@dataclass(frozen=True)
class _Piece:
    """What the scanner found in one piece of the file: counts, line numbers within the piece, first
    tokens and spans of other tags (in the file) as `_scan` lays them out, every token's value, and the
    number of lines before the piece."""

    counts: IntArray
    lines: IntArray
    first_tokens: IntArray
    other_tags: IntArray
    """(3, `MAX_OTHER_TAGS`): each distinct other tag's first span (start, stop, in the file) and lines."""
    values: FloatArray
    lines_before: int

    def line_numbers(self, tag: int) -> IntArray:
        """The file's line numbers of tag `tag`'s lines in this piece."""
        return self.lines[tag, :self.counts[tag, 0]] + self.lines_before

    def tag_rows(self, tag: int, fields: int) -> tuple[IntArray, FloatArray]:
        """The file's line numbers and the values, (rows, fields), of tag `tag`'s lines in this piece."""
        rows = int(self.counts[tag, 0])
        first = self.first_tokens[tag, :rows]
        if rows and first[-1] - first[0] == (rows - 1) * fields:  # one run of lines: a view
            values = self.values[first[0]:first[0] + rows * fields].reshape(rows, fields)
        else:
            values = self.values[first[:, None] + np.arange(fields)]
        return self.line_numbers(tag), values


PIECE_MIN_BYTES = 8 << 20
"""Files below this are scanned whole: splitting them would save less than starting the threads costs."""


def _piece_bounds(data: bytes, start: int, count: int) -> list[tuple[int, int]]:
    """Up to `count` byte ranges covering `data` from `start`, each ending just after a line end (the last
    at the end of the file), none smaller than `PIECE_MIN_BYTES`."""
    count = max(1, min(count, (len(data) - start) // PIECE_MIN_BYTES))
    bounds: list[tuple[int, int]] = []
    first = start
    for k in range(1, count):
        cut = data.find(b"\n", max(first, start + (len(data) - start) * k // count)) + 1
        if cut <= first:
            break
        bounds.append((first, cut))
        first = cut
    bounds.append((first, len(data)))
    return bounds


def _scan_piece(raw: NDArray[np.uint8], bounds: tuple[int, int], line_bound: int, lines_before: int,
                tag_bytes: NDArray[np.uint8], tag_bounds: IntArray, expected: IntArray) -> _Piece | None:
    """Scan `raw[bounds[0]:bounds[1]]` (whole lines, after any byte-order mark; at most `line_bound` of
    them, `lines_before` lines before them in the file) and convert its tokens; None when it is not
    plain."""
    first, stop = bounds
    piece = raw[first:stop]
    num_tags = len(expected)
    # Upper bounds: untouched pages of np.empty are never made resident, so only what is used costs memory.
    counts = np.zeros((num_tags + 1, 2), dtype=np.int64)  # rows, tokens of each tag; last: distinct others
    lines = np.empty((num_tags, line_bound), dtype=np.int64)
    first_tokens = np.empty((num_tags, line_bound), dtype=np.int64)
    other_tags = np.zeros((3, MAX_OTHER_TAGS), dtype=np.int64)
    token_bytes = np.empty(len(piece), dtype=np.uint8)
    wide = len(piece) >= 2**31
    offsets = np.empty(len(piece) // 2 + 2, dtype=np.int64 if wide else np.int32)
    token_count = _scan(piece, tag_bytes, tag_bounds, expected, counts, lines, first_tokens, other_tags,
                        token_bytes, offsets)
    if token_count < 0:
        return None
    strings = pa.Array.from_buffers(
        pa.large_string() if wide else pa.string(), token_count,
        [None, pa.py_buffer(offsets[:token_count + 1]), pa.py_buffer(token_bytes[:offsets[token_count]])])
    del token_bytes, offsets
    values = pc.cast(strings, pa.float64()).to_numpy(zero_copy_only=False)  # every token, in piece order
    other_tags[:2] += first
    return _Piece(counts, lines, first_tokens, other_tags, values, lines_before)


@njit(cache=True, inline="always")
def _is_digit(byte: int) -> bool:
    return _ZERO <= byte <= _NINE


@njit(cache=True, inline="always")
def _number_end(raw: np.ndarray, first: int, stop: int) -> int:
    """End of the decimal number starting at `first` ([+-] digits [. digits] [e [+-] digits], at least
    one mantissa digit), or -1 when the token there is not one."""
    k = first
    if raw[k] == _PLUS or raw[k] == _MINUS:
        k += 1
    digits = 0
    while k < stop and _is_digit(raw[k]):
        k += 1
        digits += 1
    if k < stop and raw[k] == _DOT:
        k += 1
        while k < stop and _is_digit(raw[k]):
            k += 1
            digits += 1
    if digits == 0:
        return -1
    if k < stop and (raw[k] == _LOWER_E or raw[k] == _UPPER_E):
        k += 1
        if k < stop and (raw[k] == _PLUS or raw[k] == _MINUS):
            k += 1
        exponent_digits = 0
        while k < stop and _is_digit(raw[k]):
            k += 1
            exponent_digits += 1
        if exponent_digits == 0:
            return -1
    if k < stop and raw[k] != _SPACE and raw[k] != _TAB:
        return -1
    return k


@njit(cache=True, inline="always")
def _count_other_tag(raw: np.ndarray, first: int, stop: int, other_tags: np.ndarray,
                     distinct: np.ndarray) -> bool:
    """Count one line of the tag `raw[first:stop]` in `other_tags` (its first span and its lines, a column
    per distinct tag; `distinct[0, 0]` of them); False when the table is full."""
    length = stop - first
    for k in range(distinct[0, 0]):
        start = other_tags[0, k]
        if other_tags[1, k] - start == length:
            same = True
            for c in range(length):
                if raw[start + c] != raw[first + c]:
                    same = False
                    break
            if same:
                other_tags[2, k] += 1
                return True
    k = distinct[0, 0]
    if k == other_tags.shape[1]:
        return False
    other_tags[0, k], other_tags[1, k], other_tags[2, k] = first, stop, 1
    distinct[0, 0] = k + 1
    return True


@njit(cache=True, nogil=True)
def _scan(raw: np.ndarray, tag_bytes: np.ndarray, tag_bounds: np.ndarray, expected: np.ndarray,
          counts: np.ndarray, lines: np.ndarray, first_tokens: np.ndarray, other_tags: np.ndarray,
          token_bytes: np.ndarray, offsets: np.ndarray) -> int:
    """One pass over the file (or whole lines of it); -1 as soon as a line is not plain, else the number
    of tokens. Per tag t (row t of `counts`, `lines`, `first_tokens`) it counts rows and writes their line
    numbers and first tokens; every token goes to `token_bytes`, end to end, with its end in `offsets` (an
    Arrow string array's layout). Other tags are counted in `other_tags` (`_count_other_tag`; how many
    distinct ones in the last row of `counts`)."""
    num_tags = expected.shape[0]
    token_count = 0
    offsets[0] = 0
    size = raw.shape[0]
    position = 0
    line = 0
    while position < size:
        line += 1
        end = position
        while end < size and raw[end] != _NEWLINE:
            byte = raw[end]
            if (byte < _SPACE and byte != _TAB and byte != _CR) or byte >= 127:
                return -1  # control or non-ASCII bytes: the line-by-line reader decides
            end += 1
        stop = end
        if stop > position and raw[stop - 1] == _CR:
            stop -= 1
        next_position = end + 1
        i = position
        while i < stop and (raw[i] == _SPACE or raw[i] == _TAB):
            i += 1
        if i == stop or raw[i] == _HASH:
            position = next_position
            continue
        tag_first = i
        while i < stop and raw[i] != _SPACE and raw[i] != _TAB:
            if raw[i] == _CR:
                return -1  # a carriage return inside a line
            i += 1
        tag = -1
        for t in range(num_tags):
            length = tag_bounds[t + 1] - tag_bounds[t]
            if length == i - tag_first:
                same = True
                for c in range(length):
                    if raw[tag_first + c] != tag_bytes[tag_bounds[t] + c]:
                        same = False
                        break
                if same:
                    tag = t
                    break
        if tag < 0:
            if not _count_other_tag(raw, tag_first, i, other_tags, counts[num_tags:]):
                return -1  # more distinct tags than the table holds
            position = next_position
            continue
        tokens = 0
        first_tokens[tag, counts[tag, 0]] = token_count
        while True:
            while i < stop and (raw[i] == _SPACE or raw[i] == _TAB):
                i += 1
            if i == stop:
                break
            if tokens == expected[tag]:
                return -1  # more numbers than the tag holds: at once, not after the whole line
            token_end = _number_end(raw, i, stop)
            if token_end < 0:
                return -1
            used = offsets[token_count]
            for c in range(token_end - i):
                token_bytes[used + c] = raw[i + c]
            offsets[token_count + 1] = used + token_end - i
            token_count += 1
            counts[tag, 1] += 1
            tokens += 1
            i = token_end
        if tokens != expected[tag]:
            return -1
        lines[tag, counts[tag, 0]] = line
        counts[tag, 0] += 1
        position = next_position
    return token_count
