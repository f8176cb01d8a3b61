"""Memory of a batch script: one log replayed over and over with `pipeline.replay` in one process.

    python benchmarks/batch_memory.py [LOG] [--repeats 12] [--out DIR]

LOG defaults to the bundled sample. After each replay: `gc.collect()` and glibc's `malloc_trim(0)` (so
that freed memory is given back and only what is still held counts), then the process's resident set
(VmRSS) and the number of rerun recording streams still alive (its `RecordingStream` threads, one per
stream, named in /proc/self/task/*/comm). A batch that frees what each replay recorded keeps one stream
(rerun's own global one, idle) and its RSS on a plateau. Linux only. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import tempfile
import time
from pathlib import Path

from pipeline.api import replay

SAMPLE_LOG = Path(__file__).resolve().parents[1] / "pipeline" / "samples" / "csail_sample.mcap"


def resident_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def recording_streams() -> int:
    names = (task / "comm" for task in Path("/proc/self/task").iterdir())
    return sum(1 for name in names if name.read_text().strip() == "RecordingStream")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("log", nargs="?", type=Path, default=SAMPLE_LOG)
    parser.add_argument("--repeats", type=int, default=12)
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    args = parser.parse_args()
    libc = ctypes.CDLL("libc.so.6")
    with tempfile.TemporaryDirectory() as scratch:
        out = args.out or Path(scratch)
        print(f"{args.log}, {args.repeats} replays in one process\n")
        print("| replay | s | RSS (MB) | recording streams alive |")
        print("|---|---|---|---|")
        for index in range(1, args.repeats + 1):
            start = time.perf_counter()
            replay(args.log, out_dir=out)
            seconds = time.perf_counter() - start
            gc.collect()
            libc.malloc_trim(0)
            print(f"| {index} | {seconds:.1f} | {resident_mb():.0f} | {recording_streams()} |", flush=True)


if __name__ == "__main__":
    main()
