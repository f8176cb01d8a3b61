"""The recording's content, read back from the .rrd: entities, timelines, per-iteration keyframe transforms,
colours (contrast against the view's background), and that the last iteration is the written result."""

from __future__ import annotations

import io
import itertools
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from rerun.chunk import RrdReader

from frontends.slam2d import one_per_cell_each
from optimizer import se2
from optimizer.graph_files import read_graph
from optimizer.iteration import Iteration
from pipeline import recording
from pipeline.keyframe_optimization import optimize_keyframes, wheel_odometry_start
from pipeline.recording import map2d, scans
from pipeline.replay_graph import replay_graph
from tests.pipeline_fixtures import LOOP_POSES, read_recording, recording_streams_alive, write_loop_graph

OUR_TIMELINES = {"iteration", "scan", "time"}


def relative_luminance(rgb: tuple[int, ...]) -> float:
    """WCAG 2 relative luminance of an sRGB colour."""
    channels = np.asarray(rgb[:3], dtype=np.float64) / 255.0
    linear = np.where(channels <= 0.04045, channels / 12.92, ((channels + 0.055) / 1.055) ** 2.4)
    return float(linear @ np.array([0.2126, 0.7152, 0.0722]))


def contrast(a: tuple[int, ...], b: tuple[int, ...]) -> float:
    light, dark = sorted((relative_luminance(a), relative_luminance(b)), reverse=True)
    return (light + 0.05) / (dark + 0.05)


def properties(path: Path, name: str) -> dict[str, object]:
    """The recording property `name` of the .rrd at `path` (its fields carry no archetype prefix)."""
    found: dict[str, object] = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == f"/__properties/{name}":
            for row in chunk.to_record_batch().to_pylist():
                found.update({key: value[0] for key, value in row.items() if key != "rerun.controls.RowId"})
    return found


