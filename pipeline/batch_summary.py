"""The result table of a batch: one row per input, whichever way it ran (in this process, `--jobs`,
`--ray`), written as `batch_summary.parquet` so that a fleet's results can be queried afterwards.

A row: `input`, `kind` ("log" or "graph"), `status` ("ok" or "failed"), `error`, `host` (the machine that
replayed it; null when unknown: its worker died) and, when it succeeded (null otherwise), its counts,
`chi2_initial`/`chi2_final` (null when not finite), `converged` and `stop_reason` (a run that did not
converge succeeded too, and says so here), `iterations` per optimizer stage and `wall_time_s` per
pipeline stage (maps), and `time_total_s`.

Library code: builds and writes the table; the command decides when.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.outputs import prepare_output_dir, staged_outputs, writing

if TYPE_CHECKING:
    import pyarrow as pa

    from pipeline.batch import BatchOutcome

BATCH_SUMMARY_NAME = "batch_summary.parquet"


def summary_row(outcome: BatchOutcome) -> dict[str, Any]:
    """One input's row; the columns a failed input has no value for are left out (null in the table)."""
    row = {"input": str(outcome.input_path), "kind": outcome.kind, "status": "ok" if outcome.ok else "failed",
           "error": outcome.error, "host": outcome.host}
    stats = outcome.stats
    if stats is None:
        return row
    times = {stage: float(seconds) for stage, seconds in stats.wall_time_s.items()}
    # The stats' fields are the columns of the same names (the table drops any other), some converted:
    return {**row, **vars(stats),
            "chi2_initial": _finite(stats.chi2_initial), "chi2_final": _finite(stats.chi2_final),
            "converged": bool(stats.converged),
            # Arrow maps are lists of (key, value) pairs
            "iterations": [(stage, int(count)) for stage, count in stats.iterations.items()],
            "wall_time_s": list(times.items()), "time_total_s": times.get("total")}


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def summary_table(outcomes: Sequence[BatchOutcome]) -> pa.Table:
    """The batch's rows as an Arrow table (maps for the per-stage iterations and times)."""
    import pyarrow as pa

    schema = pa.schema([
        ("input", pa.string()), ("kind", pa.string()), ("status", pa.string()), ("error", pa.string()),
        ("host", pa.string()), ("poses", pa.int64()), ("constraints", pa.int64()),
        ("loop_closures", pa.int64()), ("loop_closures_rejected", pa.int64()), ("scans", pa.int64()),
        ("chi2_initial", pa.float64()), ("chi2_final", pa.float64()),
        ("converged", pa.bool_()), ("stop_reason", pa.string()),
        ("iterations", pa.map_(pa.string(), pa.int64())),
        ("wall_time_s", pa.map_(pa.string(), pa.float64())),
        ("time_total_s", pa.float64()),
    ])
    return pa.Table.from_pylist([summary_row(outcome) for outcome in outcomes], schema=schema)


def write_batch_summary(path: Path, outcomes: Sequence[BatchOutcome]) -> Path:
    """Write the table to `path` (Parquet) atomically, creating its folder (when every input failed no
    replay created it); a failure leaves no partial file."""
    import pyarrow.parquet as pq

    table = summary_table(outcomes)
    prepare_output_dir(path.parent)
    with staged_outputs(path) as (temporary,), writing(path):
        pq.write_table(table, temporary)
    return path
