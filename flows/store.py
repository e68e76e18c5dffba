"""The on-disk layout of a sweep: chunked Parquet parts, a manifest, and execution records.

    <out>/plan.parquet                the validated plan the sweep ran (point order kept)
    <out>/manifest.json               hashes, counts, timings; ``status`` is "complete" only at the end
    <out>/sweep/part-NNNNN.parquet    one file per chunk, written atomically (temp file + rename)
    <out>/sweep/_attempts/            one small file per chunk execution (for audits and tests)

Every part carries, in its Parquet key-value metadata, the hash of what it was
computed from (spec, solver, the chunk's points); a resumed sweep keeps the
parts whose hash matches and computes only the rest.  Files whose names start
with ``_`` or ``.`` (attempt records, temp files) are ignored by
``pyarrow.dataset`` and ``pandas.read_parquet`` on the folder, so the folder
reads as one dataset of finished chunks.

No physics here, and no Prefect: plain functions over DataFrames and paths.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import uuid
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from engine_model import RESULT_COLUMNS
from engine_model.io import atomic_write

PART_META_KEY = b"mbc_chunk"
PART_GLOB = "part-*.parquet"
RUN_STRETCH = 1.25   # a run of one operating condition up to 1.25 chunks stays in one chunk (see chunk_bounds)

# dtypes of the result columns in the dataset (everything else float64)
_RESULT_TYPES = {"converged": pa.bool_(), "cycles_run": pa.int64(), "status": pa.string()}
EXTRA_RESULT_COLUMNS = ("fuel_burned_mg_per_cycle", "gross_work_j_per_cycle")


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def frame_hash(df: pd.DataFrame) -> str:
    """Stable content hash of a table (column names, order and values; float repr exact)."""
    return sha256_text(df.to_csv(index=False, float_format="%.17g", lineterminator="\n"))


def solver_hash(solver) -> str:
    return sha256_text(json.dumps(asdict(solver), sort_keys=True))


def chunk_bounds(n_points: int, chunk_size: int, groups=None, stretch: float = RUN_STRETCH) -> list[tuple[int, int]]:
    """[start, stop) row ranges of consecutive chunks covering ``n_points`` rows.

    With ``groups`` (one hashable key per row), chunks end at a change of key
    where possible: the simulator reuses the converged state between
    consecutive rows of one operating condition, and a chunk boundary inside
    such a run costs a cold start.  A chunk then holds whole runs of rows up to
    ``chunk_size``.  A run up to ``stretch * chunk_size`` rows stays whole (one
    slightly longer task is cheaper than a cold start plus one more task); a
    longer run is cut into the fewest near-equal pieces of at most
    ``chunk_size`` rows.  Deterministic in the plan and ``chunk_size``, which
    resuming relies on.
    """
    if chunk_size < 1:
        raise ValueError(f"chunk_size = {chunk_size} must be >= 1")
    if stretch < 1.0:
        raise ValueError(f"stretch = {stretch} must be >= 1")
    if groups is None:
        return [(s, min(s + chunk_size, n_points)) for s in range(0, n_points, chunk_size)]
    keys = list(groups)
    if len(keys) != n_points:
        raise ValueError(f"groups has {len(keys)} keys for {n_points} rows")
    runs, start = [], 0
    for i in range(1, n_points + 1):
        if i == n_points or keys[i] != keys[i - 1]:
            runs.append((start, i))
            start = i
    longest = max(chunk_size, int(stretch * chunk_size))
    bounds, cur = [], None
    for a, b in runs:
        if b - a > longest:                           # a long run: near-equal pieces of at most chunk_size
            if cur is not None:
                bounds.append(cur)
            pieces = -(-(b - a) // chunk_size)
            edges = [a + (k * (b - a)) // pieces for k in range(pieces + 1)]
            bounds.extend(zip(edges[:-2], edges[1:-1]))
            cur = (edges[-2], b)                     # the last piece stays open for short runs after it
            continue
        if cur is not None and (b - cur[0]) <= chunk_size:
            cur = (cur[0], b)                        # the run fits into the open chunk
        else:
            if cur is not None:
                bounds.append(cur)
            cur = (a, b)
    if cur is not None:
        bounds.append(cur)
    return bounds


def chunk_key(points: pd.DataFrame, spec_hash: str, solver_h: str) -> str:
    """What a chunk's results depend on: the engine spec, the solver settings and its points."""
    return sha256_text(f"{spec_hash}|{solver_h}|{frame_hash(points)}")


