"""The result table of a batch: one row per input, whichever way it ran (in this process, `--jobs`,
`--ray`), written as `batch_summary.parquet` so that a fleet's results can be queried afterwards.

Library code: builds and writes the table; the command decides when.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.errors import OutputError
from pipeline.outputs import prepare_output_dir, staged_outputs

if TYPE_CHECKING:
    import pyarrow as pa

    from pipeline.batch import BatchOutcome

BATCH_SUMMARY_NAME = "batch_summary.parquet"


@dataclass(frozen=True)
class BatchSummaryRow:
    """One input of a batch: its status and, when it succeeded, its counts, χ² and times (None otherwise)."""

    input: str
    kind: str
    status: str
    """"ok" or "failed"."""
    error: str | None
    host: str | None
    """The host name of the machine that replayed it (None when unknown: its worker died)."""
    poses: int | None
    constraints: int | None
    loop_closures: int | None
    loop_closures_rejected: int | None
    scans: int | None
    chi2_initial: float | None
    chi2_final: float | None
    iterations: Mapping[str, int] | None
    """Iterations per optimizer stage."""
    wall_time_s: Mapping[str, float] | None
    """Seconds per pipeline stage, and "total"."""
    time_total_s: float | None

    @classmethod
    def from_outcome(cls, outcome: BatchOutcome) -> BatchSummaryRow:
        stats = outcome.stats
        status = "ok" if outcome.ok else "failed"
        if stats is None:
            return cls(str(outcome.input_path), outcome.kind, status, outcome.error, outcome.host,
                       None, None, None, None, None, None, None, None, None, None)
        times = {stage: float(seconds) for stage, seconds in stats.wall_time_s.items()}
        return cls(str(outcome.input_path), outcome.kind, status, outcome.error, outcome.host,
                   stats.poses, stats.constraints, stats.loop_closures, stats.loop_closures_rejected,
                   stats.scans, _finite(stats.chi2_initial), _finite(stats.chi2_final),
                   {stage: int(count) for stage, count in stats.iterations.items()}, times,
                   times.get("total"))


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def summary_rows(outcomes: Sequence[BatchOutcome]) -> list[BatchSummaryRow]:
    return [BatchSummaryRow.from_outcome(outcome) for outcome in outcomes]


def summary_schema() -> pa.Schema:
    import pyarrow as pa

    return pa.schema([
        ("input", pa.string()), ("kind", pa.string()), ("status", pa.string()), ("error", pa.string()),
        ("host", pa.string()), ("poses", pa.int64()), ("constraints", pa.int64()),
        ("loop_closures", pa.int64()), ("loop_closures_rejected", pa.int64()), ("scans", pa.int64()),
        ("chi2_initial", pa.float64()), ("chi2_final", pa.float64()),
        ("iterations", pa.map_(pa.string(), pa.int64())),
        ("wall_time_s", pa.map_(pa.string(), pa.float64())),
        ("time_total_s", pa.float64()),
    ])


def summary_table(outcomes: Sequence[BatchOutcome]) -> pa.Table:
    """The batch's rows as an Arrow table (maps for the per-stage iterations and times)."""
    import pyarrow as pa

    records: list[dict[str, Any]] = []
    for row in summary_rows(outcomes):
        record = asdict(row)
        for column in ("iterations", "wall_time_s"):  # Arrow maps are lists of (key, value) pairs
            if record[column] is not None:
                record[column] = list(record[column].items())
        records.append(record)
    return pa.Table.from_pylist(records, schema=summary_schema())


def write_batch_summary(path: Path, outcomes: Sequence[BatchOutcome]) -> Path:
    """Write the table to `path` (Parquet) atomically, creating its folder (when every input failed no
    replay created it); a failure leaves no partial file."""
    import pyarrow.parquet as pq

    table = summary_table(outcomes)
    prepare_output_dir(path.parent)
    with staged_outputs(path) as (temporary,):
        try:
            pq.write_table(table, temporary)
        except OSError as error:
            raise OutputError(f"{path}: cannot write the file: {error.strerror or error}") from error
    return path
