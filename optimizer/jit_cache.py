"""Where numba keeps its compiled kernels (`cache=True`) when the package folder is read-only.

numba caches beside the sources (`__pycache__`); installed system-wide or in a container as another user,
that folder is not writable and every cached kernel failed at import ("no locator available"). Before
numba is first imported (importing this module does it; `optimizer` and `frontends` import it first),
`NUMBA_CACHE_DIR` is pointed at a per-user folder instead.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path


def cache_dir_for(package_dir: Path, environment: Mapping[str, str],
                  writable: Callable[[Path], bool]) -> Path | None:
    """The folder numba should cache in, or None to leave numba's default (beside the sources).

    A cache folder the user chose (`NUMBA_CACHE_DIR`) is kept; otherwise, when `package_dir` is not
    writable, `$XDG_CACHE_HOME/sgdslam/numba` (default `~/.cache/sgdslam/numba`)."""
    if environment.get("NUMBA_CACHE_DIR") or writable(package_dir):
        return None
    base = environment.get("XDG_CACHE_HOME") or str(Path(environment.get("HOME") or Path.home()) / ".cache")
    return Path(base) / "sgdslam" / "numba"


def use_writable_cache() -> None:
    """Set `NUMBA_CACHE_DIR` for this process when the package folder is read-only (see the module)."""
    folder = cache_dir_for(Path(__file__).resolve().parent.parent, os.environ,
                           lambda path: os.access(path, os.W_OK))
    if folder is not None:
        os.environ["NUMBA_CACHE_DIR"] = str(folder)


use_writable_cache()
