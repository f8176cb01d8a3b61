"""Reading and writing 2D pose-graph files: g2o (`VERTEX_SE2`/`EDGE_SE2`) and TORO (`VERTEX2`/`EDGE2`).

The format is told by the tags inside the file, never by its extension. Plain files (the usual case) are
grouped by tag and parsed by the compiled scanner of `graph_scan`, without a Python object per line;
anything it does not accept is read again line by line in Python, with every group converted to floats
in bulk by numpy, and per-line work happens only to explain an error once one is known to exist.

Information matrices are stored as their upper triangle, in a different order per format:
g2o `I11 I12 I13 I22 I23 I33` (xx xy xθ yy yθ θθ), TORO `xx xy yy θθ xθ yθ`.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv
from numba import config as numba_config
from numpy.typing import NDArray

from optimizer import se2
from optimizer.errors import GraphError, GraphFileError
from optimizer.file_input import read_bytes_bounded
from optimizer.graph import SPD_TOLERANCE, PoseGraph, not_positive_definite

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

REPAIR_EIGENVALUE_FLOOR = 1e-6
"""`repair_information=True` raises every eigenvalue of a bad information matrix to this fraction of
its largest eigenvalue (a direction the file gives no information about becomes very uncertain)."""


_LARGEST_EXACT_ID = 2**53  # ids go through float64 parsing; beyond this they would not be exact

_VERTEX_FIELDS = 4  # id x y θ
_EDGE_FIELDS = 11  # a b dx dy dθ + six information entries

# (vertex tag, edge tag, permutation taking the file's information order to g2o's order)
_FORMATS: dict[str, tuple[str, str, tuple[int, ...]]] = {
    "g2o": ("VERTEX_SE2", "EDGE_SE2", (0, 1, 2, 3, 4, 5)),
    # TORO: xx xy yy θθ xθ yθ → g2o: xx xy xθ yy yθ θθ
    "toro": ("VERTEX2", "EDGE2", (0, 1, 4, 2, 5, 3)),
}
_GRAPH_TAGS = {tag: (name, tag == tags[0]) for name, tags in _FORMATS.items() for tag in tags[:2]}
_3D_TAGS = ("VERTEX3", "EDGE3")
_3D_TAG_PREFIXES = ("VERTEX_SE3", "EDGE_SE3")


def is_graph_tag(word: str) -> bool:
    """Whether a line starting with `word` is a pose-graph line: a 2D g2o or TORO vertex or edge, or a 3D
    one (which `read_graph` refuses by name)."""
    return word in _GRAPH_TAGS or word in _3D_TAGS or word.startswith(_3D_TAG_PREFIXES)


# Row, column of each g2o upper-triangle slot (xx xy xθ yy yθ θθ) in the 3×3 matrix.
_UPPER_ROWS = np.array([0, 0, 0, 1, 1, 2])
_UPPER_COLS = np.array([0, 1, 2, 1, 2, 2])

WRITE_CHUNK_ROWS = 1 << 16
"""Lines formatted at once when writing: some 7 MB of edge lines, so a few held at once cost little."""


@dataclass(frozen=True, eq=False)
class GraphFile:
    """A pose graph read from a file, with what the reader had to do to get it."""

    graph: PoseGraph
    path: Path
    format: str
    """"g2o" or "toro"."""
    skipped: dict[str, int]
    """Tag → number of lines with that tag that were skipped (not 2D pose-graph lines)."""
    initialised_from_odometry: bool
    """True when some (or all) poses had no vertex line and were composed along the odometry chain."""
    repaired_lines: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """File lines (1-based) of the edges whose information was repaired (`repair_information=True`)."""


@dataclass(frozen=True)
class _Group:
    """The lines of one tag before conversion: their line numbers, and either their values (fast path)
    or the text after the tag of each (line-by-line path)."""

    lines: IntArray
    values: FloatArray | None
    texts: list[str]


@dataclass(frozen=True)
class _Block:
    """The lines of one tag: their 1-based line numbers and their fields after the tag, as floats."""

    lines: IntArray
    values: FloatArray


def read_graph(path: str | Path, *, repair_information: bool = False) -> GraphFile:
    """Read a 2D g2o or TORO pose graph.

    - unknown tags are skipped and counted; blank lines and `#` comments are ignored; 3D tags are errors;
    - poses without a vertex line are composed along the odometry chain (the constraints between
      consecutive ids, in increasing id order) from the nearest pose that has one, or from the origin
      when the file has no vertex lines at all;
    - information that is not symmetric positive definite is an error, unless `repair_information`, in
      which case its eigenvalues are raised to `REPAIR_EIGENVALUE_FLOOR` × its largest eigenvalue (the
      formats store only the upper triangle, so the matrices are symmetric by construction).

    Every problem is raised as a GraphFileError naming the file, and the line when one is at fault.
    """
    path = Path(path)
    data = _read_bytes(path)
    blocks, skipped, format_name = _scan(path, data)
    vertex_tag, edge_tag, information_order = _FORMATS[format_name]
    vertices, edges = blocks[vertex_tag], blocks[edge_tag]

    vertex_ids = _ids(path, vertices, 1)
    edge_ids = _ids(path, edges, 2)
    _check_unique_vertices(path, vertex_ids, vertices.lines)
    _check_no_self_loops(path, edge_ids, edges.lines)

    measurements = edges.values[:, 2:5]
    information = _information_from_upper(edges.values[:, 5:11][:, information_order])
    information, repaired = _check_information(path, information, edges.lines, repair_information)

    all_ids, all_poses, initialised = _complete_poses(path, vertex_ids, vertices.values[:, 1:4], edge_ids,
                                                      measurements, edges.lines)
    try:
        graph = PoseGraph.build(all_ids, all_poses, edge_ids[:, 0], edge_ids[:, 1], measurements, information,
                                check_information=False)  # just checked, with the file's line numbers
    except GraphError as error:
        raise GraphFileError(path, str(error)) from error
    if _FIX in skipped:  # held as the file says: the optimizer holds the first pose, and only that one
        _check_fixed(path, data, int(graph.vertex_ids[0]))
        skipped = {tag: count for tag, count in skipped.items() if tag != _FIX}
    return GraphFile(graph, path, format_name, skipped, initialised, repaired)


_FIX = "FIX"
_FIX_LINE = re.compile(rb"^[ \t]*FIX(?:[ \t]+([^\r\n#]*))?", re.MULTILINE)


def _check_fixed(path: Path, data: bytes, first_id: int) -> None:
    """Raise `GraphFileError` at the first FIX line that holds another pose than the graph's first: the
    optimizer anchors that one alone, and would move the others, solving another problem than the file's."""
    for match in _FIX_LINE.finditer(data):
        tokens = (match.group(1) or b"").split()
        if tokens != [str(first_id).encode()] * len(tokens) or not tokens:
            raise GraphFileError(path, f"FIX {b' '.join(tokens).decode(errors='replace')}: only the graph's "
                                       f"first pose (id {first_id}) is held fixed here, which the optimizer "
                                       "anchors; other fixed poses are not supported",
                                 line=data.count(b"\n", 0, match.start()) + 1)


