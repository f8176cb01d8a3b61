"""Replays of several inputs: one after another in this process, in parallel in a pool of processes, or
as tasks on a Ray cluster (`RayOptions`; `pipeline.ray_batch`).

A failing input never stops the others: every input ends as a `BatchOutcome`, its summary or its error.
Library code: nothing is printed; callers report the outcomes.

A pool interrupted in the calling process (Ctrl-C, or SIGTERM turned into `KeyboardInterrupt` as the
command does) stops its workers before the interrupt propagates: each gets SIGTERM, which in a worker
raises `KeyboardInterrupt` so its staged outputs are removed, then it exits; one still running after
`STOP_GRACE_S` is killed, and whatever a worker left is cleaned up here. No worker publishes outputs
afterwards, and with the workers gone the forkserver and the resource tracker (which live as long as some
process holds their pipes) exit too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import signal
import socket
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from pipeline.api import (
    DEFAULT_OUT_DIR,
    KNOWN_ERRORS,
    IterationCallback,
    ReplayStats,
    ScanCallback,
    input_kind,
    replay,
)
from pipeline.config import ReplayConfig
from pipeline.errors import PipelineError
from pipeline.outputs import (
    install_stop_signals,
    output_stem,
    raised_by_interrupt,
    recover_outputs,
    stop_signals_held,
)
from pipeline.warning_tally import with_notes

if TYPE_CHECKING:  # multiprocessing and the process pool are imported only by a run of several inputs
    from concurrent.futures import Future, ProcessPoolExecutor
    from multiprocessing.process import BaseProcess

OutcomeCallback = Callable[["BatchOutcome"], None]


@dataclass(frozen=True)
class BatchOutcome:
    """How the replay of one input ended: `stats`, `summary` and `outputs` when it succeeded, `error` (one
    line) when it failed, and `traceback` too when the failure was a bug rather than bad input."""

    input_path: Path
    kind: str
    """"log" or "graph" (see `pipeline.api.input_kind`)."""
    stats: ReplayStats | None = None
    summary: Mapping[str, Any] | None = None
    outputs: Mapping[str, Path] = field(default_factory=dict)
    error: str | None = None
    traceback: str | None = None
    host: str | None = None
    """The host name of the machine that replayed the input, when it ran as part of a batch."""

    @property
    def ok(self) -> bool:
        return self.error is None

    @classmethod
    def failure(cls, path: Path, error: BaseException, *, unexpected: bool = False) -> BatchOutcome:
        message = with_notes(error)
        if unexpected:
            message = f"internal error: {type(error).__name__}: {message}"
        trace = "".join(traceback.format_exception(error)) if unexpected else None
        return cls(path, input_kind(path), error=message, traceback=trace)

    @classmethod
    def crashed(cls, path: Path, where: str, error: BaseException) -> BatchOutcome:
        """The input's `where` ("worker process", "Ray task") died, or its outcome could not come back."""
        return cls(path, input_kind(path), error=f"{where} failed: {one_line(error)}")

    def to_json(self) -> dict[str, Any]:
        """The machine-readable form: the summary written to `<stem>.json` with `"ok": true`, or the
        input, `"ok": false` and the error."""
        host = {} if self.host is None else {"host": self.host}
        if self.summary is None:
            return {"input": str(self.input_path), "ok": False, "error": self.error, **host}
        return {"input": str(self.input_path), "ok": True, "kind": self.kind, **self.summary, **host}


@dataclass(frozen=True)
class RayOptions:
    """Run a batch on Ray: each input one task."""

    address: str | None = None
    """The cluster to connect to ("auto", "host:port", "ray://host:port"); None or "local" starts a local
    Ray runtime for the batch. A runtime already initialised in this process is used as it is."""
    cpus_per_task: float = 1.0
    retries: int = 1
    """How many times a task that crashed (an unexpected exception, or its worker died) is run again; bad
    input (our own errors) is not retried."""


def one_line(error: BaseException) -> str:
    """An exception's message on one line (some name a file and quote a multi-line reason)."""
    return " ".join(str(error).split()) or type(error).__name__


