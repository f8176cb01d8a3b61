"""Memory of a batch script: one log replayed over and over with `pipeline.replay` in one process.

    python benchmarks/batch_memory.py [LOG] [--repeats 12] [--out DIR]

LOG defaults to the bundled sample. After each replay: `gc.collect()` and glibc's `malloc_trim(0)`
(`optimizer.freed_memory.return_freed_memory`: freed memory is given back, only what is still held
counts), then the process's resident set (VmRSS) and the number of rerun recording streams still alive
(their `RecordingStream` threads). A batch that frees what each replay recorded keeps the count it had
after the first replay, and its RSS on a plateau. Linux only. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from optimizer.freed_memory import return_freed_memory  # noqa: E402
from pipeline.api import replay  # noqa: E402
from pipeline.bundled import sample_log  # noqa: E402
from tests.pipeline_fixtures import recording_streams_alive  # noqa: E402


def resident_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("log", nargs="?", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=12)
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    args = parser.parse_args()
    with (tempfile.TemporaryDirectory() as scratch,
          sample_log() if args.log is None else contextlib.nullcontext(args.log) as log):
        out = args.out or Path(scratch)
        print(f"{log}, {args.repeats} replays in one process\n")
        print("| replay | s | RSS (MB) | recording streams alive |")
        print("|---|---|---|---|")
        for index in range(1, args.repeats + 1):
            start = time.perf_counter()
            replay(log, out_dir=out)
            seconds = time.perf_counter() - start
            gc.collect()
            return_freed_memory()
            print(f"| {index} | {seconds:.1f} | {resident_mb():.0f} | {recording_streams_alive()} |",
                  flush=True)


if __name__ == "__main__":
    main()