def rgba(packed: int) -> tuple[int, int, int, int]:
    """Rerun's packed 0xRRGGBBAA colour as a tuple."""
    return (packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255, packed & 255


def test_contrast_formula_matches_the_wcag_extremes() -> None:
    assert contrast((255, 255, 255), (0, 0, 0)) == pytest.approx(21.0)
    assert contrast((119, 119, 119), (255, 255, 255)) == pytest.approx(4.48, abs=0.01)


@pytest.fixture(scope="module")
def graph_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("graph")
    result = replay_graph(write_loop_graph(folder / "loop.g2o"), out_dir=folder / "out", method="sgd",
                          iterations=8)
    return folder / "out", {"result": result, "entities": read_recording(folder / "out" / "loop.rrd")}


def test_the_recording_holds_the_opening_layout_and_the_final_framed_one(
    graph_recording: tuple[Path, dict],
) -> None:
    out, _ = graph_recording
    reader = RrdReader(out / "loop.rrd")
    assert len(reader.recordings()) == 1
    framed = []
    for store in reader.blueprints():
        entities = {chunk.entity_path for chunk in reader.stream(store=store)}
        assert "/viewport" in entities
        framed.append(any(entity.endswith("/VisualBounds2D") for entity in entities))
    # The opening layout, and the final one framing the optimized map (only known at the end).
    assert sorted(framed) == [False, True]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads through Linux's /proc")
def test_replays_in_one_process_leave_no_recording_stream_behind(tmp_path: Path) -> None:
    # A batch script replays log after log: every stream the recording made (its own and its blueprints'),
    # with the threads and the recorded data it holds, must be gone when a replay returns.
    graph = write_loop_graph(tmp_path / "loop.g2o")
    alive = []
    for run in range(3):
        replay_graph(graph, out_dir=tmp_path / f"out{run}", method="sgd", iterations=2)
        alive.append(recording_streams_alive())
    # Never more than after the first (fewer if an earlier test's streams were swept meanwhile).
    assert max(alive[1:]) <= alive[0]


def test_a_graph_recording_has_only_our_timelines_and_its_properties(
    graph_recording: tuple[Path, dict],
) -> None:
    out, content = graph_recording
    entities = content["entities"]
    timelines = set().union(*(entity.timelines for entity in entities.values()))
    assert timelines == {"iteration"}  # no log_time / log_tick
    replay = properties(out / "loop.rrd", "replay")
    assert str(replay["input"]).endswith("loop.g2o")
    assert replay["method"] == "sgd" and replay["poses"] == LOOP_POSES


def test_the_world_is_mirrored_once_so_y_points_up(graph_recording: tuple[Path, dict]) -> None:
    _, content = graph_recording
    world = content["entities"]["/world"]
    assert world.static_rows == 1
    matrix = np.asarray(world.static_columns["Transform3D:mat3x3"][0], dtype=float).reshape(3, 3)
    np.testing.assert_allclose(np.abs(matrix), np.eye(3))
    assert np.linalg.det(matrix) == pytest.approx(-1.0) and matrix[1, 1] == -1.0


def test_the_estimate_is_drawn_on_top_in_colours_that_read_against_the_background(
    graph_recording: tuple[Path, dict],
) -> None:
    _, content = graph_recording
    entities = content["entities"]
    background = recording.VIEWER_BACKGROUND

    def style(path: str, column: str) -> object:
        return entities[path].static_columns[column][0]

    trajectory_color = rgba(style("/world/trajectory", "LineStrips2D:colors")[0])
    loops_color = rgba(style("/world/loop_closures", "LineStrips2D:colors")[0])
    assert contrast(trajectory_color, background) >= 4.0
    assert contrast(loops_color, background) >= 4.0
    assert contrast(recording.MAP_COLOR, background) >= 4.0
    assert contrast(recording.MAP_COLOR, map2d.OCCUPANCY_VIEW_COLORS[map2d.GRID_FREE]) >= 4.0
    assert trajectory_color != loops_color
    on_top = style("/world/trajectory", "LineStrips2D:draw_order")
    assert on_top > style("/world/loop_closures", "LineStrips2D:draw_order")
    assert on_top > style("/world/initial_trajectory", "LineStrips2D:draw_order")
    assert entities["/legend"].static_rows == 1


def test_the_stage_log_leaves_out_repeated_converged_iterations(graph_recording: tuple[Path, dict]) -> None:
    _, content = graph_recording
    result = content["result"]
    stages = content["entities"]["/optimizer/stage"]
    lines = [row[0] for row in stages.columns["TextLog:text"]]
    # Independent expectation: a line for an iteration exactly when (stage, χ² to 6 digits) differs from
    # the previous iteration's.
    expected_steps, previous = [], None
    for record in result.iterations:
        shown = (record.stage if record.start == "estimate" else f"{record.start}: {record.stage}",
                 f"{record.chi2:.6g}")
        if shown != previous:
            expected_steps.append(record.step)
        previous = shown
    assert stages.steps == expected_steps
    assert all("χ² = " in line for line in lines)
    assert len(set(itertools.pairwise(lines))) == len(lines) - 1


def test_rows_to_send_skips_moves_below_the_threshold_and_sends_the_last_row() -> None:
    poses = np.zeros((5, 2, 3))
    poses[:, 0, 0] = [0.0, 0.01, 0.02, 0.2, 0.21]  # keyframe 0 creeps, jumps, creeps
    poses[:, 1, 2] = [0.0, 0.1, 0.1, 0.1, 0.1]  # keyframe 1 turns once
    last = np.full((2, 3), np.nan)
    sent = map2d.rows_to_send(poses, last, 0.05, 0.01, True)
    np.testing.assert_array_equal(sent[:, 0], [True, False, False, True, True])
    np.testing.assert_array_equal(sent[:, 1], [True, True, False, False, True])
    np.testing.assert_allclose(last, poses[-1])
    later = map2d.rows_to_send(poses[-1:] + np.array([0.01, 0.0, 0.0]), last, 0.05, 0.01, False)
    assert not later.any()


def test_wheel_odometry_start_is_the_odometry_chain_anchored_at_the_first_keyframe() -> None:
    odometry = np.array([[10.0, 5.0, np.pi / 2], [10.0, 6.0, np.pi / 2], [9.0, 6.0, np.pi]])
    start = wheel_odometry_start(odometry, np.zeros(3))
    # Seen from the first odometry pose (facing +y): 1 m ahead, then 1 m ahead and 1 m to the left.
    np.testing.assert_allclose(start, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, np.pi / 2]], atol=1e-12)
    assert wheel_odometry_start(np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]), np.zeros(3)) is None


