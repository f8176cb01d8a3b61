"""Peak memory of `replay` on the worst inputs we could construct (issue 11): each is generated, replayed in
a fresh process, and listed with the process's peak RSS (from wait4's rusage of that child alone), its
exit code, wall time and first stderr line. Asserts nothing.

    python benchmarks/worst_rss.py [--case NAME ...] [--timeout 900]

The documented bound is 2 GB for a 2D log whatever one message contains (issue 11); 3D logs have no bound
yet, the figure is reported. Measured on a loaded machine, the figures move with the load only a little
(RSS is not time), the seconds a lot.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.hostile_fixtures import cloud_log, scan_log, walls  # noqa: E402

BOUND_2D_BYTES = 2 << 30


@dataclass(frozen=True)
class Case:
    name: str
    dimensions: int
    write: Callable[[Path], Path]
    """Writes the input into the folder and returns its path."""


def _beams_at_limit(folder: Path) -> Path:
    # 100 scans at the largest beam count accepted (32,768), a third of the returns 10⁶ m away, and one
    # odometry message 10⁷ m away: the local map, the likelihood grid and the occupancy grid at their worst.
    beams = 32_768
    far = np.arange(beams) % 3 == 0
    return scan_log(folder / "beams.mcap",
                    lambda i: np.where(far, 1e6, 3.0 + np.sin(np.arange(beams) * 1e-4)),
                    angle_increment=2 * math.pi / beams, count=100,
                    odometry=lambda i: (1e7, 1e7, 0.0) if i == 50 else (0.02 * i, 0.0, 0.0))


def _one_huge_scan(folder: Path) -> Path:
    # One 16-million-beam scan (a 64 MB message): refused, but it has to be read to be refused.
    return scan_log(folder / "huge.mcap", lambda i: np.full(16_000_000, 5.0, np.float32), count=1,
                    angle_increment=1e-7)


def _odometry_glitches(folder: Path) -> Path:
    # Every 7th odometry message 10⁴ to 10⁷ m away: a grid sized from the raw track would be terabytes.
    return scan_log(folder / "glitches.mcap", walls, count=300,
                    odometry=lambda i: (10.0 ** (4 + i % 4), 0.0, 0.0) if i % 7 == 3
                    else (0.02 * i, 0.0, 0.0))


def _far_returns(folder: Path) -> Path:
    # Every other scan all 10³⁰ m returns, the others 2000 beams at a tiny angle increment.
    return scan_log(folder / "far.mcap",
                    lambda i: np.full(2000, 1e30, np.float32) if i % 2 else walls(i, 2000),
                    angle_increment=1e-7, count=200)


def _long_log(folder: Path) -> Path:
    # 3000 ordinary scans with odometry: what an honest long log costs, for comparison.
    return scan_log(folder / "long.mcap", walls, count=3000, odometry=lambda i: (0.02 * i, 0.0, 0.0))


def _cloud_huge_extent(folder: Path) -> Path:
    # 200,000 points, half of them scattered 10⁶ m around the sensor.
    rng = np.random.default_rng(0)
    points = rng.normal(0.0, 1e6, (200_000, 3)).astype(np.float32)
    points[::2] = rng.uniform(-20.0, 20.0, (100_000, 3))
    return cloud_log(folder / "extent.mcap", width=200_000, row_step=12 * 200_000,
                     data=np.frombuffer(points.tobytes(), np.uint8))


def _cloud_million_points(folder: Path) -> Path:
    # One cloud of 2 million points in a 100 m box (24 MB).
    points = np.random.default_rng(1).uniform(-50.0, 50.0, (2_000_000, 3)).astype(np.float32)
    return cloud_log(folder / "million.mcap", width=2_000_000, row_step=12 * 2_000_000,
                     data=np.frombuffer(points.tobytes(), np.uint8))


def _cloud_claiming_huge_width(folder: Path) -> Path:
    return cloud_log(folder / "claim.mcap", width=2**32 - 1)


CASES = [
    Case("2d-beams-at-limit-far-returns-glitch", 2, _beams_at_limit),
    Case("2d-one-16M-beam-scan", 2, _one_huge_scan),
    Case("2d-odometry-glitches-1e4-1e7-m", 2, _odometry_glitches),
    Case("2d-far-returns-tiny-increment", 2, _far_returns),
    Case("2d-long-ordinary-log", 2, _long_log),
    Case("3d-cloud-huge-extent", 3, _cloud_huge_extent),
    Case("3d-cloud-2M-points", 3, _cloud_million_points),
    Case("3d-cloud-claiming-2^32-points", 3, _cloud_claiming_huge_width),
]


def measure(case: Case, timeout: float) -> tuple[int | str, int, float, str]:
    """Exit code (or "timeout"), peak RSS in bytes, seconds, first stderr line."""
    with tempfile.TemporaryDirectory(prefix="worst-rss-") as temporary:
        folder = Path(temporary)
        path = case.write(folder)
        stderr_path = folder / "stderr.txt"
        started = time.perf_counter()
        with stderr_path.open("w") as stderr:
            process = subprocess.Popen(
                [sys.executable, "-m", "pipeline.launcher", str(path), "--out", str(folder / "out"),
                 "--quiet", "--allow-unconverged"],
                stdout=subprocess.DEVNULL, stderr=stderr, cwd=REPO)
            status, usage, timed_out = _wait_with_rusage(process.pid, timeout)
            process.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
        seconds = time.perf_counter() - started
        code: int | str = "timeout" if timed_out else process.returncode
        peak = usage.ru_maxrss * 1024  # Linux reports kilobytes
        lines = stderr_path.read_text(errors="replace").splitlines()
        return code, peak, seconds, (lines[0] if lines else "").replace(temporary, "TMP")


def _wait_with_rusage(pid: int, timeout: float) -> tuple[int, resource.struct_rusage, bool]:
    """Wait for the child `pid` (killed after `timeout` s): its wait status, its own resource usage (wait4:
    that child and its descendants only, not every child so far as RUSAGE_CHILDREN), whether it timed out."""
    deadline = time.monotonic() + timeout
    timed_out = False
    while True:
        reaped, status, usage = os.wait4(pid, os.WNOHANG)
        if reaped == pid:
            return status, usage, timed_out
        if not timed_out and time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            timed_out = True
        time.sleep(0.05)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", action="append", help="only these cases (repeatable)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds allowed per case")
    args = parser.parse_args()
    print("| case | exit | peak RSS (MB) | s | first stderr line |\n|---|---|---|---|---|", flush=True)
    worst = {2: 0, 3: 0}
    for case in CASES:
        if args.case is not None and case.name not in args.case:
            continue
        code, peak, seconds, first = measure(case, args.timeout)
        worst[case.dimensions] = max(worst[case.dimensions], peak)
        print(f"| {case.name} | {code} | {peak / 1e6:.0f} | {seconds:.1f} | {first[:150]} |", flush=True)
    print(f"\nworst 2D peak RSS {worst[2] / 1e6:.0f} MB (documented bound {BOUND_2D_BYTES / 1e6:.0f} MB); "
          f"worst 3D peak RSS {worst[3] / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
