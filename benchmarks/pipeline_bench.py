"""Benchmark of the replay pipeline (issue 5): recording cost, recording size, the sample's cold start.

    python benchmarks/pipeline_bench.py [--out benchmarks/results] [--shared ../shared]

1. ACES (`../shared/data/logs/aces/aces.mcap`) through `replay_log`: the share of the run spent writing the
   recording (scans as processed, every optimizer iteration, maps, closing the file).
2. A generated 10,000-pose grid world through `replay_graph` with 100 SGD iterations then the polish: the
   size of the `.rrd`, every iteration logged.
3. `replay` with no argument (the bundled sample) in a fresh process with an empty numba cache (the first
   run after an install, JIT compilation included), then again warm.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from threadpoolctl import threadpool_limits  # noqa: E402

from optimizer.graph_files import write_g2o  # noqa: E402
from optimizer.gridworld import generate_grid_world  # noqa: E402
from pipeline.replay_graph import replay_graph  # noqa: E402
from pipeline.replay_log import replay_log  # noqa: E402

RECORDING_SHARE_TARGET = 0.20
RRD_SIZE_TARGET_MB = 200.0
COLD_START_TARGET_S = 30.0


RECORDING_STAGES = ("record_scans", "record_iterations", "record_maps", "record_close")
"""The stages of `replay_log`'s wall time spent writing the recording."""


def recording_share(aces: Path, out: Path) -> tuple[float, float, dict[str, float]]:
    times = replay_log(aces, out_dir=out).wall_time
    return sum(times[stage] for stage in RECORDING_STAGES), times["total"], times


def rrd_size(out: Path) -> tuple[float, int]:
    out.mkdir(parents=True, exist_ok=True)
    graph_path = out / "grid10k.g2o"
    write_g2o(graph_path, generate_grid_world(10_000, seed=0).graph)
    result = replay_graph(graph_path, out_dir=out, method="sgd+gn", iterations=100)
    return result.outputs.rrd.stat().st_size / 1e6, len(result.iterations)


def cold_start(out: Path) -> tuple[float, float]:
    """`replay` on the bundled sample from a copy of the package with no numba cache, then warm."""
    with tempfile.TemporaryDirectory() as scratch:
        copy = Path(scratch) / "repo"
        shutil.copytree(REPO, copy, ignore=shutil.ignore_patterns("__pycache__", ".git", ".venv", "results",
                                                                  "recordings"))
        environment = {**os.environ, "PYTHONPATH": str(copy)}
        timings = []
        for _ in range(2):
            started = time.perf_counter()
            subprocess.run([sys.executable, "-m", "pipeline.cli", "--out", str(out), "--quiet"], cwd=copy,
                           env=environment, check=True, stdin=subprocess.DEVNULL)
            timings.append(time.perf_counter() - started)
    return timings[0], timings[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cold, warm = cold_start(args.out / "sample")
    with threadpool_limits(limits=1, user_api="blas"):
        replay_log(REPO / "pipeline" / "samples" / "csail_sample.mcap", out_dir=args.out / "warmup")
        recording, total, times = recording_share(args.shared / "data/logs/aces/aces.mcap", args.out / "aces")
        size_mb, iterations = rrd_size(args.out / "grid")
    print("| figure | measured | target | met |")
    print("|---|---|---|---|")
    share = recording / total
    print(f"| recording share of the ACES replay | {share:.1%} ({recording:.2f} s of {total:.1f} s) "
          f"| ≤ {RECORDING_SHARE_TARGET:.0%} | {'yes' if share <= RECORDING_SHARE_TARGET else 'no'} |")
    print(f"| .rrd of a 10,000-pose graph, {iterations} iterations logged | {size_mb:.1f} MB "
          f"| ≤ {RRD_SIZE_TARGET_MB:.0f} MB | {'yes' if size_mb <= RRD_SIZE_TARGET_MB else 'no'} |")
    print(f"| `replay` (bundled sample), empty numba cache | {cold:.1f} s | ≤ {COLD_START_TARGET_S:.0f} s "
          f"| {'yes' if cold <= COLD_START_TARGET_S else 'no'} |")
    print(f"| `replay` (bundled sample), warm | {warm:.1f} s | | |")
    print(f"\nACES stage times (s): {', '.join(f'{k} {v:.2f}' for k, v in times.items())}")


if __name__ == "__main__":
    main()
