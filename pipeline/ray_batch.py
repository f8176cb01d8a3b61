"""A batch of replays on a Ray cluster: each input one task, retried when it crashes or its worker dies.

Ray is an optional dependency (`pip install '.[ray]'`), imported only here and only when asked for. The
tasks run `pipeline.batch.run_one_on_this_host` in the driver's working folder, so relative paths mean
what they mean on the command line and the outputs equal those of a local `replay` byte for byte; every
node must have sgdslam installed and reach the inputs and the output folder at the same paths.

Library code: returns the outcomes, raises `PipelineError`; nothing is printed.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from pipeline.batch import BatchOutcome, limit_threads, one_line, remove_partial_outputs, run_one_on_this_host
from pipeline.config import ReplayConfig
from pipeline.errors import PipelineError
from pipeline.outputs import output_stem, prepare_output_dir

if TYPE_CHECKING:
    from pipeline.batch import RayOptions

RAY_INSTALL_HINT = "pip install 'sgdslam[ray]' (from a checkout: pip install '.[ray]')"
LOCAL_ADDRESS = "local"
CANCEL_GRACE_S = 10.0
"""How long cancelled tasks get to stop by themselves (and remove their temporary outputs) before their
workers are killed."""


ReplayOne = Callable[..., BatchOutcome]
"""What a task runs for its input: `run_one_on_this_host`, or a wrapper taking its arguments."""


def run_batch_on_ray(
    inputs: Sequence[Path],
    config: ReplayConfig,
    *,
    out_dir: Path,
    options: RayOptions,
    on_done: Callable[[BatchOutcome], None] | None = None,
    replay_one: ReplayOne = run_one_on_this_host,
) -> list[BatchOutcome]:
    """Replay each input as one Ray task (`options.cpus_per_task` CPUs, `options.retries` retries); the
    outcomes in input order. A task still failing after its retries becomes a failed outcome, the others
    go on. When this call is interrupted (KeyboardInterrupt) or `on_done` raises, the outstanding tasks are
    cancelled, completed outputs stay and no partial output file is left; the exception propagates.

    Callers normally go through `pipeline.batch.run_batch(..., ray=RayOptions(...))`, which checks the
    output names first. `replay_one` is what each task runs (a wrapper can add per-task setup).
    """
    if options.cpus_per_task <= 0:
        raise PipelineError(f"cpus per task must be > 0, got {options.cpus_per_task}")
    if options.retries < 0:
        raise PipelineError(f"retries must be >= 0, got {options.retries}")
    try:
        import ray
    except ImportError as error:
        raise PipelineError(f"running on Ray needs the ray package: {RAY_INSTALL_HINT}") from error
    started_here = _connect(ray, options.address)
    try:
        if started_here and options.address in (None, LOCAL_ADDRESS):
            _refuse_tasks_larger_than_this_machine(ray, options.cpus_per_task)
        prepare_output_dir(out_dir)  # here, not by a task: a failed replay removes a folder it created
        return _run_tasks(ray, list(inputs), config, out_dir, options, on_done, replay_one)
    finally:
        if started_here:
            ray.shutdown()
        # A worker killed mid-task (and then retried, or cancelled by force) could not remove its temporaries.
        remove_partial_outputs(out_dir, {output_stem(path) for path in inputs})


def _connect(ray: ModuleType, address: str | None) -> bool:
    """Start or join a Ray runtime unless this process already has one; whether this call started it."""
    if ray.is_initialized():
        return False
    local = address in (None, LOCAL_ADDRESS)
    # Ray reports usage to its authors unless told not to; a replay started on someone's behalf should not.
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    settings: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                "logging_level": logging.ERROR}
    if local:
        # A runtime for this machine alone: nothing in it needs to listen beyond the loopback interface.
        settings["_node_ip_address"] = "127.0.0.1"
    # "auto" is the cluster RAY_ADDRESS names when it is set (else one started on this machine: Ray's to find)
    named = os.environ.get("RAY_ADDRESS", "") if address == "auto" else address
    shown = f"{address} (RAY_ADDRESS={named})" if named != address else address
    where = "start a local Ray runtime" if local else f"connect to the Ray cluster at {shown}"
    if not local and named:
        _check_reachable(named, where)
    try:
        ray.init(address=LOCAL_ADDRESS if local else address, **settings)
    except Exception as error:  # ConnectionError, RuntimeError, ValueError…: Ray's errors vary by cause
        raise PipelineError(f"cannot {where}: {one_line(error)}") from error
    return True


CONNECT_TIMEOUT_S = 10.0
"""How long a cluster's address may take to accept a connection before it is taken as unreachable."""