def refuse_clashing_outputs(paths: Sequence[Path], out_dir: str | Path) -> None:
    """Raise `PipelineError` naming the first two inputs whose outputs would have the same names (same
    stem) in `out_dir`: one would overwrite the other."""
    first_with_stem: dict[str, Path] = {}
    for path in paths:
        first = first_with_stem.setdefault(output_stem(path), path)
        if first is path:
            continue
        if Path(first).resolve() == Path(path).resolve():
            raise PipelineError(f"{path} is listed twice (as {first} and {path}): name each input once")
        raise PipelineError(f"{first} and {path} would write the same outputs ({output_stem(path)}.*) in "
                            f"{out_dir}; replay them into different folders (--out)")


def run_one(
    path: str | Path,
    config: ReplayConfig | None = None,
    *,
    out_dir: str | Path = DEFAULT_OUT_DIR,
    on_scan: ScanCallback | None = None,
    on_iteration: IterationCallback | None = None,
    catch_unexpected: bool = True,
    replay_options: Mapping[str, Any] | None = None,
) -> BatchOutcome:
    """Replay one input, turning its failure into the outcome; with `catch_unexpected=False` only our own
    errors are (anything else, a bug, propagates with its traceback). `replay_options`: more keyword
    arguments of `pipeline.api.replay` (a session: `map`, `continue_from`, `initial_pose`)."""
    path = Path(path)
    try:
        result = replay(path, config, out_dir=out_dir, on_scan=on_scan, on_iteration=on_iteration,
                        **(replay_options or {}))
    except KNOWN_ERRORS as error:
        return BatchOutcome.failure(path, error)
    except Exception as error:
        if raised_by_interrupt(error):  # a stop signal, not this input's failure: the batch stops
            raise KeyboardInterrupt from error
        if not catch_unexpected:
            raise
        return BatchOutcome.failure(path, error, unexpected=True)
    return BatchOutcome(result.input_path, result.kind, result.stats, dict(result.summary),
                        dict(result.outputs))


def run_one_on_this_host(
    path: str | Path,
    config: ReplayConfig | None = None,
    *,
    out_dir: str | Path = DEFAULT_OUT_DIR,
    catch_unexpected: bool = True,
) -> BatchOutcome:
    """`run_one`, the outcome naming this machine (`BatchOutcome.host`): what a batch's workers run."""
    return with_this_host(run_one(path, config, out_dir=out_dir, catch_unexpected=catch_unexpected))


def with_this_host(outcome: BatchOutcome) -> BatchOutcome:
    return dataclasses.replace(outcome, host=socket.gethostname())


def run_batch(
    paths: Sequence[str | Path],
    config: ReplayConfig | None = None,
    *,
    out_dir: str | Path = DEFAULT_OUT_DIR,
    jobs: int = 1,
    ray: RayOptions | None = None,
    on_done: OutcomeCallback | None = None,
) -> list[BatchOutcome]:
    """Replay every input (outputs side by side in `out_dir`), `jobs` at a time or as Ray tasks (`ray`);
    the outcomes in input order, each naming the host that replayed it.

    With `jobs` > 1 the inputs run in worker processes (forkserver where available, else spawn: never a
    fork of a process that may hold rerun's or numba's threads). With `ray` each input is one Ray task
    (`pipeline.ray_batch.run_batch_on_ray`; `out_dir` must be reachable from every node). `on_done` is
    called in this process as each input finishes. Raises `PipelineError` before starting when two inputs
    would write the same output names, or when Ray is asked for and not installed or not reachable.
    """
    if jobs < 1:
        raise PipelineError(f"jobs must be >= 1, got {jobs}")
    if ray is not None and jobs > 1:
        raise PipelineError("choose jobs (worker processes here) or ray (tasks on a cluster), not both")
    inputs = [Path(path) for path in paths]
    refuse_clashing_outputs(inputs, out_dir)
    config = config if config is not None else ReplayConfig()
    if ray is not None:
        from pipeline.ray_batch import run_batch_on_ray

        return run_batch_on_ray(inputs, config, out_dir=Path(out_dir), options=ray, on_done=on_done)
    if jobs == 1 or len(inputs) <= 1:
        outcomes = []
        for path in inputs:
            outcome = run_one_on_this_host(path, config, out_dir=out_dir)
            outcomes.append(outcome)
            if on_done is not None:
                on_done(outcome)
        return outcomes
    return _run_in_pool(inputs, config, Path(out_dir), min(jobs, len(inputs)), on_done)


