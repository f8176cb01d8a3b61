"""The last line between a hostile file and the caller: library errors become one-line `LogFileError`s.

Containers and decoders check what they can (record lengths against the file size, chunk CRCs, payload
layouts) and name the record at fault. A mutated file can still trip a check nobody thought of deep in
sqlite, a decompressor or a struct call; those errors are about the data, not our code, so at the reader's
boundary they are reported as a damaged log naming the file, never as a traceback.
"""

from __future__ import annotations

import sqlite3
import stat
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import zstandard
from mcap.exceptions import McapError

from frontends.errors import FrontendError, LogFileError

T = TypeVar("T")

DATA_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,  # also UnicodeDecodeError and the containers' internal corruption errors
    struct.error,
    KeyError,
    IndexError,
    TypeError,
    OverflowError,
    EOFError,
    RuntimeError,  # lz4 frame errors
    zstandard.ZstdError,
    sqlite3.Error,
    McapError,
    MemoryError,  # a last resort: lengths are checked before allocating, this must not be reached
)
READ_ERRORS: tuple[type[BaseException], ...] = (*DATA_ERRORS, OSError)
"""What reading a damaged or unreadable file raises: its data's errors and the system's."""


def damaged(path: Path, error: BaseException) -> LogFileError:
    """One-line error for a library failure on the data of `path`."""
    reason = " ".join(str(error).split()) or type(error).__name__
    if isinstance(error, MemoryError):
        reason = "a record claims more memory than is available"
    elif isinstance(error, OSError):
        return LogFileError(path, f"cannot read: {error.strerror or reason}")
    return LogFileError(path, f"damaged log ({reason[:200]})")


def guarded_call(path: Path, call: Callable[[], T]) -> T:
    """`call()`, with data errors raised as `LogFileError`s naming `path`."""
    try:
        return call()
    except FrontendError:
        raise
    except READ_ERRORS as err:
        raise damaged(path, err) from None


def guarded_iter(path: Path, items: Iterator[T]) -> Iterator[T]:
    """The items, with data errors raised while producing them as `LogFileError`s naming `path`."""
    try:
        yield from items
    except FrontendError:
        raise
    except READ_ERRORS as err:
        raise damaged(path, err) from None


def check_readable_file(path: Path) -> int:
    """The size of the regular file `path`; a FIFO, socket or device is refused up front (reading one
    could block for ever or never end)."""
    try:
        status = path.stat()
    except OSError as err:
        raise LogFileError(path, f"cannot read: {err.strerror}") from None
    if not stat.S_ISREG(status.st_mode):
        kind = (
            "a FIFO" if stat.S_ISFIFO(status.st_mode)
            else "a character device" if stat.S_ISCHR(status.st_mode)
            else "a block device" if stat.S_ISBLK(status.st_mode)
            else "a socket" if stat.S_ISSOCK(status.st_mode)
            else "not a regular file"
        )
        raise LogFileError(path, f"is {kind}, not a regular file: give a log file or a bag directory")
    return status.st_size


def check_is_regular(path: Path) -> bool:
    """Whether `path` is a regular file (without following it into a FIFO or device)."""
    try:
        return stat.S_ISREG(path.stat().st_mode)
    except OSError:
        return False
