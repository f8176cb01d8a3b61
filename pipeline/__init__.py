"""The user-facing side of sgdslam: the `replay` command, its Rerun recordings and its output files.

`from pipeline import replay; result = replay("log.mcap", config)` is the Python API (`pipeline.api`),
configured by a `ReplayConfig` (`pipeline.config`, also read from TOML by `load_config`).

`load_session("run.session")` reads the session file a log replay writes (`pipeline.session_file`).

`pipeline.replay_graph.replay_graph` replays a pose-graph file through the optimizer and writes the
optimised graph, a JSON summary and a Rerun recording of every iteration. `pipeline.recording` is the only
module that imports rerun.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipeline.api import ReplayResult, replay
    from pipeline.config import ReplayConfig, load_config
    from pipeline.session_file import SessionContent, load_session

__all__ = ["ReplayConfig", "ReplayResult", "SessionContent", "load_config", "load_session", "replay"]

_LAZY = {"replay": "pipeline.api", "ReplayResult": "pipeline.api", "ReplayConfig": "pipeline.config",
         "load_config": "pipeline.config", "load_session": "pipeline.session_file",
         "SessionContent": "pipeline.session_file"}


def __getattr__(name: str) -> Any:
    # Lazy, so that `import pipeline` (and `replay --help`) does not pay for importing rerun and numba.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
