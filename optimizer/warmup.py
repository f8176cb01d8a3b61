"""Compiling the optimizer's kernels into numba's cache ahead of need, in a process of its own.

On a fresh install (or after an upgrade, which changes the sources numba's cache is keyed on) every numba
kernel compiles on its first call: on a 2-core machine the bundled sample's first replay spent ~15 s
compiling the laser frontend's kernels, then ~13 s compiling the optimizer's at its final optimization,
one after the other. The optimizer's do not depend on the log: `python -m optimizer.warmup MARKER`
compiles them on the other core while the frontend compiles its own (numba's compiler lock is per
process), and the replay then loads them from the cache (numba looks there at a kernel's first call).
The bundled sample's first interactive replay took 18–22 s instead of 30–36 s.

`MARKER` is a file written once every kernel is cached (`marker_path`: named after what numba's cache is
keyed on), so that later replays do not start the process again.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

import optimizer.jit_cache  # noqa: F401  (first: chooses numba's cache folder before numba is loaded)

if TYPE_CHECKING:
    from optimizer.graph import PoseGraph

PACKAGE = Path(__file__).resolve().parent
"""The optimizer's sources."""
LOOP_POSES = 48
"""Poses of the warm-up graph: a square driven twice, small enough to optimize in a fraction of a second
once compiled."""


def marker_path(package: Path = PACKAGE) -> Path:
    """The file that says the optimizer's kernels are in numba's cache: in the cache folder of the
    kernels of `package` (this one), named after the numba and Python versions and the size and time of
    each of its sources (what numba's cache entries are keyed on)."""
    import numba

    key = hashlib.sha256(f"{numba.__version__} {sys.version}".encode())
    for source in sorted(package.glob("*.py")):
        stat = source.stat()
        key.update(f"{source.name} {stat.st_size} {stat.st_mtime_ns}".encode())
    chosen = os.environ.get("NUMBA_CACHE_DIR")  # `optimizer.jit_cache` set it where the package is read-only
    folder = Path(chosen) if chosen else package / "__pycache__"
    return folder / f"sgdslam-optimizer-warm-{key.hexdigest()[:16]}"


def square_laps(poses: int = LOOP_POSES, seed: int = 0) -> PoseGraph:
    """Two laps of a square (`poses` a multiple of 8: 1 m odometry steps, turning at its corners), each
    pose of the first lap joined by a loop closure to the same place on the second; a noisy start."""
    from optimizer.graph import PoseGraph

    rng = np.random.default_rng(seed)
    headings = np.repeat(np.arange(8) % 4 * (np.pi / 2), poses // 8)
    steps = np.column_stack([np.ones(poses - 1), np.zeros(poses - 1), np.diff(headings)])
    truth = np.zeros((poses, 3))
    for k, (step, heading) in enumerate(zip(steps, headings[:-1], strict=True)):
        truth[k + 1] = truth[k] + [np.cos(heading) * step[0], np.sin(heading) * step[0], step[2]]
    first, second = np.arange(poses // 2), np.arange(poses // 2, poses)
    edge_from = np.concatenate([np.arange(poses - 1), first])
    edge_to = np.concatenate([np.arange(1, poses), second])
    measurements = np.concatenate([steps, np.zeros((len(first), 3))])
    measurements += rng.normal(0.0, 0.01, measurements.shape)
    information = np.repeat(np.diag([100.0, 100.0, 400.0])[None], len(edge_from), axis=0)
    start = truth + rng.normal(0.0, 0.3, truth.shape)
    return PoseGraph.build(np.arange(poses), start, edge_from, edge_to, measurements, information)


def warm_up() -> None:
    """Optimize `square_laps` as a replay's keyframe graph is optimized (the default method from several
    starts: the paper's SGD, the tree SGD, the Gauss-Newton polish, which the online loop closing uses
    too), which compiles (or loads) the kernels that takes."""
    from optimizer.solve import optimize

    graph = square_laps()
    for _ in optimize(graph, starts={"first": graph.poses, "second": square_laps(seed=1).poses}):
        pass


def start_in_background() -> subprocess.Popen[bytes] | None:
    """`python -m optimizer.warmup MARKER` in a process of its own (silent, from this package's folder, so
    that it imports this copy), or None: the marker says the kernels are cached, the machine has one core
    (the process would only take time from the replay), or it could not be started."""
    if (os.cpu_count() or 1) < 2:
        return None
    marker = marker_path()
    if marker.exists():
        return None
    try:
        return subprocess.Popen([sys.executable, "-m", "optimizer.warmup", str(marker)],
                                cwd=PACKAGE.parent, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return None


@contextmanager
def warming_up(enabled: bool) -> Iterator[None]:
    """`start_in_background` (if `enabled`) for the time of the block; a warm-up still running at its end
    is stopped (what it cached stays cached: numba writes each entry whole)."""
    process = start_in_background() if enabled else None
    try:
        yield
    finally:
        if process is not None:
            if process.poll() is None:
                process.terminate()
            process.wait()


def main(argv: list[str]) -> int:
    warm_up()
    if len(argv) > 1:
        Path(argv[1]).touch()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
