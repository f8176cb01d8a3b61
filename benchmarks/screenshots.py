"""Screenshots of the recordings in the real Rerun viewer, and the recording's figures (issue 10).

    python benchmarks/screenshots.py [--out benchmarks/results] [--shared ../shared]
                                     [--only sample,aces,m3500,kitti,grid10k]

Needs an X server with Vulkan. On Debian: `apt-get install xvfb mesa-vulkan-drivers` (Mesa's llvmpipe is a
software Vulkan); the script starts `Xvfb :99` itself when DISPLAY is unset, and moves the pointer into the
screen's corner so that no hover tooltip covers the view.

For each input it runs the replay (the bundled sample and ACES through `replay_log`, M3500 through
`replay_graph`, the KITTI log through `replay_cloud`), then:
- at a few iterations k, copies the recording's static data and its iterations ≤ k with the blueprint
  the replay wrote (rebuilt from the same functions; it opens following the last iteration) and
  screenshots it with `rerun FILE --window-size 1400x900 --screenshot-to PNG` into `<out>/screenshots/`;
- for log replays, at a few scans s, the scan-time data up to s with a blueprint showing only the scan
  playback tab on the `scan` timeline;
- per screenshot, the fraction of the main view's pixels that differ from the view's background by more
  than 40 levels (in any channel): how much of the view is drawn map rather than empty background.
Figures (printed, and `<out>/screenshots.json`): the `.rrd` sizes (targets: ACES ≤ 25 MB, sample ≤ 6 MB,
a 10,000-pose graph with 100 iterations ≤ 40 MB) and the recording's share of the ACES replay (≤ 10 %).
Timings depend on the machine's load: re-run on a quiet machine for final figures.
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import pyarrow as pa  # noqa: E402
import pyarrow.compute as pc  # noqa: E402
import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402
from PIL import Image  # noqa: E402
from rerun.chunk import Chunk, RrdReader  # noqa: E402

from pipeline.recording import APPLICATION_ID, VIEWER_BACKGROUND, default_blueprint, world_bounds  # noqa: E402
from pipeline.recording.clouds import cloud_blueprint  # noqa: E402
from pipeline.recording.scans import SCAN_TIMELINE, log_replay_blueprint, playback_views  # noqa: E402

WINDOW = "1400x900"
DISPLAY = ":99"
DRAWN_ABOVE = 40
MAIN_VIEW = (0.005, 0.075, 0.745, 0.955)
"""The map view in the screenshot as fractions (left, top, right, bottom) of the window: the default
blueprint gives it 3/4 of the width between the top bar and the collapsed time panel."""
SIZE_TARGETS_MB = {"aces": 25.0, "sample": 6.0, "grid10k": 40.0}
RECORDING_SHARE_TARGET = 0.10
RECORDING_STAGES = ("record_scans", "record_iterations", "record_maps", "record_close")
RERUN = Path(sys.executable).with_name("rerun")


def ensure_display() -> subprocess.Popen[bytes] | None:
    """Start Xvfb on :99 unless a display is set; put the pointer in the corner either way."""
    server = None
    if not os.environ.get("DISPLAY"):
        if shutil.which("Xvfb") is None:
            raise SystemExit("needs Xvfb and Mesa's Vulkan: apt-get install xvfb mesa-vulkan-drivers")
        server = subprocess.Popen(["Xvfb", DISPLAY, "-screen", "0", "1600x1000x24", "-extension",
                                   "Composite"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.environ["DISPLAY"] = DISPLAY
        time.sleep(2.0)
    os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.gettempdir())
    _pointer_to_corner()
    return server


def _pointer_to_corner() -> None:
    """Onto the empty top bar: the viewer's window (HiDPI, 2× the requested size) covers the screen."""
    library = ctypes.util.find_library("X11")
    if library is None:
        return
    x11 = ctypes.cdll.LoadLibrary(library)
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XDefaultRootWindow.restype = ctypes.c_ulong
    x11.XDefaultRootWindow.argtypes = [ctypes.c_void_p]
    x11.XWarpPointer.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong, *[ctypes.c_int] * 2,
                                 *[ctypes.c_uint] * 2, *[ctypes.c_int] * 2]
    x11.XFlush.argtypes = [ctypes.c_void_p]
    display = x11.XOpenDisplay(os.environ["DISPLAY"].encode())
    if display:
        x11.XWarpPointer(display, 0, x11.XDefaultRootWindow(display), 0, 0, 0, 0, 700, 20)
        x11.XFlush(display)


