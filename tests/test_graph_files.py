"""Reading and writing g2o / TORO 2D pose-graph files."""

from __future__ import annotations

import itertools
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from optimizer import se2
from optimizer.cost import edge_chi2
from optimizer.errors import GraphFileError
from optimizer.graph import PoseGraph
from optimizer.graph_files import REPAIR_EIGENVALUE_FLOOR, read_graph, write_g2o, write_toro
from tests.conftest import shared_file

# An SPD information matrix whose six upper-triangle entries all differ, to see every slot land right.
OMEGA = np.array([[100.0, 2.0, 3.0],
                  [2.0, 50.0, 5.0],
                  [3.0, 5.0, 20.0]])
G2O_UPPER = "100 2 3 50 5 20"  # xx xy xθ yy yθ θθ
TORO_UPPER = "100 2 50 20 3 5"  # xx xy yy θθ xθ yθ
DIAGONAL_123 = {G2O_UPPER: "1 0 0 2 0 3", TORO_UPPER: "1 0 2 3 0 0"}  # Ω = diag(1, 2, 3) in each order


def _write(tmp_path: Path, text: str, name: str = "graph.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _tiny(vertex: str, edge: str, upper: str) -> str:
    return f"""# a small graph with sparse ids
{vertex} 10 0 0 0
{vertex} 20 1 0 0.5

{vertex} 35 2 1 -0.25
FIX 10
   # an indented comment
{edge} 10 20 1 0 0.5 {upper}
{edge} 35 20 2 0 0 {DIAGONAL_123[upper]}
EQUIV 10 20
{edge} 10 35 2 1 -0.25 {upper}
ROBOTLASER1 0 -1.57 3.14 0.01 80 0.01 0 3 1.0 2.0 3.0 0 0 0 0 0 0 0 0 0 0 0 0 hostname 0.0
"""


@pytest.mark.parametrize(("vertex", "edge", "upper", "format_name"), [
    ("VERTEX_SE2", "EDGE_SE2", G2O_UPPER, "g2o"),
    ("VERTEX2", "EDGE2", TORO_UPPER, "toro"),
])
def test_tiny_file_is_parsed(tmp_path: Path, vertex: str, edge: str, upper: str, format_name: str) -> None:
    path = _write(tmp_path, _tiny(vertex, edge, upper), name="graph.txt")
    result = read_graph(path)
    graph = result.graph

    assert result.format == format_name
    assert result.path == path
    assert result.skipped == {"EQUIV": 1, "ROBOTLASER1": 1}  # FIX 10: the first pose, anchored: held
    assert not result.initialised_from_odometry
    np.testing.assert_array_equal(graph.vertex_ids, [10, 20, 35])
    np.testing.assert_allclose(graph.poses, [[0, 0, 0], [1, 0, 0.5], [2, 1, -0.25]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(graph.edge_from, [0, 2, 0])  # 35 → 20 stays as the file stores it
    np.testing.assert_array_equal(graph.edge_to, [1, 1, 2])
    np.testing.assert_allclose(graph.measurements[0], [1, 0, 0.5], rtol=0, atol=1e-15)
    np.testing.assert_allclose(graph.measurements[2], [2, 1, -0.25], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(graph.information[0], OMEGA)
    np.testing.assert_array_equal(graph.information[2], OMEGA)


def test_reversed_edge_is_kept_as_the_file_states_it(tmp_path: Path) -> None:
    # 35 → 20 measures pose 20 two metres ahead of pose 35, Ω = diag(1, 2, 3).
    graph = read_graph(_write(tmp_path, _tiny("VERTEX_SE2", "EDGE_SE2", G2O_UPPER))).graph
    assert (graph.edge_from[1], graph.edge_to[1]) == (2, 1)
    np.testing.assert_array_equal(graph.measurements[1], [2, 0, 0])
    np.testing.assert_array_equal(graph.information[1], np.diag([1.0, 2.0, 3.0]))


def test_reversed_edge_has_the_files_cost(tmp_path: Path) -> None:
    z = np.array([-1.5, 0.5, -0.2])
    x1 = np.array([1.0, 2.0, 0.3])
    x0 = se2.compose(x1, z).tolist()  # the file's edge is satisfied exactly
    text = (f"VERTEX_SE2 0 {x0[0]!r} {x0[1]!r} {x0[2]!r}\nVERTEX_SE2 1 1 2 0.3\n"
            f"EDGE_SE2 1 0 -1.5 0.5 -0.2 {G2O_UPPER}\n")
    graph = read_graph(_write(tmp_path, text)).graph
    poses = graph.poses + np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3]])  # far off: no linearisation
    error = se2.relative(z, se2.relative(poses[1], poses[0]))  # the file's direction: 1 → 0
    np.testing.assert_allclose(edge_chi2(graph, poses)[0], error @ OMEGA @ error, rtol=1e-12)


def test_written_file_repeats_the_input_edges_line_for_line(tmp_path: Path) -> None:
    # Reversed edges, θ outside [-π, π) and full-precision numbers come back exactly as the input wrote them.
    text = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n"
            "EDGE_SE2 1 0 -1.0000000000000002 0.125 4.0 7 0.5 0.25 9 0.125 11\n"
            "EDGE_SE2 1 2 1 0 -3.5 1 0 0 1 0 1\n"
            "EDGE_SE2 2 0 -2.25 0.1 0.3 100 0 0 0.01 0 50\n")
    graph = read_graph(_write(tmp_path, text)).graph
    write_g2o(tmp_path / "out.g2o", graph, graph.poses + 0.5)
    edges_in = [line.split() for line in text.splitlines() if line.startswith("EDGE")]
    edges_out = [line.split() for line in (tmp_path / "out.g2o").read_text().splitlines()
                 if line.startswith("EDGE")]
    assert [row[:3] for row in edges_out] == [row[:3] for row in edges_in]
    np.testing.assert_array_equal(np.array([row[3:] for row in edges_out], dtype=float),
                                  np.array([row[3:] for row in edges_in], dtype=float))