def write_g2o(path: str | Path, graph: PoseGraph, poses: FloatArray | None = None) -> None:
    """Write `graph` (around `poses`, default its own estimate) as g2o 2D, at full precision."""
    _write(Path(path), graph, poses, "g2o")


def write_toro(path: str | Path, graph: PoseGraph, poses: FloatArray | None = None) -> None:
    """Write `graph` (around `poses`, default its own estimate) as TORO 2D, at full precision."""
    _write(Path(path), graph, poses, "toro")


# --------------------------------------------------------------------------------------------- reading


MAX_GRAPH_LINE_CHARS = 4096
"""Longest pose-graph line read: 11 numbers at full precision take under 300 characters."""
MAX_GRAPH_FILE_BYTES = 4 << 30
"""Largest graph file read: a 10⁶-pose, 2·10⁶-constraint g2o file is 190 MB, so some 20 times that."""


def _read_bytes(path: Path) -> bytes:
    try:
        data = read_bytes_bounded(path, MAX_GRAPH_FILE_BYTES)
    except FileNotFoundError as error:
        raise GraphFileError(path, "no such file") from error
    except IsADirectoryError as error:
        raise GraphFileError(path, "is a directory, not a graph file") from error
    except OSError as error:
        raise GraphFileError(path, f"cannot read the file: {error.strerror or error}") from error
    if not data or data.isspace():  # isspace: no copy of a possibly large file
        raise GraphFileError(path, "the file is empty")
    nul = data.find(b"\x00")
    if nul >= 0:
        raise GraphFileError(path, "binary data (NUL byte), not a text graph file",
                             line=data.count(b"\n", 0, nul) + 1)
    return data


