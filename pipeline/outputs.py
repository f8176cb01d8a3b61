"""Writing outputs so that a failed, interrupted or killed run leaves nothing partial and never clobbers
good files.

A run's outputs are written into a hidden staging folder inside the output folder (same file system),
flushed to disk (files, then the folder), and only then renamed into place one after another, with SIGINT
and SIGTERM held back until the last rename, so an interruption leaves the old outputs or the new ones.
A rename that fails (an output made read-only meanwhile) puts back the outputs it had already replaced,
which waited in the staging folder; a folder where an output would go is refused before the run.
A run killed outright (SIGKILL, power loss) leaves its staging folder behind: the next run writing the
same outputs cleans it up, and finishes its renames first if it was killed while publishing (a `.complete`
marker says the staged set was whole). A lock per output name (`.<stem>.lock`, removed afterwards) makes a
second run of the same outputs into the same folder fail with a clear message instead of interleaving.
The clean-up after a failure (the staging folder, the lock file) also runs with the stop signals held
back: one arriving during it (Ctrl-C pressed twice, or the alarm retrying an interrupt that was lost) is
delivered once it is done.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import secrets
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from optimizer.errors import OptimizerError
from pipeline.errors import OutputError

if TYPE_CHECKING:
    from optimizer.solve import OptimizationResult

_STAGING = ".staging-"
_COMPLETE = ".complete"
_REPLACED = ".replaced"
"""The folder in a staging folder where the outputs being replaced wait until every new one is in place."""
_HELD_SIGNALS = {signal.SIGINT, signal.SIGTERM, signal.SIGALRM}
"""The stop signals, and the alarm that retries a lost interrupt (`install_stop_signals`)."""
INTERRUPT_RETRY_SECONDS = 0.05


def prepare_output_dir(directory: Path) -> bool:
    """Create `directory` (and its parents) if needed; returns whether it was created by this call."""
    if directory.is_dir():
        return False
    try:
        directory.mkdir(parents=True)
    except FileExistsError:  # a file, or a folder created concurrently by someone else (fine)
        if not directory.is_dir():
            raise OutputError(f"{directory}: exists and is not a folder") from None
        return False
    except OSError as error:
        raise OutputError(f"{directory}: cannot create the folder: {error.strerror or error}") from error
    return True


@contextmanager
def staged_outputs(*targets: Path) -> Iterator[tuple[Path, ...]]:
    """Yield one temporary path per target (same name, in a hidden staging folder beside the targets); on
    success publish them all (see the module docstring), on any failure (KeyboardInterrupt included)
    delete them and leave the targets untouched. The targets must share one folder; the lock and the
    staging folder are named after the first target's stem."""
    if not targets:
        raise ValueError("no outputs to stage")
    directory = targets[0].parent
    if any(target.parent != directory for target in targets):
        raise ValueError("staged outputs must share one folder")
    stem = targets[0].stem
    refuse_folders_as_targets(targets)
    with _output_lock(directory, stem):
        _recover_stale_staging(directory, stem)
        staging = directory / f".{stem}{_STAGING}{os.getpid()}-{secrets.token_hex(4)}"
        try:
            staging.mkdir()
        except OSError as error:
            raise _folder_error(directory, error) from error
        temporaries = tuple(staging / target.name for target in targets)
        try:
            try:
                yield temporaries
            except Exception as error:
                renamed = _naming_the_outputs(error, staging, directory)
                if renamed is None:
                    raise
                raise renamed from error
            for temporary, target in zip(temporaries, targets, strict=True):
                if not temporary.is_file():
                    raise OutputError(f"{target}: was not written")
            _publish(staging, temporaries, targets)
        finally:
            with stop_signals_held():  # a second Ctrl-C must not cut the clean-up short
                shutil.rmtree(staging, ignore_errors=True)


def _naming_the_outputs(error: Exception, staging: Path, directory: Path) -> OutputError | None:
    """A failure to write a staged file (ours, or the OS's: disk full, read-only) as an `OutputError`
    naming the output the user asked for, not its hidden copy; None for any other error."""
    hidden = str(staging)
    if isinstance(error, OSError):
        if error.filename is None or hidden not in str(error.filename):
            return None
        name = str(error.filename).replace(hidden, str(directory))
        return OutputError(f"{name}: cannot write the file: {error.strerror or error}")
    if isinstance(error, OutputError | OptimizerError) and hidden in str(error):
        return OutputError(str(error).replace(hidden, str(directory)))
    return None