def test_no_vertex_lines_are_initialised_from_odometry(tmp_path: Path) -> None:
    text = ("EDGE_SE2 0 1 1 0 1.5707963267948966 1 0 0 1 0 1\n"
            "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n"
            "EDGE_SE2 0 2 9 9 0 1 0 0 1 0 1\n"  # a loop closure: not used to initialise
            "EDGE_SE2 3 2 -1 0 0 1 0 0 1 0 1\n")  # odometry stored backwards
    result = read_graph(_write(tmp_path, text))
    assert result.initialised_from_odometry
    # x1 = 1 m ahead then a left turn; x2 = 1 m ahead of x1 (north); x3 = 1 m further north.
    expected = [[0, 0, 0], [1, 0, np.pi / 2], [1, 1, np.pi / 2], [1, 2, np.pi / 2]]
    np.testing.assert_allclose(result.graph.poses, expected, atol=1e-12)


def test_missing_vertices_are_composed_from_their_neighbours(tmp_path: Path) -> None:
    text = ("VERTEX_SE2 1 5 5 0\n"
            "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"  # 0 lies 1 m behind 1
            "EDGE_SE2 1 2 0 1 1.5707963267948966 1 0 0 1 0 1\n")
    result = read_graph(_write(tmp_path, text))
    assert result.initialised_from_odometry
    np.testing.assert_allclose(result.graph.poses, [[4, 5, 0], [5, 5, 0], [5, 6, np.pi / 2]], atol=1e-12)


def test_unreachable_pose_is_an_error(tmp_path: Path) -> None:
    text = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 0 2 1 0 0 1 0 0 1 0 1\n"
    path = _write(tmp_path, text)
    with pytest.raises(GraphFileError, match="odometry chain") as caught:
        read_graph(path)
    assert f"{path}:2" in str(caught.value)


GOOD_EDGE = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"


@pytest.mark.parametrize(("bad_line", "reason"), [
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0", "needs 11 values"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1 7", "needs 11 values"),
    ("VERTEX_SE2 1 abc 0 0", "'abc' is not a number"),
    ("VERTEX_SE2 1 nan 0 0", "non-finite"),
    ("EDGE_SE2 0 1 1 0 0 inf 0 0 1 0 1", "non-finite"),
    ("VERTEX_SE2 1.5 0 0 0", "integers"),
    ("VERTEX_SE2 9007199254740993 0 0 0", "integers (below 2^53)"),  # 2^53 + 1: parsed, it would be 2^53
    ("EDGE_SE2", "without values"),
    ("EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1", "to itself"),
    ("VERTEX_SE2 0 3 3 3", "defined again (first on line 1)"),
    ("EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1", "not positive definite"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "3D pose graphs are not supported"),
    ("EDGE3 0 1 0 0 0 0 0 0 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1", "3D pose graphs are not supported"),
    ("VERTEX2 2 0 0 0", "mixes g2o"),
])
def test_bad_line_is_named(tmp_path: Path, bad_line: str, reason: str) -> None:
    text = f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n# comment\n\n{GOOD_EDGE}\n{bad_line}\n{GOOD_EDGE}\n"
    path = _write(tmp_path, text)
    with pytest.raises(GraphFileError) as caught:
        read_graph(path)
    assert f"{path}:6: " in str(caught.value)
    assert reason in str(caught.value)
    assert caught.value.line == 6


