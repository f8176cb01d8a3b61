"""Writing outputs so that a failed run leaves nothing partial behind and never clobbers good files.

Every output is first written under a hidden temporary name in its final folder (same file system, so the
final `os.replace` is atomic) and renamed only once all of a run's outputs are complete.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.errors import OutputError

if TYPE_CHECKING:
    from optimizer.solve import OptimizationResult


def temporary_path(target: Path) -> Path:
    """A hidden, unique name beside `target` that keeps its suffix (some writers look at it)."""
    return target.with_name(f".{target.stem}.{secrets.token_hex(4)}.partial{target.suffix}")


def prepare_output_dir(directory: Path) -> bool:
    """Create `directory` (and its parents) if needed; returns whether it was created by this call."""
    if directory.is_dir():
        return False
    if directory.exists():
        raise OutputError(f"{directory}: exists and is not a folder")
    try:
        directory.mkdir(parents=True)
    except FileExistsError:  # created concurrently by someone else: fine as long as it is a folder
        if not directory.is_dir():
            raise OutputError(f"{directory}: exists and is not a folder") from None
        return False
    except OSError as error:
        raise OutputError(f"{directory}: cannot create the folder: {error.strerror or error}") from error
    return True


@contextmanager
def staged_outputs(*targets: Path) -> Iterator[tuple[Path, ...]]:
    """Yield one temporary path per target; on success rename each onto its target, on any failure
    (including KeyboardInterrupt) delete the temporaries and leave the targets untouched.

    Each rename is atomic; a set of several files is renamed one after another once all are written.
    """
    temporaries = tuple(temporary_path(target) for target in targets)
    try:
        yield temporaries
        for temporary in temporaries:
            if not temporary.is_file():
                raise OutputError(f"{temporary}: was not written")
        for temporary, target in zip(temporaries, targets, strict=True):
            try:
                os.replace(temporary, target)
            except OSError as error:
                raise OutputError(f"{target}: cannot write the file: {error.strerror or error}") from error
    except BaseException:
        for temporary in temporaries:
            temporary.unlink(missing_ok=True)
        raise


@contextmanager
def staged_outputs_in(directory: Path, *targets: Path) -> Iterator[tuple[Path, ...]]:
    """`staged_outputs` for a run's outputs in `directory`, created if needed: a folder this call created
    is removed again when the run fails (left alone if someone else wrote there meanwhile)."""
    created = prepare_output_dir(directory)
    try:
        with staged_outputs(*targets) as temporaries:
            yield temporaries
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                directory.rmdir()
        raise


def output_stem(path: Path) -> str:
    """What a replay names its outputs after: a file's stem, a folder's name (a ROS 2 bag)."""
    return path.stem if path.is_file() else path.name


def atomic_write_text(path: Path, text: str) -> None:
    """Write `text` (UTF-8) to `path` through a temporary file and an atomic rename."""
    with staged_outputs(path) as (temporary,):
        write_text(temporary, text)


def write_text(path: Path, text: str) -> None:
    """Write `text` as UTF-8, turning OS errors into an OutputError that names the file."""
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as error:
        raise OutputError(f"{path}: cannot write the file: {error.strerror or error}") from error


def write_png(path: Path, image: Any) -> None:
    """Write a uint8 grey or RGB image (rows top to bottom) as PNG."""
    from PIL import Image

    try:
        Image.fromarray(image).save(path, format="PNG", optimize=False)
    except OSError as error:
        raise OutputError(f"{path}: cannot write the image: {error.strerror or error}") from error


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
