"""The `replay` entry point (`pipeline.launcher`): the collector is paused for the imports only."""

from __future__ import annotations

import os
import subprocess
import sys

PROBE = """
import gc, sys
import pipeline.cli
import pipeline.launcher

def probe():
    app = sys.modules["pipeline.cli"].app
    tracked = {id(o) for o in gc.get_objects()}
    print(gc.isenabled(), gc.get_freeze_count() > 0, id(app) in tracked, id(app.__dict__) in tracked)

pipeline.cli.main = probe
pipeline.launcher.main()
"""


def test_the_command_runs_with_the_collector_on_and_its_imports_frozen() -> None:
    # A fresh interpreter: the test process's own collector state is left alone.
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    enabled, frozen, app_collected, app_dict_collected = done.stdout.split()
    # The run's own garbage is still collected; the command's objects are kept out of every collection.
    assert enabled == "True"
    assert frozen == "True"
    assert (app_collected, app_dict_collected) == ("False", "False")
