"""The `replay` console script's entry point.

Importing the command takes a few seconds (numba, rerun, scipy); a Ctrl-C or SIGTERM in that time ends
the process at once, quietly, since nothing has been written yet. `pipeline.cli.main` then installs the
handlers that clean up what a run has started.

The imports build some 200 000 objects (modules, classes, functions, numba's typing tables) that live until
the process ends. Python's cyclic collector would walk them over and over: while importing (every 700 new
objects a young collection, and full ones as the heap grows) and in every full collection of the run
after. On a 3D replay of 163 clouds that was 0.3–0.4 CPU s of collections, 0.07 s with the collector
paused during the imports and what they built frozen (`gc.freeze`: kept out of every later collection).
The imports leave a few thousand objects of cyclic garbage (about 0.5 MB), kept until exit by the freeze;
the run itself is collected as usual.

`arrow_without_pandas` keeps pyarrow from importing pandas in the processes the command owns.
"""

from __future__ import annotations

import gc
import importlib.abc
import os
import signal
import sys
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType


def main() -> None:
    def exit_at_once(signum: int, _frame: object) -> None:
        os._exit(128 + signum)

    signal.signal(signal.SIGINT, exit_at_once)
    signal.signal(signal.SIGTERM, exit_at_once)
    gc.disable()
    try:
        from pipeline.cli import main as run
    finally:
        gc.freeze()
        gc.enable()
    run()


class _RefusePandas(importlib.abc.MetaPathFinder):
    def find_spec(self, name: str, path: Sequence[str] | None, target: ModuleType | None = None
                  ) -> ModuleSpec | None:
        if name == "pandas":
            raise ImportError("pandas is not imported for pyarrow's type checks")
        return None


def arrow_without_pandas() -> None:
    """Make pyarrow believe pandas is absent, for its type checks.

    pyarrow imports pandas (when installed) the first time it converts anything, to ask whether a numpy
    array or a list is a pandas object: 0.4 s of a 2 s replay, for what rerun converts, which never is.
    With pandas refused while pyarrow first looks for it, it takes every input for what it is from then
    on; what needs pandas (`Table.to_pandas`) still imports it. Only for the processes the command owns
    (its own, its batch workers): a pandas Series given to pyarrow is then converted as a plain sequence
    (NaN stays NaN, not null), which a user's script in the same process may not want."""
    if "pandas" in sys.modules:
        return
    import numpy as np
    import pyarrow as pa

    refuse = _RefusePandas()
    sys.meta_path.insert(0, refuse)
    try:
        # pyarrow looks for pandas once in each of its two conversions: of arrays, and of Python sequences.
        pa.array(np.zeros(1))
        pa.array([0.0])
    finally:
        sys.meta_path.remove(refuse)


if __name__ == "__main__":
    main()
