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
"""

from __future__ import annotations

import gc
import os
import signal


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


if __name__ == "__main__":
    main()
