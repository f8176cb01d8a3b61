"""Where a batch's inputs come from when they are too many for a command line: a file listing them, or a
folder searched for logs and pose graphs.

Library code: returns paths, raises `PipelineError`.
"""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.api import GRAPH_SUFFIXES, input_kind
from pipeline.errors import PipelineError

INPUT_SUFFIXES = frozenset({".mcap", ".bag", ".db3", *GRAPH_SUFFIXES})
"""The files a folder search takes as inputs: logs (MCAP, ROS 1 bags, bare ROS 2 sqlite3) and pose graphs."""

ROS2_BAG_MARKER = "metadata.yaml"


def batch_inputs(source: Path, *, exclude: Path | None = None) -> list[Path]:
    """The inputs named by `source`: the paths listed in it when it is a file (`read_input_list`), the
    logs and pose graphs found in it when it is a folder (`find_inputs`, skipping `exclude`)."""
    if source.is_dir():
        return find_inputs(source, exclude=exclude)
    return read_input_list(source)


def read_input_list(path: Path) -> list[Path]:
    """The paths in a text file, one a line, blank lines and lines starting with `#` skipped. Relative paths
    are taken from the current folder, as they would be on the command line."""
    if path.suffix.lower() in INPUT_SUFFIXES or input_kind(path) == "graph":  # by name, or by its first line
        raise PipelineError(f"{path}: a log or pose graph, not a list of inputs: name it as an input itself")
    try:
        text = path.read_text(encoding="utf-8-sig")  # (a byte-order mark, as Windows editors write)
    except (OSError, UnicodeDecodeError) as error:
        reason = error.strerror if isinstance(error, OSError) and error.strerror else error
        raise PipelineError(f"{path}: cannot read the input list: {reason}") from error
    entries = (line.strip() for line in text.splitlines())
    return [Path(entry) for entry in entries if entry and not entry.startswith("#")]


def find_inputs(directory: Path, *, exclude: Path | None = None) -> list[Path]:
    """The logs and pose graphs under `directory`, in sorted order: files with an input suffix and ROS 2 bag
    folders (holding `metadata.yaml`, taken whole). Hidden files and folders are skipped (our own
    temporaries among them), and so is `exclude` (the output folder, whose `.g2o` files are results; when it
    is the searched folder itself, the pose graphs a replay wrote there, beside their `.json` summaries).
    Folder symlinks are followed, each real folder once."""
    if (directory / ROS2_BAG_MARKER).is_file():
        return [directory]
    excluded = exclude.resolve() if exclude is not None else None
    found: list[Path] = []
    seen: set[Path] = set()
    for folder, subfolders, files in os.walk(directory, onerror=_raise_walk_error, followlinks=True):
        here = Path(folder)
        seen.add(here.resolve())
        kept = []
        for name in sorted(subfolders):
            child = here / name
            real = child.resolve()
            if name.startswith(".") or real == excluded or real in seen:
                continue  # (a symlink back up the tree would loop)
            seen.add(real)
            if (child / ROS2_BAG_MARKER).is_file():
                found.append(child)
            else:
                kept.append(name)
        subfolders[:] = kept  # os.walk descends into what is left, in this order
        outputs_here = here.resolve() == excluded
        found.extend(here / name for name in sorted(files)
                     if not name.startswith(".") and Path(name).suffix.lower() in INPUT_SUFFIXES
                     and not (outputs_here and _a_replay_output(here / name)))
    return sorted(found)


def _a_replay_output(path: Path) -> bool:
    """Whether `path` is a pose graph a replay wrote (its summary `.json` beside it)."""
    return path.suffix.lower() == ".g2o" and path.with_suffix(".json").is_file()


def _raise_walk_error(error: OSError) -> None:
    raise PipelineError(f"{error.filename}: cannot search the folder: {error.strerror or error}") from error
