"""Benchmark of a fresh install's first replay: numba compiling every kernel on its first call.

    python benchmarks/first_run_bench.py [--input LOG] [--top 12]

Each row replays `--input` (default: the bundled sample log) in a new process with an empty numba cache
(`NUMBA_CACHE_DIR` in a temporary folder), as `replay -q` does:

- "cold": nothing cached, one process compiles everything (the frontend's kernels as the log needs them,
  the optimizer's at the first optimization);
- "cold, optimizer warm-up beside it": `python -m optimizer.warmup` started at the same time in a process
  of its own, as an interactive `replay` does on a fresh install (`pipeline.cli`);
- "cached": the same replay again, everything loaded from the cache.

Then the kernels that took longest to compile in the cold run (seconds, a kernel's nested compilations
included), from numba's compile events.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

REPLAY_WITH_COMPILE_EVENTS = """
import json, sys, time
from numba.core import event
stack, seconds = [], {}
class Listener(event.Listener):
    def on_start(self, data):
        function = data.data["dispatcher"].py_func
        stack.append((function.__module__ + "." + function.__qualname__, time.perf_counter()))
    def on_end(self, data):
        name, started = stack.pop()
        if not stack:  # a top-level compilation: its nested ones are inside its time
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - started
event.register("numba:compile", Listener())
from pipeline import replay
from pipeline.bundled import sample_log
path, out = sys.argv[1], sys.argv[2]
if path:
    replay(path, out_dir=out)
else:
    with sample_log() as sample:
        replay(sample, out_dir=out)
print(json.dumps(seconds))
"""


def timed_replay(log: str, cache: Path, out: Path, *, warm_up: bool) -> tuple[float, dict[str, float]]:
    """Wall seconds of one replay process (start-up included) with numba's cache in `cache`, and the
    seconds of each top-level compilation in it."""
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    started = time.perf_counter()
    helper = None
    if warm_up:
        helper = subprocess.Popen([sys.executable, "-m", "optimizer.warmup", str(cache / "warm")], cwd=REPO,
                                  env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run = subprocess.run([sys.executable, "-c", REPLAY_WITH_COMPILE_EVENTS, log, str(out)], cwd=REPO,
                         env=environment, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - started
    if helper is not None:
        helper.wait()
    return wall, json.loads(run.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--input", default="", help="a log (default: the bundled sample)")
    parser.add_argument("--top", type=int, default=12, help="kernels listed")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        cold, compiled = timed_replay(args.input, root / "cold", root / "out", warm_up=False)
        cached, _ = timed_replay(args.input, root / "cold", root / "out", warm_up=False)
        beside, compiled_beside = timed_replay(args.input, root / "beside", root / "out", warm_up=True)
    print(f"## First replay of {args.input or 'the bundled sample'} (one process each, start-up included)\n")
    print("| run | wall (s) | compiling in the replay's process (s) |")
    print("|---|---:|---:|")
    print(f"| cold | {cold:.1f} | {sum(compiled.values()):.1f} |")
    print(f"| cold, optimizer warm-up beside it | {beside:.1f} | {sum(compiled_beside.values()):.1f} |")
    print(f"| cached | {cached:.1f} | 0.0 |")
    print(f"\n## The {args.top} longest compilations of the cold run\n")
    print("| kernel | s |")
    print("|---|---:|")
    for name, seconds in sorted(compiled.items(), key=lambda item: -item[1])[: args.top]:
        print(f"| `{name}` | {seconds:.2f} |")


if __name__ == "__main__":
    main()