def _check_reachable(address: str, where: str) -> None:
    """`PipelineError` when nothing accepts a connection at `address` ("host:port" or "ray://host:port"; other
    forms are Ray's to find): `ray.init` retries such an address for minutes, silently."""
    host, separator, port = address.removeprefix("ray://").rpartition(":")
    if not separator or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as error:
        raise PipelineError(f"cannot {where}: {error.strerror or error}") from error


def _refuse_tasks_larger_than_this_machine(ray: ModuleType, cpus_per_task: float) -> None:
    """A local runtime has this machine's CPUs and never more: a task wanting more would wait forever,
    silently. (A cluster may grow to fit it: not checked there.)"""
    cpus = float(ray.cluster_resources().get("CPU", 0.0))
    if cpus_per_task > cpus:
        raise PipelineError(f"--cpus-per-task {cpus_per_task:g}: the local Ray runtime has {cpus:g} CPUs; a "
                            "task asking for more would never start")


def _run_tasks(ray: ModuleType, inputs: list[Path], config: ReplayConfig, out_dir: Path, options: RayOptions,
               on_done: Callable[[BatchOutcome], None] | None, replay_one: ReplayOne) -> list[BatchOutcome]:
    task = ray.remote(_replay_task).options(num_cpus=options.cpus_per_task, max_retries=options.retries,
                                            retry_exceptions=True)
    config_ref = ray.put(config)  # sent to the object store once, not with each of thousands of tasks
    working_folder = os.getcwd()
    threads = max(1, int(options.cpus_per_task))  # the cores the task holds, for its kernels' threads
    index_of = {task.remote(str(path), config_ref, str(out_dir), working_folder, replay_one, threads): index
                for index, path in enumerate(inputs)}
    outcomes: list[BatchOutcome | None] = [None] * len(inputs)
    pending = list(index_of)
    try:
        while pending:
            [ref], pending = ray.wait(pending, num_returns=1)  # the next task to finish
            index = index_of[ref]
            outcome = _outcome_of(ray, ref, inputs[index])
            outcomes[index] = outcome
            if on_done is not None:
                on_done(outcome)
    except BaseException:
        _cancel(ray, pending)
        raise
    return [outcome for outcome in outcomes if outcome is not None]


def _replay_task(path: str, config: ReplayConfig, out_dir: str, working_folder: str,
                 replay_one: ReplayOne, threads: int) -> BatchOutcome:
    """One input, in a Ray worker. Our own errors (bad input) are outcomes; anything else raises, so that
    Ray retries the task."""
    if os.path.isdir(working_folder):  # the driver's, so that relative paths resolve as they do there
        os.chdir(working_folder)
    # Ray starts a worker per core it schedules on: each keeps to the cores its task holds (and the BLAS
    # limit ends with the task: the worker may run others' tasks next).
    with limit_threads(threads):
        return replay_one(Path(path), config, out_dir=Path(out_dir), catch_unexpected=False)


def _outcome_of(ray: ModuleType, ref: Any, path: Path) -> BatchOutcome:
    from ray.exceptions import RayError, RayTaskError

    try:
        return ray.get(ref)
    except RayTaskError as error:  # it raised on every try: a bug, reported with the remote traceback
        cause = error.cause if isinstance(error.cause, BaseException) else error
        return dataclasses.replace(BatchOutcome.failure(path, cause, unexpected=True), traceback=str(error))
    except RayError as error:  # its worker died on every try (killed, out of memory) or its node was lost
        return BatchOutcome.crashed(path, "Ray task", error)


def _cancel(ray: ModuleType, pending: list[Any]) -> None:
    """Cancel the outstanding tasks: queued ones do not start, running ones get a KeyboardInterrupt (their
    staged outputs are removed); those still running after `CANCEL_GRACE_S` have their workers killed."""
    if not pending:
        return
    for ref in pending:
        ray.cancel(ref)
    _, still_running = ray.wait(pending, num_returns=len(pending), timeout=CANCEL_GRACE_S)
    for ref in still_running:
        ray.cancel(ref, force=True)
    if still_running:
        ray.wait(still_running, num_returns=len(still_running), timeout=CANCEL_GRACE_S)
