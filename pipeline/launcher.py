"""The `replay` console script's entry point.

Importing the command takes a few seconds (numba, rerun, scipy); a Ctrl-C or SIGTERM in that time ends
the process at once, quietly, since nothing has been written yet. `pipeline.cli.main` then installs the
handlers that clean up what a run has started.
"""

from __future__ import annotations

import os
import signal


def main() -> None:
    def exit_at_once(signum: int, _frame: object) -> None:
        os._exit(128 + signum)

    signal.signal(signal.SIGINT, exit_at_once)
    signal.signal(signal.SIGTERM, exit_at_once)
    from pipeline.cli import main as run

    run()


if __name__ == "__main__":
    main()