def _decode(path: Path, data: bytes) -> str:
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise GraphFileError(path, "not UTF-8 text (a binary file?)",
                             line=data.count(b"\n", 0, error.start) + 1) from error


def _scan(path: Path, data: bytes) -> tuple[dict[str, _Block], dict[str, int], str]:
    """Group the lines by tag, count the skipped ones and tell the format. The result holds a block for
    both graph tags of the format (an empty one when the file has no such line)."""
    grouped = _group_plain(data)
    if grouped is None:
        _refuse_long_graph_lines(path, data)
    groups, skipped = grouped if grouped is not None else _group_lines(path, _decode(path, data))

    first_line = {name: min((int(groups[tag].lines[0]) for tag in tags[:2] if len(groups[tag].lines)),
                            default=None)
                  for name, tags in _FORMATS.items()}
    present = {name: first for name, first in first_line.items() if first is not None}
    if not present:
        found = f" (only {', '.join(sorted(skipped))} lines)" if skipped else ""
        raise GraphFileError(path, "no pose-graph lines: expected VERTEX_SE2/EDGE_SE2 (g2o) or "
                                   f"VERTEX2/EDGE2 (TORO){found}")
    if len(present) > 1:
        later = max(present, key=lambda name: present[name])
        raise GraphFileError(path, "the file mixes g2o (VERTEX_SE2/EDGE_SE2) and TORO (VERTEX2/EDGE2) lines",
                             line=present[later])
    format_name = next(iter(present))

    blocks: dict[str, _Block] = {}
    problems: list[tuple[int, str]] = []
    for tag in _FORMATS[format_name][:2]:
        expected = _VERTEX_FIELDS if _GRAPH_TAGS[tag][1] else _EDGE_FIELDS
        group = groups[tag]
        if not len(group.lines):
            blocks[tag] = _Block(np.zeros(0, dtype=np.int64), np.zeros((0, expected)))
            continue
        values = group.values
        if values is None:
            values, problem = _parse_block(tag, group.texts, expected)
            if problem is not None:
                problems.append((int(group.lines[problem[0]]), problem[1]))
                continue
        finite = np.isfinite(values).all(axis=1)
        if not finite.all():
            problems.append((int(group.lines[np.argmin(finite)]),
                             f"non-finite value (nan or inf) in a {tag} line"))
            continue
        blocks[tag] = _Block(group.lines, values)
    if problems:
        line, message = min(problems)
        raise GraphFileError(path, message, line=line)
    return blocks, skipped, format_name


