"""Reading a whole input file without trusting what it is: a FIFO, a device or /dev/zero must not block
the process for ever or fill its memory."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

STREAM_LIMIT = 256 << 20
"""What is read at most from a pipe or a device, whose size cannot be known before reading it."""


def read_bytes_bounded(path: Path, limit: int) -> bytes:
    """The file's bytes, refusing more than `limit` (more than `STREAM_LIMIT` from a pipe or a device). A
    pipe without a writer reads as empty instead of blocking. Raises OSError (with `strerror` set, as for
    any read error) when the file cannot be read or is too large; FileNotFoundError and IsADirectoryError
    as usual."""
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        info = os.fstat(descriptor)
        if stat.S_ISDIR(info.st_mode):
            raise IsADirectoryError(errno.EISDIR, "is a folder, not a file", str(path))
        if not stat.S_ISREG(info.st_mode):
            limit = min(limit, STREAM_LIMIT)
        elif info.st_size > limit:
            raise OSError(errno.EFBIG, f"larger than the {_size(limit)} such a file may have", str(path))
        os.set_blocking(descriptor, True)  # a writer is there now, or the pipe reads as empty
        chunks: list[bytes] = []
        total = 0
        while True:
            chunk = os.read(descriptor, min(1 << 20, limit + 1 - total))
            if not chunk:
                return b"".join(chunks)
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise OSError(errno.EFBIG, f"larger than the {_size(limit)} such a file may have", str(path))
    finally:
        os.close(descriptor)


def _size(limit: int) -> str:
    for unit, factor in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if limit >= factor:
            return f"{limit / factor:g} {unit}"
    return f"{limit} bytes"
