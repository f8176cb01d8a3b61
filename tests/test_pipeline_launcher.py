"""The `replay` entry point (`pipeline.launcher`): the collector is paused for the imports only, and pyarrow
does not import pandas for rerun's conversions."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.pipeline_fixtures import write_loop_graph

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


AFTER_ARROW_PROBE = """
import numpy as np
import pyarrow as pa
from pipeline.launcher import arrow_without_pandas

arrow_without_pandas()
pa.array(["a"], type=pa.string())
import pandas as pd
# What needs pandas still gets it: a table converts to a DataFrame, a Series converts.
print(pa.array(pd.Series([1.0, 2.0])).to_pylist(), type(pa.table({"a": [1, 2]}).to_pandas()).__name__)
"""


def test_a_replay_does_not_import_pandas_and_pandas_still_works_after(tmp_path: Path) -> None:
    pytest.importorskip("pandas", reason="pyarrow imports pandas only where it is installed")
    environment = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    graph = write_loop_graph(tmp_path / "loop.g2o")
    # -X importtime lists every module the command imports, on stderr.
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "pipeline.launcher", str(graph), "--out",
                           str(tmp_path / "out"), "--quiet"], capture_output=True, text=True, timeout=120,
                          env=environment)
    assert done.returncode == 0, done.stderr[-2000:]
    imported = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if "|" in line}
    assert "rerun" in imported and "pyarrow" in imported
    # pyarrow's refused attempts show as a bare `pandas` line; an import brings its submodules.
    assert not [name for name in imported if name.startswith("pandas.")]
    after = subprocess.run([sys.executable, "-c", AFTER_ARROW_PROBE], capture_output=True, text=True,
                           timeout=120, env=environment)
    assert after.returncode == 0, after.stderr
    assert after.stdout.split() == ["[1.0,", "2.0]", "DataFrame"]
