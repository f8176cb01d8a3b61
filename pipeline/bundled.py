"""Data bundled inside the package (see `samples/ATTRIBUTION.md`), found through importlib.resources so it
works from a source tree, a wheel or a zip alike."""

from __future__ import annotations

from contextlib import AbstractContextManager
from importlib import resources
from pathlib import Path

SAMPLE_LOG = "csail_sample.mcap"
"""The default input of `replay`: the first 1000 scans of the real MIT CSAIL laser log, with loops."""
SAMPLE_DESCRIPTION = "the bundled sample log (the first 1000 scans of the real MIT CSAIL laser log)"
"""What `replay` without an input runs, in words (for help texts)."""


def sample_log() -> AbstractContextManager[Path]:
    """A context manager giving a file-system path of the bundled sample laser log."""
    return resources.as_file(resources.files("pipeline") / "samples" / SAMPLE_LOG)