def _keyframe_scans(count: int) -> list[np.ndarray]:
    """A short wall ahead of every keyframe, different per keyframe."""
    along = np.linspace(-1.0, 1.0, 41)
    return [np.stack([np.full_like(along, 2.0 + 0.01 * k), along], axis=1) for k in range(count)]


def test_the_walls_move_with_every_iteration_and_end_at_the_written_poses(tmp_path: Path) -> None:
    graph = read_graph(write_loop_graph(tmp_path / "loop.g2o")).graph
    keyframe_scans = _keyframe_scans(graph.num_poses)
    path = tmp_path / "keyframes.rrd"
    stream = recording.create_recording(path, name="keyframes", with_map=True)
    seen: list[np.ndarray] = []

    def keep(iteration: Iteration) -> None:
        seen.append(np.array(iteration.poses))

    wheel = se2.compose_chain(se2.relative(graph.poses[:-1], graph.poses[1:]) + np.array([0.0, 0.0, 0.01]))
    optimized = optimize_keyframes(stream, graph, graph, "sgd", 20, keep, keyframe_scans=keyframe_scans,
                                   wheel_odometry=wheel)
    recording.close_recording(stream)
    entities = read_recording(path)
    assert len(seen) == len(optimized.trace)
    assert "wheel odometry" in [candidate.start for candidate in optimized.result.candidates]
    timelines = set().union(*(entity.timelines for entity in entities.values()))
    assert timelines <= OUR_TIMELINES and "iteration" in timelines
    assert "/world/map" not in entities  # the walls are the keyframe scans, no static copy

    last_step = len(seen) - 1
    rows_sent = 0
    for index in range(graph.num_poses):
        scan = entities[f"/world/keyframes/k{index:06d}/scan"]
        assert scan.steps == [0] and scan.static_rows == 0  # once, in the keyframe's own frame
        assert {"Points2D:positions", "Points2D:radii", "Points2D:colors", "Points2D:draw_order"} <= set(
            scan.columns)
        np.testing.assert_allclose(np.asarray(scan.columns["Points2D:positions"][0]), keyframe_scans[index],
                                   atol=1e-6)
        transform = entities[f"/world/keyframes/k{index:06d}"]
        assert transform.steps[0] == 0 and transform.steps[-1] == last_step
        rows_sent += len(transform.steps)
        translations = np.asarray(transform.columns["Transform3D:translation"], dtype=float).reshape(-1, 3)
        quaternions = np.asarray(transform.columns["Transform3D:quaternion"], dtype=float).reshape(-1, 4)
        yaws = 2.0 * np.arctan2(quaternions[:, 2], quaternions[:, 3])
        # At every step the viewer shows the latest row: within the threshold of that iteration's pose.
        latest = np.searchsorted(transform.steps, np.arange(len(seen)), side="right") - 1
        truth = np.array([poses[index] for poses in seen])
        assert np.all(np.hypot(*(translations[latest, :2] - truth[:, :2]).T) <= map2d.SHOWN_MOVE + 1e-5)
        assert np.all(np.abs(se2.wrap_angle(yaws[latest] - truth[:, 2])) <= map2d.SHOWN_TURN + 1e-5)
        # The last row is the written result exactly (float32).
        np.testing.assert_allclose(translations[-1, :2], optimized.poses[index, :2], atol=1e-5)
        assert se2.wrap_angle(yaws[-1] - optimized.poses[index, 2]) == pytest.approx(0.0, abs=1e-5)
    assert rows_sent < len(seen) * graph.num_poses  # still keyframes are not repeated
    # The trajectory likewise: a row when some pose moved more than the threshold, the last one whole.
    trajectory = entities["/world/trajectory"]
    assert trajectory.steps[0] == 0 and trajectory.steps[-1] == last_step
    strips = trajectory.columns["LineStrips2D:strips"]
    latest = np.searchsorted(trajectory.steps, np.arange(len(seen)), side="right") - 1
    for step, row in enumerate(latest):
        drawn = np.asarray(strips[row], dtype=float).reshape(-1, 2)
        assert np.max(np.abs(drawn - seen[step][:, :2])) <= map2d.SHOWN_MOVE + 1e-5
    np.testing.assert_allclose(np.asarray(strips[-1], dtype=float).reshape(-1, 2), optimized.poses[:, :2],
                               atol=1e-5)
    assert entities["/optimizer/chi2"].steps == list(range(len(seen)))
    assert properties(path, "optimization") == {"method": "sgd", "keyframes": graph.num_poses,
                                                "constraints": graph.num_edges, "loop_closures": 2}