def _group_plain(data: bytes) -> tuple[dict[str, _Group], dict[str, int]] | None:
    """The compiled fast path; None when the file needs the line-by-line reader (which explains errors)."""
    # Imported by the first read: its pyarrow.compute costs a replay of a log 0.1 s of start-up to write a
    # graph it never reads.
    from optimizer.graph_scan import scan_graph_bytes

    tags = tuple(_GRAPH_TAGS)
    scanned = scan_graph_bytes(data, tags, tuple(_VERTEX_FIELDS if _GRAPH_TAGS[tag][1] else _EDGE_FIELDS
                                                 for tag in tags))
    if scanned is None:
        return None
    if any(tag in _3D_TAGS or tag.startswith(_3D_TAG_PREFIXES) for tag in scanned.other_tags):
        return None  # an error, which the line-by-line reader names with its line
    return ({tag: _Group(group.lines, group.values, []) for tag, group in scanned.tags.items()},
            dict(scanned.other_tags))


def _refuse_long_graph_lines(path: Path, data: bytes) -> None:
    """Raise `GraphFileError` at the first pose-graph line longer than `MAX_GRAPH_LINE_CHARS`, before the
    line-by-line reader copies and splits it (a 50 MB line took 1.5 GB; a line may be as long as the file)."""
    ends = np.flatnonzero(np.frombuffer(data, dtype=np.uint8) == ord("\n"))
    starts = np.concatenate([[0], ends + 1])
    lengths = np.append(ends, len(data)) - starts
    for line in np.flatnonzero(lengths > MAX_GRAPH_LINE_CHARS).tolist():
        tag = data[starts[line]:starts[line] + 64].split(maxsplit=1)[:1]
        if tag and tag[0].decode(errors="replace") in _GRAPH_TAGS:
            raise GraphFileError(path, f"{tag[0].decode()} line of {int(lengths[line])} bytes; a pose-graph "
                                       f"line holds at most {_EDGE_FIELDS} numbers", line=line + 1)


def _group_lines(path: Path, text: str) -> tuple[dict[str, _Group], dict[str, int]]:
    """Group the lines by tag in one Python pass (one string kept per line), counting the skipped ones."""
    line_numbers: dict[str, list[int]] = {tag: [] for tag in _GRAPH_TAGS}
    fields: dict[str, list[str]] = {tag: [] for tag in _GRAPH_TAGS}
    skipped: dict[str, int] = {}
    for number, raw in enumerate(text.split("\n"), start=1):
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        parts = line.split(None, 1)
        tag = parts[0]
        if tag in _GRAPH_TAGS:
            if len(parts) == 1:
                raise GraphFileError(path, f"{tag} line without values", line=number)
            line_numbers[tag].append(number)
            fields[tag].append(parts[1])
        elif tag in _3D_TAGS or tag.startswith(_3D_TAG_PREFIXES):
            raise GraphFileError(path, f"3D pose graphs are not supported ({tag}); only 2D g2o and TORO",
                                 line=number)
        else:
            skipped[tag] = skipped.get(tag, 0) + 1
    groups = {tag: _Group(np.asarray(line_numbers[tag], dtype=np.int64), None, fields[tag])
              for tag in _GRAPH_TAGS}
    return groups, skipped


def _parse_block(tag: str, texts: list[str], expected: int) -> tuple[FloatArray, tuple[int, str] | None]:
    """Convert the fields of all lines of one tag at once; on failure, (row, what is wrong) of the first
    bad line."""

    def parse(chunk: Sequence[str]) -> FloatArray | None:
        try:
            values = np.loadtxt(chunk, dtype=np.float64, comments=None, ndmin=2)
        except ValueError:
            return None
        return values if values.shape == (len(chunk), expected) else None

    values = parse(texts)
    if values is not None:
        return values, None
    # Bisect for the first bad row: each step parses half of the remaining range in bulk.
    low, high = 0, len(texts)  # texts[:low] parse; texts[low:high] holds a bad row
    while high - low > 1:
        middle = (low + high) // 2
        if parse(texts[low:middle]) is None:
            high = middle
        else:
            low = middle
    return np.zeros((0, expected)), (low, _describe_bad_fields(tag, texts[low], expected))


def _describe_bad_fields(tag: str, text: str, expected: int) -> str:
    tokens = text.split()
    if len(tokens) != expected:
        return f"{tag} needs {expected} values after the tag, found {len(tokens)}"
    for token in tokens:
        try:
            float(token)
        except ValueError:
            return f"{token!r} is not a number"
    return f"cannot read the numbers of this {tag} line"


