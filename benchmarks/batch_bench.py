"""Benchmark of batches (issue 14): the same inputs through `replay --jobs 2` and `replay --ray`.

    python benchmarks/batch_bench.py [--logs 4] [--graphs 36] [--shared ../shared] [--out DIR] [--no-cluster]

Inputs: copies of the bundled sample log (the first 1000 scans of CSAIL) and of the shared 2D pose graphs
(M3500, FR079, CSAIL, pg1, w100, pose2example), 40 by default (a sample log takes about 20 times as long as
a graph). Each run is the whole `replay` command in a fresh process (`--inputs LIST --quiet
--repair-information`, pg1 needs it), its wall time from start to exit, numba's cache already warm:

1. `--jobs 2`: two worker processes on this machine;
2. `--ray`: a local Ray runtime started by the command (2 CPUs, one task per input);
3. `--ray ADDRESS` on a two-node Ray cluster started on this machine (`ray.cluster_utils.Cluster`: two
   raylets of 1 CPU each, loopback only), unless `--no-cluster`;

and, in this process, what Ray itself costs: starting and stopping a runtime, and the round trip of an
empty task. The outputs of the runs are compared (g2o and TUM bytes, JSON apart from timings and paths).
Needs the `ray` extra. Prints markdown tables; timings on a shared machine vary from run to run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE_LOG = REPO / "pipeline" / "samples" / "csail_sample.mcap"
SHARED_GRAPHS = ("M3500.g2o", "FR079.g2o", "CSAIL.g2o", "pg1.g2o", "w100.graph", "pose2example.txt")
EMPTY_TASKS = 200
TIMINGS = ("wall_time_s", "optimize_time_s", "outputs")
"""JSON keys that differ between two runs of the same input into different folders."""


def make_inputs(folder: Path, shared: Path, logs: int, graphs: int) -> Path:
    """Copies with distinct stems (outputs are named after them) and the list naming them."""
    folder.mkdir(parents=True)
    paths = []
    for index in range(logs):
        paths.append(folder / f"log{index:02d}_{SAMPLE_LOG.name}")
        shutil.copyfile(SAMPLE_LOG, paths[-1])
    sources = [shared / "data" / "posegraphs" / "2d" / name for name in SHARED_GRAPHS]
    sources = [path for path in sources if path.exists()]
    if graphs and not sources:
        raise SystemExit(f"batch_bench: the graphs need ../shared/data/posegraphs/2d ({shared} has none)")
    for index in range(graphs):
        source = sources[index % len(sources)]
        paths.append(folder / f"graph{index:02d}_{source.name}")
        shutil.copyfile(source, paths[-1])
    listing = folder / "inputs.txt"
    listing.write_text("".join(f"{path}\n" for path in paths))
    return listing


def run_replay(listing: Path, out: Path, *options: str) -> float:
    """The whole command in a fresh process; its wall time."""
    command = [sys.executable, "-m", "pipeline.cli", "--inputs", str(listing), "--out", str(out), "--quiet",
               "--repair-information", "--allow-unconverged", *options]
    started = time.perf_counter()
    completed = subprocess.run(command, cwd=REPO, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({completed.returncode}):\n{completed.stderr}")
    return seconds


def batch_figures(out: Path) -> tuple[float, int, set[str]]:
    """Σ of the inputs' own replay times, the rows, and the hosts, from batch_summary.parquet."""
    import pyarrow.parquet as pq

    rows = pq.read_table(out / "batch_summary.parquet").to_pylist()
    return sum(row["time_total_s"] or 0.0 for row in rows), len(rows), {row["host"] for row in rows}


def comparable(out: Path) -> dict[str, object]:
    found: dict[str, object] = {}
    for path in sorted(out.iterdir()):
        if path.suffix in (".g2o", ".tum"):
            found[path.name] = path.read_bytes()
        elif path.suffix == ".json":
            found[path.name] = {key: value for key, value in json.loads(path.read_text()).items()
                                if key not in TIMINGS}
    return found


def ray_costs() -> tuple[float, float, float]:
    """Seconds to start a local runtime, to stop it, and per empty task (submitted together, warm)."""
    import ray

    started = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False,
             logging_level="ERROR")
    start_s = time.perf_counter() - started

    @ray.remote
    def empty() -> None:
        return None

    ray.get([empty.remote() for _ in range(EMPTY_TASKS)])  # start the workers
    started = time.perf_counter()
    ray.get([empty.remote() for _ in range(EMPTY_TASKS)])
    per_task_s = (time.perf_counter() - started) / EMPTY_TASKS
    started = time.perf_counter()
    ray.shutdown()
    return start_s, time.perf_counter() - started, per_task_s


def cluster_run(listing: Path, out: Path) -> float:
    """`replay --ray ADDRESS` on a two-node cluster (1 CPU each) started here on the loopback interface.
    Ray turns a 127.0.0.1 address into the machine's network address unless told that this is a
    single-machine cluster (RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0, set for the nodes and the command)."""
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "node_ip_address": "127.0.0.1",
                                                            "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
        cluster.wait_for_nodes()
        return run_replay(listing, out, "--ray", cluster.address)
    finally:
        cluster.shutdown()
        del os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", type=int, default=4, help="copies of the bundled sample log")
    parser.add_argument("--graphs", type=int, default=36, help="copies of the shared pose graphs")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--out", type=Path, default=None, help="keep the inputs and outputs here")
    parser.add_argument("--no-cluster", action="store_true", help="skip the two-node cluster run")
    args = parser.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    for variable in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(variable, "1")
    os.chdir(REPO)  # Ray workers started from this process import pipeline from the driver's folder
    sys.path.insert(0, str(REPO))

    scratch = Path(tempfile.mkdtemp(prefix="batch_bench_")) if args.out is None else args.out
    try:
        listing = make_inputs(scratch / "inputs", args.shared, args.logs, args.graphs)
        inputs = args.logs + args.graphs
        print(f"## {inputs} inputs ({args.logs} sample logs, {args.graphs} pose graphs), 2 CPUs\n")
        print("| run | wall s | Σ replay s | (wall − Σ/2)/input s | outputs equal to --jobs 2 |")
        print("|---|---:|---:|---:|---|", flush=True)
        reference: dict[str, object] = {}

        def report(label: str, wall: float, out: Path) -> None:
            replay_sum, rows, _ = batch_figures(out)
            assert rows == inputs
            outputs = comparable(out)
            if not reference:
                reference.update(outputs)
            same = "yes" if outputs == reference else "NO"
            overhead = (wall - replay_sum / 2) / inputs
            print(f"| {label} | {wall:.1f} | {replay_sum:.1f} | {overhead:.3f} | {same} |", flush=True)

        report("replay --jobs 2", run_replay(listing, scratch / "jobs", "--jobs", "2"), scratch / "jobs")
        report("replay --ray (local runtime, 2 CPUs)", run_replay(listing, scratch / "ray", "--ray"),
               scratch / "ray")
        if not args.no_cluster:
            report("replay --ray ADDRESS (2 nodes × 1 CPU)",
                   cluster_run(listing, scratch / "cluster"), scratch / "cluster")
        start_s, stop_s, per_task_s = ray_costs()
        print("\n| Ray cost | seconds |\n|---|---:|")
        print(f"| start a local runtime (ray.init) | {start_s:.2f} |")
        print(f"| stop it (ray.shutdown) | {stop_s:.2f} |")
        print(f"| one empty task ({EMPTY_TASKS} submitted at once, warm workers) | {per_task_s:.5f} |")
    finally:
        if args.out is None:
            shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