STOP_GRACE_S = 5.0
"""How long an interrupted pool's workers have to clean up after SIGTERM before they are killed."""


def _run_in_pool(inputs: list[Path], config: ReplayConfig, out_dir: Path, workers: int,
                 on_done: OutcomeCallback | None) -> list[BatchOutcome]:
    """The inputs in a pool of `workers` processes. A worker that dies (killed, out of memory) breaks the
    pool, and every input not finished by then with it: those go to a fresh pool, once more each; an
    input lost twice failed."""
    outcomes: list[BatchOutcome | None] = [None] * len(inputs)
    pending = list(range(len(inputs)))
    for attempt in range(MAX_POOL_ATTEMPTS):
        pending = _pool_round(inputs, pending, config, out_dir, workers, outcomes, on_done,
                              last=attempt == MAX_POOL_ATTEMPTS - 1)
        if not pending:
            break
    return [outcome for outcome in outcomes if outcome is not None]


MAX_POOL_ATTEMPTS = 2
"""Pools an input may be lost with before it counts as failed (its own worker dying, or another's)."""


def _pool_round(inputs: list[Path], indices: list[int], config: ReplayConfig, out_dir: Path, workers: int,
                outcomes: list[BatchOutcome | None], on_done: OutcomeCallback | None, *,
                last: bool) -> list[int]:
    """Run `inputs[indices]` in one pool, filling `outcomes`; the indices lost with a broken pool (failed
    instead on the `last` round)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    from numba import config as numba_config

    # numba's count (NUMBA_NUM_THREADS, else the cores), shared by the workers.
    threads = max(1, numba_config.NUMBA_NUM_THREADS // workers)  # type: ignore[attr-defined]
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(max_workers=min(workers, len(indices)),
                               mp_context=multiprocessing.get_context(method),
                               initializer=_init_worker, initargs=(threads,))
    broken: list[int] = []
    try:
        futures: dict[Future[BatchOutcome], int] = {
            pool.submit(_run_in_worker, inputs[index], config, out_dir): index for index in indices
        }
        for future in as_completed(futures):
            index = futures[future]
            try:
                outcome = future.result()
            except Exception as error:  # a dead worker broke the pool, or the result did not pickle
                if isinstance(error, BrokenProcessPool):
                    broken.append(index)
                    if not last:
                        continue
                outcome = BatchOutcome.crashed(inputs[index], "worker process", error)
            outcomes[index] = outcome
            if on_done is not None:
                on_done(outcome)
    except BaseException:  # Ctrl-C or SIGTERM here: stop every worker before the interrupt goes on
        with stop_signals_held(redeliver=False):  # a second Ctrl-C must not cut the clean-up short
            _stop_pool(pool, inputs, out_dir)
        raise
    if broken:  # a dead worker may have left its staging folder and lock
        _stop_pool(pool, [inputs[index] for index in broken], out_dir)
    else:
        pool.shutdown(wait=True)
    return [] if last else sorted(broken)


def _stop_pool(pool: ProcessPoolExecutor, inputs: list[Path], out_dir: Path) -> None:
    """SIGTERM every worker, wait up to `STOP_GRACE_S` for them to clean up and exit, kill the rest, and
    clean up whatever any of them left."""
    workers = _pool_processes(pool)
    pool.shutdown(wait=False, cancel_futures=True)
    for worker in workers:
        with contextlib.suppress(OSError, ValueError):
            worker.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for worker in workers:
        worker.join(max(0.0, deadline - time.monotonic()))
    # A forkserver's workers are its children, not ours: once a signal to the whole process group has
    # ended the forkserver, `join` and `is_alive` say they ended while they may still be cleaning up.
    running = _wait_until_gone([worker.pid for worker in workers if worker.pid is not None], deadline)
    for pid in running:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
    # until they are gone: a killed worker's lock holds until its process ends
    _wait_until_gone(running, time.monotonic() + STOP_GRACE_S)
    # Not only after the killed ones: a worker that died otherwise mid-write (the OS's OOM killer) left its
    # staging folder and lock too.
    remove_partial_outputs(out_dir, {output_stem(path) for path in inputs})


def _wait_until_gone(pids: Sequence[int], deadline: float) -> list[int]:
    """Wait until none of these processes runs any more, or until `deadline` (`time.monotonic`); the ones
    still running."""
    running = list(pids)
    while (running := [pid for pid in running if _running(pid)]) and time.monotonic() < deadline:
        time.sleep(0.01)
    return running


def _running(pid: int) -> bool:
    """Whether process `pid` exists and has not ended (a zombie waiting to be reaped has)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # Linux: the state letter follows the command name, which is in parentheses
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def remove_partial_outputs(out_dir: Path, stems: set[str]) -> list[str]:
    """Clean up what replays of these stems killed mid-write left in `out_dir` (a staging folder, a lock
    file: see `pipeline.outputs`) the way the next replay of the same outputs would: a staged set that was
    complete is published, anything else deleted. Returns the stems cleaned up."""
    try:
        names = os.listdir(out_dir)  # once, not once per stem: batches have thousands
    except OSError:
        return []
    matches = (_LEFT_BEHIND.fullmatch(name) for name in names)
    left_by = {match["stem"] for match in matches if match is not None and match["stem"] in stems}
    cleaned = []
    for stem in sorted(left_by):
        with contextlib.suppress(PipelineError):  # still held by a live process (a worker Ray could not kill)
            recover_outputs(out_dir, stem)
            cleaned.append(stem)
    return cleaned