def _publish(staging: Path, temporaries: tuple[Path, ...], targets: tuple[Path, ...]) -> None:
    """Flush the staged files to disk, mark the set complete, then rename each into place with SIGINT and
    SIGTERM held back (delivered right after), and flush the folder."""
    try:
        for temporary in temporaries:
            _fsync_path(temporary)
        (staging / _COMPLETE).touch()
        _fsync_path(staging)
    except OSError as error:
        raise _folder_error(targets[0].parent, error) from error
    with stop_signals_held():
        refuse_folders_as_targets(targets)
        replaced = staging / _REPLACED
        published: list[tuple[Path, Path | None]] = []  # (target, its previous file in `replaced`, if any)
        try:
            replaced.mkdir()
            for temporary, target in zip(temporaries, targets, strict=True):
                with writing(target):
                    previous = replaced / target.name if os.path.lexists(target) else None
                    if previous is not None:
                        os.replace(target, previous)
                    published.append((target, previous))
                    os.replace(temporary, target)
        except (OSError, OutputError) as error:
            _put_back(staging, published)
            if isinstance(error, OutputError):
                raise
            raise _folder_error(targets[0].parent, error) from error
        with contextlib.suppress(OSError):
            _fsync_path(targets[0].parent)


def _put_back(staging: Path, published: Sequence[tuple[Path, Path | None]]) -> None:
    """Undo a failed publication: the previous outputs it had moved aside return, the new ones it had put
    where there was none are removed. The set is no longer complete: a run killed meanwhile must not be
    finished by the next."""
    with contextlib.suppress(OSError):
        (staging / _COMPLETE).unlink()
    for target, previous in reversed(published):
        with contextlib.suppress(OSError):
            if previous is None:
                target.unlink()
            else:
                os.replace(previous, target)


def refuse_folders_as_targets(targets: Sequence[Path]) -> None:
    """Raise `OutputError` when a folder stands where an output would go: a file cannot replace it, and
    finding out only while publishing would waste the run."""
    for target in targets:
        if target.is_dir() and not target.is_symlink():
            raise OutputError(f"{target}: is a folder; the output of that name cannot replace it (move it, "
                              "or write the outputs into another folder with --out)")