def screenshot(rrd: Path, png: Path) -> float:
    """Screenshot `rrd` in the viewer; returns the main view's drawn fraction."""
    png.parent.mkdir(parents=True, exist_ok=True)
    _pointer_to_corner()  # the server puts it back in the middle now and then
    # --new: never stream into a viewer another run (or a user) has open on the default port.
    subprocess.run([str(RERUN), str(rrd), "--new", "--window-size", WINDOW, "--screenshot-to", str(png)],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    return drawn_fraction(png)


def drawn_fraction(png: Path, region: tuple[float, float, float, float] = MAIN_VIEW) -> float:
    """The fraction of `region`'s pixels differing from the view background by > DRAWN_ABOVE levels."""
    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.int16)
    height, width = pixels.shape[:2]
    left, top, right, bottom = region
    view = pixels[int(top * height):int(bottom * height), int(left * width):int(right * width)]
    difference = np.abs(view - np.asarray(VIEWER_BACKGROUND, dtype=np.int16)).max(axis=-1)
    return float(np.mean(difference > DRAWN_ABOVE))


def cut(rrd: Path, timeline: str, last: int, target: Path, blueprint: rrb.Blueprint) -> Path:
    """Static data and the `timeline` data up to `last` of the recording at `rrd`, with `blueprint`.

    (`rerun rrd split` would keep the file's own blueprint but puts each static chunk into one split
    only: cuts lost the mirror of `world` or the grid's placement.)"""
    stream = rr.RecordingStream(APPLICATION_ID)
    stream.save(target, default_blueprint=blueprint)
    for chunk in RrdReader(rrd).stream():
        if chunk.is_static:
            stream.send_chunks(chunk)
        elif timeline in chunk.timeline_names:
            batch = chunk.to_record_batch()
            kept = batch.filter(pc.less_equal(batch.column(timeline), pa.scalar(last, pa.int64())))
            if kept.num_rows:
                stream.send_chunks(Chunk.from_record_batch(kept, entity_path=chunk.entity_path))
    stream.flush()
    stream.disconnect()
    return target