def _ids(path: Path, block: _Block, count: int) -> IntArray:
    """The first `count` columns of a block as integer ids."""
    raw = block.values[:, :count]
    # Strictly below: 2^53 + 1 reads as 2^53, which would pass for another id unnoticed.
    integral = (raw == np.round(raw)) & (np.abs(raw) < _LARGEST_EXACT_ID)
    rows_ok = integral.all(axis=1)
    if not rows_ok.all():
        row = int(np.argmin(rows_ok))
        raise GraphFileError(path, f"ids must be integers (below 2^53), got {raw[row].tolist()}",
                             line=int(block.lines[row]))
    ids = raw.astype(np.int64)
    return ids[:, 0] if count == 1 else ids


def _check_unique_vertices(path: Path, vertex_ids: IntArray, lines: IntArray) -> None:
    order = np.argsort(vertex_ids, kind="stable")
    repeated = np.flatnonzero(vertex_ids[order][1:] == vertex_ids[order][:-1])
    if len(repeated):
        # the repeat that appears earliest in the file, and the first definition of its id
        repeats = order[repeated + 1]
        row = int(repeats[np.argmin(lines[repeats])])
        first = int(lines[np.flatnonzero(vertex_ids == vertex_ids[row])[0]])
        raise GraphFileError(path, f"vertex {int(vertex_ids[row])} is defined again (first on line {first})",
                             line=int(lines[row]))


def _check_no_self_loops(path: Path, edge_ids: IntArray, lines: IntArray) -> None:
    loops = edge_ids[:, 0] == edge_ids[:, 1]
    if loops.any():
        row = int(np.argmax(loops))
        raise GraphFileError(path, f"the edge joins pose {int(edge_ids[row, 0])} to itself",
                             line=int(lines[row]))


def _information_from_upper(upper: FloatArray) -> FloatArray:
    """(M, 3, 3) symmetric matrices from (M, 6) upper triangles in g2o order."""
    information = np.empty((len(upper), 3, 3))
    information[:, _UPPER_ROWS, _UPPER_COLS] = upper
    information[:, _UPPER_COLS, _UPPER_ROWS] = upper
    return information


def _clearly_positive_definite(information: FloatArray) -> NDArray[np.bool_]:
    """Mask of the symmetric matrices that Gershgorin's discs alone show to pass `not_positive_definite`:
    every eigenvalue lies in [min(a_ii − r_i), max(a_ii + r_i)], r_i = Σ_{j≠i} |a_ij|. It spares the
    eigenvalue computation of the (usual) diagonally dominant information matrices of big graphs."""
    xy, xt, yt = (np.abs(information[:, row, column]) for row, column in ((0, 1), (0, 2), (1, 2)))
    discs = ((information[:, 0, 0], xy + xt), (information[:, 1, 1], xy + yt),
             (information[:, 2, 2], xt + yt))
    lowest = np.minimum.reduce([centre - radius for centre, radius in discs])
    highest = np.maximum.reduce([centre + radius for centre, radius in discs])
    return lowest > 2.0 * SPD_TOLERANCE * highest  # twice: a margin for the rounding of these sums


