"""The bad-input battery through the command, case by case (issue 11's "cases tried by family, with exit
codes"): each case is generated (with the generators of tests/hostile_fixtures.py), replayed by `replay` in
a fresh process, and listed with its exit code and the first line it printed on stderr. Asserts nothing.

    python benchmarks/hostile_cases.py [--family NAME ...] [--timeout 300]

Exit codes: 0 replayed, 2 refused with one line, 3 not converged; anything else (1, a signal) is a bug, as
is a traceback on stderr (the table marks both with "!!").
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.hostile_fixtures import (  # noqa: E402
    CLOUD_LAYOUTS,
    DAMAGED,
    GARBAGE_RANGES,
    cloud_log,
    scan_log,
    walls,
)

Arguments = Callable[[Path], list[str]]
"""Given a fresh temporary folder: the command's arguments (the input written into the folder)."""


@dataclass(frozen=True)
class Case:
    family: str
    name: str
    arguments: Arguments


def _log(make: Callable[[Path], Path], *options: str) -> Arguments:
    return lambda folder: [str(make(folder)), *options]


def _scan_case(**scan_options: object) -> Arguments:
    def arguments(folder: Path) -> list[str]:
        return [str(scan_log(folder / "scans.mcap", **scan_options))]  # type: ignore[arg-type]

    return arguments


def _config_case(text: str) -> Arguments:
    def arguments(folder: Path) -> list[str]:
        graph = folder / "graph.g2o"
        graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
        config = folder / "replay.toml"
        config.write_text(text)
        return [str(graph), "--config", str(config)]

    return arguments


def _graph_case(text: str, *options: str) -> Arguments:
    def arguments(folder: Path) -> list[str]:
        graph = folder / "graph.g2o"
        graph.write_text(text)
        return [str(graph), *options]

    return arguments


_GOOD_GRAPH = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"


def _fifo_case(folder: Path) -> list[str]:
    path = folder / "pipe.g2o"
    os.mkfifo(path)
    return [str(path)]


def _graph_in_out_folder(folder: Path) -> list[str]:
    """A graph inside the folder `run_case` passes as --out: its output `graph.g2o` would replace it."""
    (folder / "out").mkdir()
    graph = folder / "out" / "graph.g2o"
    graph.write_text(_GOOD_GRAPH)
    return [str(graph)]