def playback_blueprint(bounds: tuple[float, float, float, float]) -> rrb.Blueprint:
    """The scan playback tab alone, on the `scan` timeline."""
    return rrb.Blueprint(
        *playback_views(bounds),
        rrb.TimePanel(timeline=SCAN_TIMELINE, state="collapsed", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
    )


def shoot_iterations(name: str, rrd: Path, count: int, out: Path,
                     blueprint: rrb.Blueprint) -> dict[str, float]:
    """Screenshots at a few iterations; `blueprint` is the one the replay wrote (the cuts need it again)."""
    steps = sorted({0, min(10, count - 1), count // 3, count - 1})
    fractions = {}
    with tempfile.TemporaryDirectory() as scratch:
        for step in steps:
            cut_file = rrd
            if step < count - 1:
                cut_file = cut(rrd, "iteration", step, Path(scratch) / f"{step}.rrd", blueprint)
            png = f"{name}_iteration{step:04d}.png"
            fractions[png] = screenshot(cut_file, out / png)
    return fractions


def shoot_scans(name: str, rrd: Path, scans: int, bounds: tuple[float, float, float, float],
                out: Path) -> dict[str, float]:
    fractions = {}
    with tempfile.TemporaryDirectory() as scratch:
        for scan in sorted({scans // 4, scans // 2, scans - 1}):
            cut_file = cut(rrd, SCAN_TIMELINE, scan, Path(scratch) / f"scan{scan}.rrd",
                           playback_blueprint(bounds))
            png = f"{name}_scan{scan:05d}.png"
            fractions[png] = screenshot(cut_file, out / png)
    return fractions


def log_replay(name: str, log: Path, out: Path, shots: Path) -> dict[str, Any]:
    from pipeline.recording.map2d import placed_bounds
    from pipeline.replay_log import replay_log

    result = replay_log(log, out_dir=out / name)
    times = result.wall_time
    recording_seconds = sum(times.get(stage, 0.0) for stage in RECORDING_STAGES)
    bounds = placed_bounds(result.frontend.result.keyframe_scans, result.keyframe_poses)
    fractions = shoot_iterations(name, result.outputs.rrd, len(result.chi2_per_iteration), shots,
                                 log_replay_blueprint(bounds))
    fractions |= shoot_scans(name, result.outputs.rrd, int(result.counts["scans"]), bounds, shots)
    return {"rrd_mb": result.outputs.rrd.stat().st_size / 1e6, "recording_share": recording_seconds /
            times["total"], "recording_s": recording_seconds, "total_s": times["total"],
            "iterations": len(result.chi2_per_iteration), "drawn_fraction": fractions}


def graph_replay(name: str, graph: Path, out: Path, shots: Path | None, **options: Any) -> dict[str, Any]:
    from pipeline.replay_graph import replay_graph

    result = replay_graph(graph, out_dir=out / name, **options)
    figures: dict[str, Any] = {"rrd_mb": result.outputs.rrd.stat().st_size / 1e6,
                                  "iterations": len(result.iterations), "poses": result.graph.num_poses}
    if shots is not None:
        blueprint = default_blueprint(bounds=world_bounds(result.poses))
        figures["drawn_fraction"] = shoot_iterations(name, result.outputs.rrd, len(result.iterations), shots,
                                                     blueprint)
    return figures


def cloud_replay(name: str, log: Path, out: Path, shots: Path) -> dict[str, Any]:
    from pipeline.replay_log import replay_log

    result = replay_log(log, out_dir=out / name)
    fractions = shoot_iterations(name, result.outputs.rrd, len(result.chi2_per_iteration), shots,
                                 cloud_blueprint(world_bounds(result.keyframe_poses)))
    return {"rrd_mb": result.outputs.rrd.stat().st_size / 1e6, "drawn_fraction": fractions}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--only", default="sample,aces,m3500,kitti,grid10k")
    arguments = parser.parse_args()
    chosen = set(arguments.only.split(","))
    data = arguments.shared / "data"
    shots = arguments.out / "screenshots"
    server = ensure_display()
    figures: dict[str, dict[str, Any]] = {}
    try:
        with tempfile.TemporaryDirectory() as scratch:
            work = Path(scratch)
            if "sample" in chosen:
                sample = REPO / "pipeline" / "samples" / "csail_sample.mcap"
                figures["sample"] = log_replay("sample", sample, work, shots)
            if "aces" in chosen:
                figures["aces"] = log_replay("aces", data / "logs" / "aces" / "aces.mcap", work, shots)
            if "m3500" in chosen:
                m3500 = data / "posegraphs" / "2d" / "M3500.g2o"
                figures["m3500"] = graph_replay("m3500", m3500, work, shots)
            if "kitti" in chosen:
                kitti = data / "logs" / "kitti" / "kitti_city.mcap"
                figures["kitti"] = cloud_replay("kitti", kitti, work, shots)
            if "grid10k" in chosen:
                from optimizer.graph_files import write_g2o
                from optimizer.gridworld import generate_grid_world

                graph = work / "grid10k.g2o"
                write_g2o(graph, generate_grid_world(10_000, seed=0).graph)
                figures["grid10k"] = graph_replay("grid10k", graph, work, None, method="sgd+gn",
                                                  iterations=100)
    finally:
        if server is not None:
            server.terminate()
    for name, values in figures.items():
        target = SIZE_TARGETS_MB.get(name)
        print(f"{name}: .rrd {values['rrd_mb']:.1f} MB" + (f" (target ≤ {target:g} MB)" if target else ""))
        if "recording_share" in values:
            print(f"  recording share {values['recording_share']:.1%} "
                  f"(target ≤ {RECORDING_SHARE_TARGET:.0%})")
        for png, fraction in values.get("drawn_fraction", {}).items():
            print(f"  {png}: {fraction:.1%} of the main view drawn")
    arguments.out.mkdir(parents=True, exist_ok=True)
    table = arguments.out / "screenshots.json"
    earlier = json.loads(table.read_text()) if table.exists() else {}  # --only keeps the other rows
    table.write_text(json.dumps(earlier | figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