@contextmanager
def stop_signals_held(*, redeliver: bool = True) -> Iterator[None]:
    """Hold SIGINT, SIGTERM and SIGALRM back while the block runs, then deliver them (or, with
    `redeliver=False`, drop them: the block is itself the reaction to one). Python runs signal handlers in
    the main thread whichever thread the kernel picks, so the main thread's handlers are swapped (a thread
    mask would not do); elsewhere signals cannot interrupt this thread anyway. A handler installed outside
    Python (`getsignal` None) could not be put back, so its signal is left alone."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = {number: handler for number in _HELD_SIGNALS
                if (handler := signal.getsignal(number)) is not None}
    for number in previous:
        signal.signal(number, lambda signum, _frame: received.append(signum))
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        for signum in received if redeliver else ():
            signal.raise_signal(signum)


def install_stop_signals(handler: Callable[[int, FrameType | None], None]) -> None:
    """`handler` for SIGINT, SIGTERM and SIGALRM; it raises `KeyboardInterrupt`, which unwinds the run and
    removes its staged outputs.

    An exception raised where Python cannot propagate it (in a `__del__`, or in a callback from C such as
    numba's LLVM object cache while a kernel compiles) goes to `sys.unraisablehook`, which prints it with a
    traceback and drops it: the interrupt would be lost. Such an interrupt is retried a moment later by
    SIGALRM, silently (so `handler` must raise again on SIGALRM); other unraisable exceptions are reported
    as before."""
    for number in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM):
        signal.signal(number, handler)
    report = sys.unraisablehook

    def retry_interrupt(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            signal.setitimer(signal.ITIMER_REAL, INTERRUPT_RETRY_SECONDS)
        else:
            report(unraisable)

    sys.unraisablehook = retry_interrupt


def raised_by_interrupt(error: BaseException) -> bool:
    """Whether `error` stands for a stop signal: a `KeyboardInterrupt`, or an error it caused where Python
    code was called back from C (numba's dispatcher wraps it as `SystemError: ... returned a result with an
    exception set`)."""
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


def _folder_error(directory: Path, error: OSError) -> OutputError:
    return OutputError(f"{directory}: cannot write in the folder: {error.strerror or error}")


def _fsync_path(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def recover_outputs(directory: Path, stem: str) -> None:
    """Clean up what a killed run writing the `stem` outputs left in `directory`, as the next run into it
    would (see `staged_outputs`). Raises `OutputError` while a live run still holds their lock."""
    with _output_lock(directory, stem):
        _recover_stale_staging(directory, stem)


def _recover_stale_staging(directory: Path, stem: str) -> None:
    """Clean up what a killed run writing these outputs left (the caller holds their lock): finish the
    renames of a set it had completed, put back what one killed while undoing a failed publication had
    moved aside (`_put_back`), delete the staging folder."""
    for staging in directory.glob(f".{stem}{_STAGING}*"):
        complete = (staging / _COMPLETE).is_file()
        moved = staging / _REPLACED
        for staged in staging.iterdir() if complete else moved.glob("*") if moved.is_dir() else ():
            if staged.name not in (_COMPLETE, _REPLACED):
                with contextlib.suppress(OSError):
                    os.replace(staged, directory / staged.name)
        shutil.rmtree(staging, ignore_errors=True)


@contextmanager
def _output_lock(directory: Path, stem: str) -> Iterator[None]:
    """Hold an exclusive lock on `.<stem>.lock` in `directory`; fail at once when another run holds it.

    The lock file is removed on release; a run that opened it just before is detected (the path no
    longer names the locked file) and retries with a fresh one."""
    path = directory / f".{stem}.lock"
    while True:
        try:
            descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise _folder_error(directory, error) from error
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            os.close(descriptor)
            if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise OutputError(f"{directory}: another replay is writing the {stem} outputs there now; "
                                  "wait for it or choose another --out folder") from None
            raise OutputError(f"{path}: cannot lock: {error.strerror or error}") from error
        with contextlib.suppress(FileNotFoundError):
            if os.path.samestat(os.fstat(descriptor), os.stat(path)):
                break
        os.close(descriptor)
    try:
        yield
    finally:
        with stop_signals_held():
            with contextlib.suppress(OSError):
                path.unlink()
            os.close(descriptor)


@contextmanager
def staged_outputs_in(directory: Path, *targets: Path,
                      inputs: Sequence[Path] = ()) -> Iterator[tuple[Path, ...]]:
    """`staged_outputs` for a run's outputs in `directory`, created if needed: a folder this call created
    is removed again when the run fails (left alone if someone else wrote there meanwhile). `inputs`: the
    files the run reads, which no output may replace (`refuse_replacing_inputs`)."""
    refuse_replacing_inputs(targets, inputs)
    created = prepare_output_dir(directory)
    try:
        with staged_outputs(*targets) as temporaries:
            yield temporaries
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                directory.rmdir()
        raise


def refuse_replacing_inputs(targets: Sequence[Path], inputs: Sequence[Path]) -> None:
    """Raise `OutputError` when one of `targets` is one of the run's `inputs` (the same file, whatever the
    path: a graph replayed into its own folder, a session continued under its own name): publishing the
    outputs would destroy the very file they were made from."""
    for target in targets:
        for source in inputs:
            with contextlib.suppress(OSError):  # a target not there yet replaces nothing
                if os.path.samefile(source, target):
                    raise OutputError(f"{target}: is an input of this replay, and its output of the same "
                                      "name would replace it; write the outputs into another folder (--out)")


def output_stem(path: str | Path) -> str:
    """What a replay names its outputs after (`<stem>.rrd`, …): a folder's name (a ROS 2 bag), otherwise
    the file's stem (whether or not it exists yet)."""
    path = Path(path)
    return path.resolve().name if path.is_dir() else path.stem  # resolved: `.` names its folder


@contextmanager
def writing(path: Path, what: str = "the file") -> Iterator[None]:
    """OS errors inside become an `OutputError` naming the file: "<path>: cannot write <what>: <reason>"."""
    try:
        yield
    except OSError as error:
        raise OutputError(f"{path}: cannot write {what}: {error.strerror or error}") from error


def write_bytes(path: Path, data: bytes) -> None:
    """Write `data`, turning OS errors into an OutputError that names the file."""
    with writing(path):
        path.write_bytes(data)


def write_text(path: Path, text: str) -> None:
    """Write `text` as UTF-8, turning OS errors into an OutputError that names the file."""
    write_bytes(path, text.encode("utf-8"))


def write_png(path: Path, image: Any) -> None:
    """Write a uint8 grey or RGB image (rows top to bottom) as PNG."""
    from PIL import Image

    with writing(path, "the image"):
        Image.fromarray(image).save(path, format="PNG", optimize=False)


def json_text(data: Any) -> str:
    """Pretty JSON with non-finite floats as null (JSON has no NaN or infinity)."""
    return json.dumps(_finite_or_none(data), indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(item) for item in value]
    return value


def optimization_summary(result: OptimizationResult) -> dict[str, Any]:
    """How an optimization ended, for the JSON summaries: converged or not and why, every start."""
    return {
        "converged": result.converged,
        "stop_reason": result.reason,
        "start": result.winner,
        "candidates": [
            {"start": candidate.start, "chi2_final": candidate.chi2, "converged": candidate.converged,
             "stop_reason": candidate.reason, "iterations": candidate.iterations}
            for candidate in result.candidates
        ],
    }