def cases() -> list[Case]:
    # The damaged logs hold both a LaserScan and a PointCloud2 topic: name the scans, so that the replay
    # reads on into the damage instead of stopping at the choice of topic.
    battery = [Case("damaged container", name, _log(make, "--scan-topic", "/scan"))
               for name, make in DAMAGED.items()]
    battery += [Case("garbage scans", name, _scan_case(ranges=ranges))
                for name, ranges in GARBAGE_RANGES.items()]
    battery += [Case("scan angles", f"angle-increment-{increment}", _scan_case(ranges=walls,
                                                                              angle_increment=increment))
                for increment in (math.nan, math.inf, -math.inf, 0.0, 1.0, -0.01)]
    battery += [Case("beam times", f"time-increment-{value}", _scan_case(ranges=walls, time_increment=value))
                for value in (math.nan, math.inf, -math.inf, 1.0, -1e-4, 1e-30)]
    stamps: dict[str, Callable[[int], int]] = {  # what the fast-laser cadence counts its strides from
        "1-kHz-laser": lambda i: 10**18 + i * 1_000_000,
        "pairs-of-equal-stamps": lambda i: 10**18 + (i // 2) * 25_000_000,
        "bursts-of-ten-in-1-ms-a-second-apart": lambda i: 10**18 + (i // 10) * 10**9 + (i % 10) * 100_000,
        "40-Hz-jittered-by-half-an-interval": lambda i: 10**18 + i * 25_000_000 + (i * 7919 % 25) * 500_000,
        "never-set-all-0": lambda i: 0,  # replayed at the log times
    }
    battery += [Case("scan stamps", name, _scan_case(ranges=walls, count=200, stamp=stamp,
                                                     odometry=lambda i: (0.01 * i, 0.0, 0.0)))
                for name, stamp in stamps.items()]
    without_odometry: dict[str, Callable[[int], int]] = {  # the search after a gap (`MAX_GAP_REACH`)
        "no-odometry-an-hour-gap": lambda i: 10**18 + i * 100_000_000 + (3600 * 10**9 if i >= 30 else 0),
        "no-odometry-one-stamp-a-year-ahead": lambda i: 10**18 + i * 100_000_000
        + (365 * 86_400 * 10**9 if i == 30 else 0),
    }
    battery += [Case("scan stamps", name, _scan_case(ranges=walls, count=60, stamp=stamp))
                for name, stamp in without_odometry.items()]
    battery += [
        Case("huge values", "two-million-beams", _scan_case(ranges=lambda i: np.full(2_000_000, 5.0), count=1,
                                                            angle_increment=1e-6)),
        *(Case("huge values", f"odometry-glitch-{distance:g}-m", _scan_case(
            ranges=walls, odometry=lambda i, d=distance: (d, -d, 0.0) if i == 17 else (0.05 * i, 0.0, 0.0)))
          for distance in (1e4, 1e5, 1e7)),
        Case("huge values", "odometry-nan", _scan_case(
            ranges=walls, odometry=lambda i: (math.nan, 0.0, 0.0) if i % 10 == 3 else (0.05 * i, 0.0, 0.0))),
        Case("huge values", "time-going-backwards", _scan_case(
            ranges=walls, count=60, odometry=lambda i: (0.05 * i, 0.0, 0.0),
            stamp=lambda i: 10**18 + i * 100_000_000 - (20 * 10**9 if i >= 40 else 0))),
    ]
    battery += [Case("cloud layout", name, _log(lambda folder, layout=layout, name=name:
                                                cloud_log(folder / f"{name}.mcap", **layout)))
                for name, layout in CLOUD_LAYOUTS.items()]
    battery += [
        Case("special files", "dev-zero-as-graph", lambda folder: ["/dev/zero"]),
        Case("special files", "dev-zero-as-config",
             lambda folder: ["--config", "/dev/zero", "--dump-config"]),
        Case("special files", "dev-zero-as-relations",
             lambda folder: ["evaluate", "/dev/zero", "/dev/zero"]),
        Case("special files", "fifo-as-graph", _fifo_case),
        Case("special files", "missing-file", lambda folder: [str(folder / "missing.g2o")]),
        Case("special files", "folder-as-graph", lambda folder: [str(folder)]),
    ]
    battery += [
        Case("graph text", "edge-missing-values", _graph_case("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
                                                              "EDGE_SE2 0 1 1 0\n")),
        Case("graph text", "nan-pose", _graph_case("VERTEX_SE2 0 nan 0 0\nVERTEX_SE2 1 1 0 0\n"
                                                   "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")),
        Case("graph text", "information-not-positive", _graph_case(
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1\n")),
        Case("graph text", "edge-to-unknown-vertex", _graph_case(
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n")),
        Case("graph text", "binary", _graph_case("VERTEX_SE2 0 0 0 0\x00\n")),
    ]
    battery += [
        Case("options", f"{' '.join(options)}", _graph_case(_GOOD_GRAPH, *options))
        for options in (("--iterations", "2147483648"), ("--iterations", "-1"), ("--jobs", "100000"),
                        ("--method", "newton"), ("--robust", "huber"), ("--jobs", "0"))
    ]
    battery += [Case("options", "graph-inside-the-out-folder", _graph_in_out_folder)]  # its .g2o replaced?
    battery += [
        Case("config values", text.replace("\n", " ").strip(), _config_case(text))
        for text in ("[matching]\nresolution = 1e-9\n", "[matching]\nmax_range = 1e300\n",
                     "[keyframes]\nlocal_map_keyframes = 2000000000\n",
                     "[optimizer]\niterations = 1000000000\n",
                     "[optimizer]\nmethod = 7\n", "[nonsense]\nx = 1\n", "not toml at all [[[\n")
    ]
    return battery


def run_case(case: Case, timeout: float) -> tuple[int | str, str, float]:
    """Exit code (or "timeout"), first stderr line ("!!" prefixed on a traceback), seconds."""
    with tempfile.TemporaryDirectory(prefix="hostile-") as temporary:
        folder = Path(temporary)
        arguments = case.arguments(folder)
        started = time.perf_counter()
        try:
            options = [] if arguments[0] == "evaluate" else ["--out", str(folder / "out"), "--quiet"]
            done = subprocess.run(
                [sys.executable, "-m", "pipeline.launcher", *arguments, *options],
                capture_output=True, text=True,
                timeout=timeout, cwd=REPO, stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            return "timeout", "", time.perf_counter() - started
        seconds = time.perf_counter() - started
        lines = done.stderr.splitlines()
        first = lines[0] if lines else ""
        if "Traceback" in done.stderr:
            first = "!! traceback: " + lines[-1]
        elif len(lines) > 1:
            first += f"  (+{len(lines) - 1} more lines)"
        return done.returncode, first.replace(temporary, "TMP"), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--family", action="append", help="only these families (repeatable)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds allowed per case")
    args = parser.parse_args()
    battery = [case for case in cases() if args.family is None or case.family in args.family]
    print("| family | case | exit | s | first stderr line |\n|---|---|---|---|---|", flush=True)
    per_family: dict[str, Counter[str]] = {}
    for case in battery:
        code, first, seconds = run_case(case, args.timeout)
        flag = "" if code in (0, 2, 3) else "!! "
        per_family.setdefault(case.family, Counter())[str(code)] += 1
        print(f"| {case.family} | {case.name} | {flag}{code} | {seconds:.1f} | {first[:160]} |", flush=True)
    print("\n| family | cases | exit codes |\n|---|---|---|")
    for family, codes in per_family.items():
        print(f"| {family} | {sum(codes.values())} | "
              + ", ".join(f"{code}: {count}" for code, count in sorted(codes.items())) + " |")
    total = sum(sum(codes.values()) for codes in per_family.values())
    print(f"\n{total} cases; measured on a loaded 2-core machine, timings are indicative only")


if __name__ == "__main__":
    main()