def test_the_occupancy_grid_lies_in_world_metres_north_up(tmp_path: Path) -> None:
    # A 4 × 3-cell grid of 0.5 m cells from (10, 20): the occupied cell is ix = 3, iy = 2, the north-east
    # corner, so its centre is at (10 + 3.5·0.5, 20 + 2.5·0.5) = (11.75, 21.25).
    origin, resolution = np.array([10.0, 20.0]), 0.5
    picture = np.full((3, 4), map2d.GRID_FREE, dtype=np.uint8)
    picture[0, 3] = map2d.GRID_OCCUPIED  # image row 0 is the northern edge
    picture[2, 0] = map2d.GRID_UNKNOWN
    path = tmp_path / "grid.rrd"
    stream = recording.create_recording(path, name="grid")
    map2d.log_occupancy(stream, picture, origin, resolution)
    recording.close_recording(stream)
    entities = read_recording(path)
    placement = entities["/world/occupancy"].static_columns
    translation = np.asarray(placement["Transform3D:translation"][0], dtype=float).reshape(3)
    scale = np.asarray(placement["Transform3D:scale"][0], dtype=float).reshape(3)
    image_row = entities["/world/occupancy/grid"].static_columns
    blob = np.asarray(image_row["EncodedImage:blob"][0], dtype=np.uint8).tobytes()
    decoded = np.asarray(Image.open(io.BytesIO(blob)).convert("RGBA"))  # as a viewer expands a palette
    # Every cell in the colour of its grey, pixel for pixel.
    expected = [[map2d.OCCUPANCY_VIEW_COLORS[grey] for grey in row] for row in picture.tolist()]
    np.testing.assert_array_equal(decoded, np.array(expected, dtype=np.uint8))
    rows, cols = np.nonzero(np.all(decoded == map2d.OCCUPANCY_VIEW_COLORS[map2d.GRID_OCCUPIED], axis=-1))
    assert (rows.tolist(), cols.tolist()) == ([0], [3])
    centre = translation[:2] + scale[:2] * (np.array([cols[0], rows[0]]) + 0.5)
    np.testing.assert_allclose(centre, [11.75, 21.25])


def test_thin_scan_keeps_the_first_point_of_each_cell_in_scan_order() -> None:
    points = np.array([[0.01, 0.01], [0.02, 0.03], [0.5, -0.01], [-0.01, 0.0], [0.04, 0.0], [np.nan, 0.0]])
    # Cells of 0.05 m: (0, 0) twice then again, (10, −1), (−1, 0); the NaN point is dropped.
    np.testing.assert_allclose(map2d.thin_scan(points), [[0.01, 0.01], [0.5, -0.01], [-0.01, 0.0]], atol=1e-7)
    assert map2d.thin_scan(np.zeros((0, 2))).shape == (0, 2)


def _chain_graph_text(start_error: float) -> str:
    """A 6-pose chain of odometry edges (no loop closure); vertex k after the first is off by
    `start_error` metres in x from where the edges put it."""
    step = np.array([1.0, 0.0, 0.3])
    poses = [np.zeros(3)]
    for _ in range(5):
        poses.append(se2.compose(poses[-1], step))
    lines = [f"VERTEX_SE2 {k} {x + (start_error if k else 0.0):.17g} {y:.17g} {t:.17g}"
             for k, (x, y, t) in enumerate(poses)]
    lines += [f"EDGE_SE2 {k} {k + 1} 1 0 0.3 100 0 0 100 0 1000" for k in range(5)]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("start_error", [0.0, 0.5])
