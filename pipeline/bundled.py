"""Data bundled inside the package (see `samples/ATTRIBUTION.md`), found through importlib.resources so it
works from a source tree, a wheel or a zip alike."""

from __future__ import annotations

from contextlib import AbstractContextManager
from importlib import resources
from pathlib import Path

SAMPLE_GRAPH = "M3500.g2o"
"""The default input of `replay`: Olson's Manhattan world, the paper's own benchmark (3500 poses)."""


def sample_graph() -> AbstractContextManager[Path]:
    """A context manager giving a file-system path of the bundled sample pose graph."""
    return resources.as_file(resources.files("pipeline") / "samples" / SAMPLE_GRAPH)