def _check_information(path: Path, information: FloatArray, lines: IntArray,
                       repair: bool) -> tuple[FloatArray, IntArray]:
    """Reject (or, with `repair`, fix) information matrices that are not positive definite."""
    if len(information) == 0:
        return information, np.zeros(0, dtype=np.int64)
    bad = np.zeros(len(information), dtype=bool)
    uncertain = np.flatnonzero(~_clearly_positive_definite(information))
    bad[uncertain] = not_positive_definite(information[uncertain])
    if not bad.any():
        return information, np.zeros(0, dtype=np.int64)
    first = int(np.argmax(bad))
    eigenvalues = np.linalg.eigvalsh(information[first:first + 1])
    if not repair:
        raise GraphFileError(
            path,
            "the edge's information matrix is not positive definite (eigenvalues "
            f"{', '.join(f'{value:.6g}' for value in eigenvalues[0])}); "
            "ask for it to be repaired (replay --repair-information) to clamp its eigenvalues",
            line=int(lines[first]),
        )
    values, vectors = np.linalg.eigh(information[bad])
    largest = values[:, 2]
    if not (largest > 0).all():
        row = int(np.flatnonzero(bad)[np.argmin(largest > 0)])
        raise GraphFileError(path, "the edge's information matrix has no positive eigenvalue: "
                                   "nothing to repair", line=int(lines[row]))
    clamped = np.maximum(values, REPAIR_EIGENVALUE_FLOOR * largest[:, None])
    repaired = np.einsum("mij,mj,mkj->mik", vectors, clamped, vectors)
    information = information.copy()
    information[bad] = 0.5 * (repaired + np.swapaxes(repaired, 1, 2))
    return information, lines[bad].copy()


def _complete_poses(path: Path, vertex_ids: IntArray, vertex_poses: FloatArray, edge_ids: IntArray,
                    measurements: FloatArray, edge_lines: IntArray) -> tuple[IntArray, FloatArray, bool]:
    """Poses for every id that a vertex or an edge names; ids without a vertex line are composed along
    the odometry chain. Returns the sorted ids, their poses and whether any pose was composed."""
    all_ids = np.sort(np.concatenate([vertex_ids, edge_ids.reshape(-1)]))
    all_ids = all_ids[np.concatenate([[True], all_ids[1:] != all_ids[:-1]])]  # np.unique is slower here
    known = np.isin(all_ids, vertex_ids)
    poses = np.zeros((len(all_ids), 3))
    if known.all():
        poses[np.searchsorted(all_ids, vertex_ids)] = vertex_poses
        return all_ids, poses, False
    if known.any():
        poses[np.searchsorted(all_ids, vertex_ids)] = vertex_poses
    else:
        known[0] = True  # no vertex lines at all: the first pose is the origin

    steps, has_step = _odometry_steps(all_ids, edge_ids, measurements)

    def unreachable(index: int, gap: int) -> GraphFileError:
        pose_id = int(all_ids[index])
        uses = np.flatnonzero((edge_ids == pose_id).any(axis=1))
        return GraphFileError(
            path,
            f"pose {pose_id} has no vertex line and cannot be reached along the odometry chain "
            f"(no edge between poses {int(all_ids[gap])} and {int(all_ids[gap + 1])})",
            line=int(edge_lines[uses[0]]) if len(uses) else None,
        )

    # Runs [start, stop) of consecutive unknown poses, composed from the known pose just before them
    # (or, for a run at the very beginning, backwards from the known pose just after).
    change = np.diff(np.concatenate([[0], (~known).astype(np.int8), [0]]))
    for start, stop in zip(np.flatnonzero(change == 1).tolist(), np.flatnonzero(change == -1).tolist(),
                           strict=True):
        if start > 0:
            missing = np.flatnonzero(~has_step[start - 1:stop - 1])
            if len(missing):
                gap = start - 1 + int(missing[0])
                raise unreachable(gap + 1, gap)
            poses[start:stop] = se2.compose_chain(steps[start - 1:stop - 1], start=poses[start - 1])[1:]
        else:
            missing = np.flatnonzero(~has_step[:stop])
            if len(missing):
                gap = int(missing[-1])
                raise unreachable(gap, gap)
            backwards = se2.inverse(steps[:stop][::-1])  # x_k = x_{k+1} · z_{k,k+1}⁻¹
            poses[:stop] = se2.compose_chain(backwards, start=poses[stop])[1:][::-1]
    return all_ids, poses, True