def test_first_bad_line_of_the_file_is_reported(tmp_path: Path) -> None:
    # The bad edge comes before the bad vertex; both kinds are checked, the earlier line wins.
    lines = ["VERTEX_SE2 0 0 0 0"] + [GOOD_EDGE] * 20 + ["EDGE_SE2 0 1 x 0 0 1 0 0 1 0 1"] + [GOOD_EDGE] * 20
    lines += ["VERTEX_SE2 1 1 y 0"]
    path = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(GraphFileError, match="'x' is not a number") as caught:
        read_graph(path)
    assert caught.value.line == 22


def test_a_pose_graph_line_of_a_megabyte_is_refused_by_its_length(tmp_path: Path) -> None:
    """Parsed whole, such a line took 20-30 times its size in memory (a 2 GB line, under the file size
    bound, would have exhausted it); it holds at most 11 numbers."""
    path = _write(tmp_path, "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1" + " 10" * 400_000 + "\n")
    with pytest.raises(GraphFileError, match=r"EDGE_SE2 line of 1200012 bytes; a pose-graph line holds "
                                             r"at most 11 numbers") as caught:
        read_graph(path)
    assert caught.value.line == 2


def test_many_lines_of_other_tags_are_counted_by_tag(tmp_path: Path) -> None:
    others = ["XY 1", "ROBOTLASER1 3 4", "XY"] * 50_000
    lines = ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0", GOOD_EDGE, *others]
    result = read_graph(_write(tmp_path, "\n".join(lines) + "\nPARAMS_SE2OFFSET 0 0 0 0\n"))
    assert result.skipped == {"XY": 100_000, "ROBOTLASER1": 50_000, "PARAMS_SE2OFFSET": 1}
    assert list(result.skipped) == ["XY", "ROBOTLASER1", "PARAMS_SE2OFFSET"]  # as they first appear
    # More distinct tags than the fast path counts: the line-by-line reader counts them alike.
    many = read_graph(_write(tmp_path, "\n".join(lines[:3] + [f"TAG{k} 1" for k in range(300)] * 2) + "\n",
                             name="many.g2o"))
    assert many.skipped == {f"TAG{k}": 2 for k in range(300)}


@pytest.mark.parametrize("fix", ["FIX 0 3", "FIX 3", "FIX"])
def test_a_pose_fixed_other_than_the_first_is_refused_not_moved(tmp_path: Path, fix: str) -> None:
    """The optimizer anchors the first pose and moves every other: a file holding another fixed states a
    problem it would not solve (skipped before, the fixed pose moved)."""
    lines = ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 3 1 0 0", GOOD_EDGE.replace(" 0 1 ", " 0 3 ", 1), fix]
    path = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(GraphFileError, match=r"only the graph's first pose \(id 0\) is held fixed") as caught:
        read_graph(path)
    assert caught.value.line == 4


@pytest.mark.parametrize("content", [b"", b"  \n\n", b"# only a comment\n", b"FIX 0\nEQUIV 1 2\n"])
def test_file_without_graph_lines_is_an_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "empty.g2o"
    path.write_bytes(content)
    with pytest.raises(GraphFileError) as caught:
        read_graph(path)
    assert str(caught.value).startswith(f"{path}: ")


@pytest.mark.parametrize("content", [
    b"VERTEX_SE2 0 0 0 0\n\xff\xfe\x80 garbage\n",
    b"VERTEX_SE2 0 0 0 0\n\x00\x01\x02",
])
def test_binary_file_is_a_graph_file_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "binary.g2o"
    path.write_bytes(content)
    with pytest.raises(GraphFileError) as caught:
        read_graph(path)
    assert f"{path}:2: " in str(caught.value)


