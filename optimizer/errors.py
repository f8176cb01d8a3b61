"""Exceptions raised by the optimizer package; callers (the CLI) turn them into one-line messages."""

from __future__ import annotations

from pathlib import Path


class OptimizerError(Exception):
    """Base class of every error the optimizer raises on purpose."""


class GraphError(OptimizerError):
    """The pose graph itself is unusable (disconnected, self-loops, bad information, ...)."""


class FileLineError(Exception):
    """An input file could not be read: names the file, and the line when one is at fault (`path`, `line`,
    and `reason`, the message without them). Mixed into each package's own base class."""

    def __init__(self, path: str | Path, message: str, line: int | None = None) -> None:
        self.path = Path(path)
        self.line = line
        self.reason = message
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {message}")


class GraphFileError(FileLineError, OptimizerError):
    """A graph file could not be read."""
