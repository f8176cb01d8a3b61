"""Exceptions raised by the pipeline on purpose; the CLI turns them into one-line messages (exit code 2)."""

from __future__ import annotations


class PipelineError(Exception):
    """Base class of every error the pipeline raises on purpose."""


class OutputError(PipelineError):
    """An output file or folder could not be written; nothing partial is left behind."""