def part_path(sweep_dir: Path, chunk: int) -> Path:
    return Path(sweep_dir) / f"part-{chunk:05d}.parquet"


def result_schema(plan: pd.DataFrame) -> pa.Schema:
    """Arrow schema of the dataset: the plan's columns with their types, then the result columns.

    Fixed for the whole sweep, so every part has the same column names and
    types (a chunk whose points all failed still writes float NaN, not nulls
    of another type).
    """
    fields = [pa.field(c, pa.string() if c == "point_id" else pa.Schema.from_pandas(plan[[c]], preserve_index=False)
                       .field(c).type) for c in plan.columns]
    for c in list(RESULT_COLUMNS) + list(EXTRA_RESULT_COLUMNS):
        if c not in plan.columns:
            fields.append(pa.field(c, _RESULT_TYPES.get(c, pa.float64())))
    return pa.schema(fields)


def write_part(df: pd.DataFrame, path: Path, schema: pa.Schema, meta: dict) -> Path:
    """Write one chunk's rows atomically, cast to the sweep schema, with ``meta`` in the file metadata."""
    cols = {}
    for f in schema:
        s = df[f.name] if f.name in df.columns else pd.Series([None] * len(df))
        if pa.types.is_string(f.type):
            s = s.astype(object).where(s.notna(), None).map(lambda v: v if v is None else str(v))
        cols[f.name] = pa.array(s.to_list() if pa.types.is_string(f.type) else s.to_numpy(), type=f.type,
                                from_pandas=True)
    table = pa.table(cols, schema=schema)
    table = table.replace_schema_metadata({PART_META_KEY: json.dumps(meta, sort_keys=True).encode()})
    return atomic_write(path, lambda tmp: pq.write_table(table, tmp))


def read_part_meta(path: Path) -> dict | None:
    """The metadata a part was written with, or None if the file is unreadable (then it is recomputed)."""
    try:
        md = pq.read_schema(path).metadata or {}
        return json.loads(md[PART_META_KEY])
    except Exception:  # noqa: BLE001 - a torn or foreign file is simply not a finished chunk
        return None


def record_attempt(sweep_dir: Path, chunk: int) -> None:
    """Leave a record that chunk ``chunk`` started executing (best effort: never fails the chunk).

    Written by the worker, so on a cluster without a shared file system the
    record is simply absent; results never depend on it.
    """
    try:
        d = Path(sweep_dir) / "_attempts"
        d.mkdir(parents=True, exist_ok=True)
        name = f"chunk-{chunk:05d}.{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        (d / name).write_text("")
    except OSError:
        pass


def attempt_counts(sweep_dir: Path) -> dict[int, int]:
    """Number of recorded executions per chunk."""
    counts: dict[int, int] = {}
    d = Path(sweep_dir) / "_attempts"
    if d.is_dir():
        for p in d.iterdir():
            if p.name.startswith("chunk-"):
                c = int(p.name.split(".")[0].split("-")[1])
                counts[c] = counts.get(c, 0) + 1
    return counts


def read_results(out_dir, columns: list[str] | None = None) -> pd.DataFrame:
    """All finished points of a sweep as one DataFrame (order of the plan; ``columns`` to read only some)."""
    sweep = Path(out_dir) / "sweep"
    parts = sorted(sweep.glob(PART_GLOB))
    if not parts:
        return pd.DataFrame()
    df = pd.read_parquet(sweep, columns=None if columns is None else list(dict.fromkeys([*columns, "plan_row"])))
    if "plan_row" in df.columns:
        df = df.sort_values("plan_row", kind="stable").reset_index(drop=True)
    return df


def summarize(df: pd.DataFrame) -> dict:
    """Counts of a result table: points, converged, not converged, failed."""
    if df.empty:
        return {"points": 0, "ok": 0, "not_converged": 0, "failed": 0}
    status = df["status"].astype(str)
    failed = status.str.startswith("failed") | status.str.startswith("error")
    return {"points": int(len(df)), "ok": int((status == "ok").sum()),
            "not_converged": int((status == "not converged").sum()), "failed": int(failed.sum())}


def numeric_equal(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    """Exact equality of two result tables (NaN equal to NaN), for determinism checks."""
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        return False
    for c in a.columns:
        x, y = a[c].to_numpy(), b[c].to_numpy()
        if x.dtype.kind == "f" and y.dtype.kind == "f":
            if not np.array_equal(x, y, equal_nan=True):
                return False
        elif not (pd.Series(x).astype(str) == pd.Series(y).astype(str)).all():
            return False
    return True