_LEFT_BEHIND = re.compile(r"\.(?P<stem>.+?)(\.staging-.*|\.lock)")


def _pool_processes(pool: ProcessPoolExecutor) -> list[BaseProcess]:
    """The pool's worker processes: the executor's own table (`ProcessPoolExecutor` keeps it, a broken
    pool's too, until `shutdown`, which `_stop_pool` calls after reading it)."""
    return list(pool._processes.values())


def limit_threads(threads: int) -> contextlib.AbstractContextManager[Any]:
    """Keep a worker to its share of the cores: `threads` for our kernels (graph files' parsing, wide
    scan-matching searches share their work by numba's count), and one for BLAS, whose threads only add
    hand-off latency to our small linear algebra (as in the command's main()). The BLAS limit holds until
    the returned limiter exits."""
    from numba import config as numba_config
    from threadpoolctl import threadpool_limits

    numba_config.NUMBA_NUM_THREADS = threads  # type: ignore[attr-defined]
    return threadpool_limits(limits=1, user_api="blas")


_worker_replaying = False
"""Whether this worker is replaying an input now: a stop signal then unwinds it (staged outputs removed)
rather than ending the process at once."""
_worker_stopping = False
"""Whether a stop signal is unwinding the replay: later ones (Ctrl-C to the group, then the parent's
SIGTERM) must not interrupt that clean-up."""


def _init_worker(threads: int) -> None:
    # Several workers each spinning a thread per core would fight over the cores: each gets its share.
    limit_threads(threads)  # for the worker's whole life
    install_stop_signals(_on_worker_stop_signal)
    from pipeline.launcher import arrow_without_pandas

    arrow_without_pandas()


def _on_worker_stop_signal(signum: int, frame: FrameType | None) -> None:
    """SIGTERM from the parent stopping the pool, or Ctrl-C to the whole process group."""
    global _worker_stopping
    if not _worker_replaying:
        os._exit(128 + signum)  # idle between inputs: nothing to clean up, and no traceback to print
    if _worker_stopping and signum != signal.SIGALRM:
        return
    _worker_stopping = True
    raise KeyboardInterrupt


def _run_in_worker(path: Path, config: ReplayConfig, out_dir: Path) -> BatchOutcome:
    """`run_one_on_this_host` in a pool's worker: a stop signal unwinds the replay, which removes its staged
    outputs, and then ends the worker instead of letting it take the next input."""
    global _worker_replaying
    _worker_replaying = True
    try:
        return run_one_on_this_host(path, config, out_dir=out_dir)
    except KeyboardInterrupt:
        os._exit(128 + signal.SIGTERM)
    finally:
        _worker_replaying = False