def test_a_graph_without_loop_closures_says_so_and_plots_no_round_off_chi2(
    tmp_path: Path, start_error: float,
) -> None:
    path = tmp_path / "chain.g2o"
    path.write_text(_chain_graph_text(start_error))
    result = replay_graph(path, out_dir=tmp_path / "out", method="sgd", iterations=20)
    entities = read_recording(tmp_path / "out" / "chain.rrd")
    plain = [row[0] for row in entities["/optimizer/chi2"].columns["Scalars:scalars"]]
    assert len(plain) == len(result.iterations)  # the data keeps every value, round-off included
    assert min(plain) < recording.ROUND_OFF_CHI2  # the chain's optimum is zero: SGD gets there
    logged = entities.get("/optimizer/log10_chi2")
    log10 = [] if logged is None else [row[0] for row in logged.columns["Scalars:scalars"]]
    # Independent expectation: the plot holds exactly the χ² values that are more than round-off.
    assert log10 == pytest.approx([np.log10(c) for c in plain if c > recording.ROUND_OFF_CHI2])
    assert bool(log10) == (start_error > 0)
    notes = [row[0] for row in entities["/optimizer/stage"].columns["TextLog:text"]]
    assert recording.NO_LOOP_CLOSURES_NOTE in notes
    # The stage log words round-off as zero, so no line shows a meaningless 1e-2x.
    lines = [line for line in notes if line != recording.NO_LOOP_CLOSURES_NOTE]
    assert not any(re.search(r"e-(1[3-9]|[2-9]\d)", line) for line in lines)  # nothing below 1e-12
    assert any(line.endswith("χ² = 0 (round-off)") for line in lines)


def test_a_graph_with_loop_closures_plots_every_positive_chi2(graph_recording: tuple[Path, dict]) -> None:
    _, content = graph_recording
    plain = [row[0] for row in content["entities"]["/optimizer/chi2"].columns["Scalars:scalars"]]
    log10 = [row[0] for row in content["entities"]["/optimizer/log10_chi2"].columns["Scalars:scalars"]]
    assert log10 == pytest.approx([np.log10(c) for c in plain if c > 0])
    notes = [row[0] for row in content["entities"]["/optimizer/stage"].columns["TextLog:text"]]
    assert recording.NO_LOOP_CLOSURES_NOTE not in notes


def test_thinning_many_scans_in_one_call_equals_thinning_each() -> None:
    rng = np.random.default_rng(4)
    scans = [rng.uniform(-3.0, 3.0, size=(n, 2)) for n in (0, 1, 50, 400, 7)]
    scans[3][::9] = np.nan  # dropped, as thin_scan drops them
    points = np.concatenate(scans)
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in scans])])
    keep, counts = one_per_cell_each(points, offsets, 0.5)
    expected = [map2d.thin_scan(s, 0.5) for s in scans]
    assert counts.tolist() == [len(e) for e in expected]
    np.testing.assert_array_equal(points[keep].astype(np.float32), np.concatenate(expected))


def test_played_back_scans_are_placed_at_their_poses_and_thinned_per_scan(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    scans_in_robot_frame = [rng.uniform(-4.0, 4.0, size=(n, 2)) for n in (120, 0, 60)]
    poses = np.array([[1.0, 2.0, 0.3], [0.0, 0.0, 0.0], [-3.0, 0.5, -2.0]])
    path = tmp_path / "scans.rrd"
    stream = recording.create_recording(path, name="scans")
    recorder = scans.ScanRecorder(stream)
    for index, (points, pose) in enumerate(zip(scans_in_robot_frame, poses, strict=True)):
        recorder.add(index, 10**9 * (index + 1), points, pose)
    recorder.flush()
    recording.close_recording(stream)
    played = read_recording(path, timeline="scan")
    rows = played["/world/scan"].columns["Points2D:positions"]
    for row, points, pose in zip(rows, scans_in_robot_frame, poses, strict=True):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        placed = points @ np.array([[c, s], [-s, c]]) + pose[:2]  # independent of `place`
        expected = map2d.thin_scan(placed, scans.PLAYBACK_CELL)
        np.testing.assert_allclose(np.asarray(row, dtype=float).reshape(-1, 2), expected, atol=1e-5)
    robot = [row[0] for row in played["/world/robot"].columns["Points2D:positions"]]
    np.testing.assert_allclose(robot, poses[:, :2], atol=1e-6)