def test_missing_file_and_directory_are_graph_file_errors(tmp_path: Path) -> None:
    with pytest.raises(GraphFileError, match="no such file"):
        read_graph(tmp_path / "absent.g2o")
    with pytest.raises(GraphFileError, match="directory"):
        read_graph(tmp_path)


def test_disconnected_graph_names_the_file(tmp_path: Path) -> None:
    text = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n" + GOOD_EDGE + "\n"
    path = _write(tmp_path, text)
    with pytest.raises(GraphFileError, match="not connected") as caught:
        read_graph(path)
    assert str(caught.value).startswith(f"{path}: ")


def test_repair_information_clamps_eigenvalues(tmp_path: Path) -> None:
    text = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 500 0 0 500 0 0\n"
            f"EDGE_SE2 0 1 1 0 0 {G2O_UPPER}\n")
    path = _write(tmp_path, text)
    with pytest.raises(GraphFileError, match="not positive definite"):
        read_graph(path)
    result = read_graph(path, repair_information=True)
    floor = 500 * REPAIR_EIGENVALUE_FLOOR
    np.testing.assert_allclose(result.graph.information[0], np.diag([500, 500, floor]), rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(result.graph.information[1], OMEGA)  # good edges are untouched
    np.testing.assert_array_equal(result.repaired_lines, [3])


def test_information_without_positive_eigenvalue_cannot_be_repaired(tmp_path: Path) -> None:
    text = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 0 0 0 0 0 0\n"
    path = _write(tmp_path, text)
    with pytest.raises(GraphFileError, match="no positive eigenvalue") as caught:
        read_graph(path, repair_information=True)
    assert caught.value.line == 3


def test_writers_use_original_ids_and_format_order(tmp_path: Path) -> None:
    graph = read_graph(_write(tmp_path, _tiny("VERTEX_SE2", "EDGE_SE2", G2O_UPPER))).graph
    write_g2o(tmp_path / "out.g2o", graph)
    write_toro(tmp_path / "out.graph", graph)
    g2o_lines = (tmp_path / "out.g2o").read_text().splitlines()
    toro_lines = (tmp_path / "out.graph").read_text().splitlines()
    assert g2o_lines[2].split()[:2] == ["VERTEX_SE2", "35"]
    assert toro_lines[3].split()[:3] == ["EDGE2", "10", "20"]
    assert [float(v) for v in g2o_lines[3].split()[6:]] == [100, 2, 3, 50, 5, 20]
    assert [float(v) for v in toro_lines[3].split()[6:]] == [100, 2, 50, 20, 3, 5]


def _assert_same_graph(a: PoseGraph, b: PoseGraph) -> None:
    for name in ("poses", "edge_from", "edge_to", "measurements", "information", "vertex_ids"):
        left, right = getattr(a, name), getattr(b, name)
        assert left.shape == right.shape and left.dtype == right.dtype, name
        assert left.tobytes() == right.tobytes(), name  # bit-identical


@pytest.mark.parametrize("writer", [write_g2o, write_toro])
def test_round_trip_is_exact(tmp_path: Path, writer) -> None:
    graph = read_graph(_write(tmp_path, _tiny("VERTEX_SE2", "EDGE_SE2", G2O_UPPER))).graph
    writer(tmp_path / "out.txt", graph)
    _assert_same_graph(read_graph(tmp_path / "out.txt").graph, graph)
    other = graph.poses + np.pi / 7
    writer(tmp_path / "moved.txt", graph, other)
    assert read_graph(tmp_path / "moved.txt").graph.poses.tobytes() == graph.with_poses(
        np.column_stack([other[:, :2], se2.wrap_angle(other[:, 2])])).poses.tobytes()


@pytest.mark.parametrize("writer", [write_g2o, write_toro])
def test_a_file_written_in_chunks_is_the_file_written_whole(tmp_path: Path, writer,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    from optimizer import graph_files

    graph = read_graph(_write(tmp_path, _tiny("VERTEX_SE2", "EDGE_SE2", G2O_UPPER))).graph
    writer(tmp_path / "whole.txt", graph)
    whole = (tmp_path / "whole.txt").read_bytes()
    assert whole.count(b"\n") == graph.num_poses + graph.num_edges
    for rows in (1, 2):  # chunks of one line, and chunks that straddle the vertex and edge lines
        monkeypatch.setattr(graph_files, "WRITE_CHUNK_ROWS", rows)
        writer(tmp_path / f"chunks{rows}.txt", graph)
        assert (tmp_path / f"chunks{rows}.txt").read_bytes() == whole


@st.composite
def random_graphs(draw: st.DrawFn) -> PoseGraph:
    seed = draw(st.integers(0, 2**32 - 1))
    num_poses = draw(st.integers(1, 12))
    num_extra = draw(st.integers(0, 10))
    rng = np.random.default_rng(seed)
    ids = rng.choice(10_000, size=num_poses, replace=False) - 100
    poses = rng.normal(scale=[50, 50, 3], size=(num_poses, 3))
    # a random spanning tree keeps it connected, then random extra edges in random directions
    tree_to = np.arange(1, num_poses)
    tree_from = np.array([rng.integers(0, to) for to in tree_to], dtype=np.int64)
    extra = rng.integers(0, num_poses, size=(num_extra, 2)) if num_poses > 1 else np.zeros((0, 2), np.int64)
    extra = extra[extra[:, 0] != extra[:, 1]]
    ends = np.concatenate([np.stack([tree_from, tree_to], axis=1), extra]).astype(np.int64)
    flip = rng.random(len(ends)) < 0.5
    ends[flip] = ends[flip][:, ::-1]
    measurements = rng.normal(scale=[5, 5, 2], size=(len(ends), 3))
    roots = rng.normal(size=(len(ends), 3, 3))
    information = np.einsum("mij,mkj->mik", roots, roots) + 0.1 * np.eye(3)
    information *= 10.0 ** rng.uniform(-2, 4, size=(len(ends), 1, 1))
    return PoseGraph.build(ids, poses, ids[ends[:, 0]], ids[ends[:, 1]], measurements, information)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(graph=random_graphs())
def test_random_graphs_round_trip_exactly(tmp_path: Path, graph: PoseGraph) -> None:
    for writer, name in ((write_g2o, "random.g2o"), (write_toro, "random.graph")):
        writer(tmp_path / name, graph)
        result = read_graph(tmp_path / name)
        assert result.format == ("g2o" if name.endswith("g2o") else "toro")
        _assert_same_graph(result.graph, graph)


# ------------------------------------------------------------------------------------------ real files


def test_fr079_g2o_and_toro_twins_agree() -> None:
    g2o = read_graph(shared_file("posegraphs/2d/FR079.g2o")).graph
    toro = read_graph(shared_file("posegraphs/2d/FR079.graph")).graph
    assert g2o.num_poses == 989 and g2o.num_edges == 1217
    for name in ("vertex_ids", "edge_from", "edge_to", "measurements"):
        np.testing.assert_array_equal(getattr(g2o, name), getattr(toro, name))
    # The g2o twin prints 6 significant digits, the TORO one 6 decimals: equal to that precision.
    np.testing.assert_allclose(g2o.poses, toro.poses, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(g2o.information, toro.information, rtol=1e-5, atol=1e-12)


def test_m3500_sizes() -> None:
    result = read_graph(shared_file("posegraphs/2d/M3500.g2o"))
    assert (result.graph.num_poses, result.graph.num_edges) == (3500, 5453)
    assert result.format == "g2o" and result.skipped == {}


def test_csail_has_no_vertices_and_follows_its_odometry() -> None:
    result = read_graph(shared_file("posegraphs/2d/CSAIL.g2o"))
    graph = result.graph
    assert result.initialised_from_odometry
    assert graph.num_edges == 1172
    odometry = graph.is_odometry
    assert odometry.sum() == graph.num_poses - 1
    predicted = se2.relative(graph.poses[graph.edge_from[odometry]], graph.poses[graph.edge_to[odometry]])
    np.testing.assert_allclose(predicted, graph.measurements[odometry], atol=1e-9)


def test_w100_reversed_edges_and_equiv_lines() -> None:
    path = shared_file("posegraphs/2d/w100.graph")
    result = read_graph(path)
    assert result.format == "toro"
    assert result.skipped == {"EQUIV": 40}
    assert (result.graph.num_poses, result.graph.num_edges) == (100, 300)
    first = path.read_text().splitlines()[100].split()  # "EDGE2 1 0 dx dy dθ ..."
    assert first[:3] == ["EDGE2", "1", "0"]
    z_file = np.array([float(v) for v in first[3:6]])
    assert (result.graph.edge_from[0], result.graph.edge_to[0]) == (1, 0)
    np.testing.assert_array_equal(result.graph.measurements[0], z_file)


def test_pg1_needs_repair() -> None:
    path = shared_file("posegraphs/2d/pg1.g2o")
    with pytest.raises(GraphFileError, match="not positive definite") as caught:
        read_graph(path)
    assert f"{path}:5: " in str(caught.value)
    result = read_graph(path, repair_information=True)
    assert result.graph.num_edges == 4
    np.testing.assert_array_equal(result.repaired_lines, [5])


@pytest.mark.parametrize("name", ["INTEL.g2o", "pose2example.txt"])
def test_other_2d_files_load(name: str) -> None:
    result = read_graph(shared_file(f"posegraphs/2d/{name}"))
    assert result.format == "g2o"
    assert result.graph.num_edges > 0


@pytest.mark.parametrize("name", [
    "tinyGrid3D.g2o", "smallGrid3D.g2o", "pose3example.txt", "sphere_smallnoise.graph",
])
def test_3d_files_are_refused(name: str) -> None:
    path = shared_file(f"posegraphs/3d/{name}")
    with pytest.raises(GraphFileError, match="3D pose graphs are not supported") as caught:
        read_graph(path)
    assert f"{path}:1: " in str(caught.value)


def test_crlf_lines_tabs_and_repeated_spaces(tmp_path: Path) -> None:
    path = tmp_path / "windows.g2o"
    path.write_bytes(b"VERTEX_SE2\t0 0 0 0\r\nVERTEX_SE2 1   2.5 0 0\r\n\r\n# c\r\n"
                     b"EDGE_SE2 0 1 2.5 0 0 1 0 0 1 0 1\r\n")
    graph = read_graph(path).graph
    np.testing.assert_array_equal(graph.poses, [[0, 0, 0], [2.5, 0, 0]])
    np.testing.assert_array_equal(graph.measurements, [[2.5, 0, 0]])


# ------------------------------------------------------------------------- the compiled fast path

PLAIN_FILES = {
    "interleaved lines, sparse ids, other tags": _tiny("VERTEX_SE2", "EDGE_SE2", G2O_UPPER),
    "toro": _tiny("VERTEX2", "EDGE2", TORO_UPPER),
    "crlf, tabs, repeated spaces": "VERTEX_SE2\t0 0 0 0\r\nVERTEX_SE2 1   2.5 0 0\r\n\r\n# c\r\n"
                                   "EDGE_SE2 0 1 2.5 0 0 1 0 0 1 0 1\r\n",
    "vertices after edges": "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nVERTEX_SE2 1 1 0 0\n"
                            "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\nVERTEX_SE2 2 2 0 0\n",
    "number forms, no final newline": "\ufeffVERTEX_SE2 0 +1. .5 -0\n  VERTEX_SE2 1 1e-3 -2.5E+2 7\n"
                                      "EDGE_SE2 0 1 1e308 -1e-308 0.1 1 0 0 1 0 1",
}


@pytest.fixture(params=[1, 3], ids=["whole", "in 3 pieces"])
def scan_pieces(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> int:
    """The fast path scanning files whole, or cut into up to 3 pieces scanned side by side (as a large
    file is on a machine with 3 threads): these small files are cut between almost every line."""
    from optimizer import graph_scan

    monkeypatch.setattr(graph_scan, "numba_config", SimpleNamespace(NUMBA_NUM_THREADS=request.param))
    monkeypatch.setattr(graph_scan, "PIECE_MIN_BYTES", 1)
    return request.param


@pytest.mark.parametrize("name", PLAIN_FILES)
def test_fast_path_agrees_with_the_line_by_line_reader(name: str, tmp_path: Path, scan_pieces: int) -> None:
    from optimizer.graph_files import _group_lines, _group_plain, _parse_block

    text = PLAIN_FILES[name]
    fast = _group_plain(text.encode("utf-8"))
    assert fast is not None, "a plain file must take the fast path"
    slow_groups, slow_skipped = _group_lines(tmp_path / "x", text.lstrip("\ufeff"))
    fast_groups, fast_skipped = fast
    assert fast_skipped == slow_skipped
    for tag, slow in slow_groups.items():
        np.testing.assert_array_equal(fast_groups[tag].lines, slow.lines)
        expected = 4 if tag.startswith("VERTEX") else 11
        values = np.zeros((0, expected))
        if slow.texts:
            values, problem = _parse_block(tag, slow.texts, expected)
            assert problem is None
        np.testing.assert_array_equal(fast_groups[tag].values, values)


@pytest.mark.parametrize("text", [
    "VERTEX_SE2 0 nan 0 0\n",
    "VERTEX_SE2 0 inf 0 0\n",
    "VERTEX_SE2 0 1.2.3 0\n",
    "VERTEX_SE2 0 1e 0 0\n",
    "VERTEX_SE2 0 0x10 0 0\n",
    "VERTEX_SE2 0 0 0\n",
    "VERTEX_SE2 0 0 0 0 0\n",
    "VERTEX_SE2\n",
    "VERTEX_SE2 0 0 0 0\r5\n",
    "VERTEX_SE2 0 0\x0b0 0\n",
    "# Größe\nVERTEX_SE2 0 0 0 0\n",
    "VERTEX_SE2 0 0 0 0\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n",
    "VERTEX3 0 0 0 0 0 0 0\n",
])
def test_fast_path_leaves_irregular_files_to_the_line_by_line_reader(text: str, scan_pieces: int) -> None:
    from optimizer.graph_files import _group_plain

    plain = "VERTEX_SE2 7 0 0 0\n" * 4
    assert _group_plain(text.encode("utf-8")) is None
    assert _group_plain((plain + text).encode("utf-8")) is None, "an irregular line in a later piece"
    assert _group_plain(plain.encode("utf-8")) is not None


def test_pieces_cut_at_line_ends_and_cover_the_file(monkeypatch: pytest.MonkeyPatch) -> None:
    from optimizer import graph_scan

    data = b"\xef\xbb\xbf" + b"".join(b"EDGE_SE2 %d %d 1 0 0 1 0 0 1 0 1\n" % (k, k + 1) for k in range(1000))
    assert graph_scan._piece_bounds(data, 3, 4) == [(3, len(data))], "a small file is scanned whole"
    monkeypatch.setattr(graph_scan, "PIECE_MIN_BYTES", 1)
    for count in (1, 2, 3, 7):
        bounds = graph_scan._piece_bounds(data, 3, count)
        assert len(bounds) == count
        assert bounds[0][0] == 3 and bounds[-1][1] == len(data)
        assert all(stop == first for (_, stop), (first, _) in itertools.pairwise(bounds))
        assert all(data[stop - 1:stop] == b"\n" for _, stop in bounds[:-1])


def test_a_bad_line_in_a_later_piece_is_named_with_its_line(tmp_path: Path, scan_pieces: int) -> None:
    lines = ["VERTEX_SE2 0 0 0 0"] + [f"EDGE_SE2 {k} {k + 1} 1 0 0 1 0 0 1 0 1" for k in range(30)]
    lines[25] = "EDGE_SE2 24 25 1 0 nan 1 0 0 1 0 1"
    path = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(GraphFileError) as caught:
        read_graph(path)
    assert f"{path}:26: " in str(caught.value)


def test_gershgorin_shortcut_never_passes_a_matrix_the_eigenvalues_reject() -> None:
    from optimizer.graph import not_positive_definite
    from optimizer.graph_files import _clearly_positive_definite

    rng = np.random.default_rng(5)
    rotations = np.linalg.qr(rng.standard_normal((4000, 3, 3)))[0]
    # eigenvalues from clearly positive through the tolerance down to zero and negative
    eigenvalues = 10.0 ** rng.uniform(-17, 3, (4000, 3)) * rng.choice([1.0, 1.0, 1.0, -1.0], (4000, 3))
    matrices = np.einsum("mij,mj,mkj->mik", rotations, eigenvalues, rotations)
    matrices = 0.5 * (matrices + np.swapaxes(matrices, 1, 2))
    diagonal = np.abs(rng.standard_normal((1000, 3))) * 10.0 ** rng.uniform(-3, 8, (1000, 1))
    matrices = np.concatenate([matrices, np.einsum("mi,ij->mij", diagonal, np.eye(3))])
    clear = _clearly_positive_definite(matrices)
    assert clear.any() and not clear.all()
    assert not (clear & not_positive_definite(matrices)).any()