def _odometry_steps(all_ids: IntArray, edge_ids: IntArray,
                    measurements: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """For each k, the motion from pose k to pose k+1 (sorted-id order) given by the first edge in the
    file joining them (inverted when stored k+1 → k), and whether there is one."""
    index_from = np.searchsorted(all_ids, edge_ids[:, 0])
    index_to = np.searchsorted(all_ids, edge_ids[:, 1])
    forward = index_to - index_from == 1
    backward = index_from - index_to == 1
    candidates = np.flatnonzero(forward | backward)
    keys = np.minimum(index_from, index_to)[candidates]
    keys, first = np.unique(keys, return_index=True)  # first occurrence in file order
    chosen = candidates[first]
    step = measurements[chosen].copy()
    flip = backward[chosen]
    step[flip] = se2.inverse(step[flip])
    steps = np.zeros((max(len(all_ids) - 1, 0), 3))
    has_step = np.zeros(len(steps), dtype=bool)
    steps[keys] = step
    has_step[keys] = True
    return steps, has_step


# --------------------------------------------------------------------------------------------- writing


def _write(path: Path, graph: PoseGraph, poses: FloatArray | None, format_name: str) -> None:
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    if poses.shape != graph.poses.shape:
        raise GraphError(f"expected poses of shape {graph.poses.shape}, got {poses.shape}")
    vertex_tag, edge_tag, information_order = _FORMATS[format_name]
    # g2o slot k is file slot information_order.index(k) → invert the permutation to go g2o → file
    to_file = np.argsort(information_order)
    upper = graph.information[:, _UPPER_ROWS, _UPPER_COLS][:, to_file]
    vertices = _table(vertex_tag, [graph.vertex_ids], poses)
    edges = _table(edge_tag, [graph.vertex_ids[graph.edge_from], graph.vertex_ids[graph.edge_to]],
                   np.concatenate([graph.measurements, upper], axis=1))
    try:
        with path.open("wb") as file:
            _write_rows(file, [vertices, edges])
    except OSError as error:
        raise GraphFileError(path, f"cannot write the file: {error.strerror or error}") from error


def _write_rows(file: BinaryIO, tables: Sequence[pa.Table]) -> None:
    """Write the rows of `tables` in order, formatted `WRITE_CHUNK_ROWS` at a time on as many threads as
    numba's kernels use (`NUMBA_NUM_THREADS`): Arrow's CSV writer formats on one thread, and lets go of the
    GIL while it does. At most one chunk of text per thread is held at once."""
    options = pa_csv.WriteOptions(include_header=False, delimiter=" ", quoting_style="none")

    def formatted(rows: pa.Table) -> pa.Buffer:
        sink = pa.BufferOutputStream()
        pa_csv.write_csv(rows, sink, options)
        return sink.getvalue()

    chunks = (table.slice(start, WRITE_CHUNK_ROWS) for table in tables
              for start in range(0, table.num_rows, WRITE_CHUNK_ROWS))
    # Without starting numba's thread pool (numba's config module sets its attributes at import).
    workers = numba_config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]
    pending: deque[Future[pa.Buffer]] = deque()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for chunk in chunks:
            pending.append(pool.submit(formatted, chunk))
            if len(pending) > workers:
                file.write(pending.popleft().result())
        while pending:
            file.write(pending.popleft().result())


def _table(tag: str, ids: list[IntArray], values: FloatArray) -> pa.Table:
    """One row per file line: the tag, integer ids, then floats. Arrow's CSV writer prints each float in its
    shortest form that reads back to the same float64 (exact round trip), in compiled code: Python's
    per-line formatting took a minute for a 10⁶-pose graph."""
    same_tag = pa.DictionaryArray.from_arrays(pa.array(np.zeros(len(values), dtype=np.int8)), pa.array([tag]))
    columns: dict[str, pa.Array] = {"tag": same_tag}
    for k, column in enumerate(ids):
        columns[f"id{k}"] = pa.array(np.asarray(column, dtype=np.int64))
    for k in range(values.shape[1]):
        columns[f"value{k}"] = pa.array(np.ascontiguousarray(values[:, k]))
    return pa.table(columns)
