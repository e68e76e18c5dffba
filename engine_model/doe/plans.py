"""Plan files: content hash, validation, save/load (Parquet + CSV + meta JSON), the example plans."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import warnings
from typing import Mapping
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from engine_model import io as _io
from engine_model.contracts import PLAN_COLUMNS
from engine_model.doe.designs import bench_order, full_factorial, sobol
from engine_model.doe.screening import feasibility
from engine_model.priors import BDUR_REF_DEG, WIEBE_M_REF, with_combustion
from engine_model.spec import EngineSpec, default_spec
from engine_model.version import package_version

__all__ = ["plan_hash", "save_plan", "validate_plan", "load_plan", "write_example_plans"]

_TEXT_COLUMNS = ("point_id", "base_point_id", "design", "infeasible_reason", "stop_reason")
_META_KEY = b"mbc_plan"


def plan_hash(plan: pd.DataFrame) -> str:
    """Stable content hash of a plan: sha256 hex of the canonical CSV.

    Canonical form: columns sorted by name, rows in plan order, no index,
    floats written round-trip exactly, missing text as ''.  Independent of
    ``attrs``, column order and CSV/Parquet round trips.
    """
    df = plan[sorted(plan.columns)].copy()
    for c in df.columns:
        if c in _TEXT_COLUMNS:
            df[c] = df[c].astype(object).where(df[c].notna(), "").astype(str)
        elif df[c].dtype.kind in "iuf":
            df[c] = df[c].astype(float)  # int 3000 and float 3000.0 hash alike
    text = df.to_csv(index=False, lineterminator="\n", float_format=None)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def save_plan(plan: pd.DataFrame, name: str, directory: str | Path = "doe_plans",
              metadata: Mapping | None = None) -> dict:
    """Write ``<name>.parquet``, ``<name>.csv`` and ``<name>.meta.json`` atomically.

    Parameters
    ----------
    plan : DataFrame
        The plan; its ``attrs`` supply ``generator``, ``seed``, ``bounds``.
    name : str
        File stem (letters, digits, '_', '-', '.').
    directory : str or Path
        Target folder (created if needed).
    metadata : dict, optional
        Extra JSON-able entries; they override the ones from ``attrs``.

    Returns
    -------
    dict
        ``{'parquet': Path, 'csv': Path, 'meta': Path, 'metadata': dict}``.  The
        metadata (``generator, seed, bounds, n_points, created_by`` =
        'engine_model <version>', ``created_at`` (UTC ISO 8601), ``plan_hash``,
        plus the other attrs) is in the Parquet schema metadata under
        ``b'mbc_plan'`` (JSON) and in the ``.meta.json``.
    """
    if not name or any(not (ch.isalnum() or ch in "_-.") for ch in name):
        raise ValueError(f"save_plan: name {name!r} may only use letters, digits, '_', '-', '.'")
    validate_plan(plan, f"save_plan({name!r})")
    meta = {k: v for k, v in plan.attrs.items()}
    meta.setdefault("generator", None)
    meta.setdefault("seed", None)
    meta.setdefault("bounds", None)
    meta.update(n_points=len(plan), created_by=f"engine_model {package_version()}",
                created_at=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                plan_hash=plan_hash(plan))
    meta.update(metadata or {})
    meta = _jsonable(meta)
    directory = Path(directory)
    df = plan.copy()
    df.attrs = {}
    table = pa.Table.from_pandas(df, preserve_index=False)
    table = table.replace_schema_metadata({**(table.schema.metadata or {}),
                                           _META_KEY: json.dumps(meta, sort_keys=True).encode()})
    paths = {"parquet": directory / f"{name}.parquet", "csv": directory / f"{name}.csv",
             "meta": directory / f"{name}.meta.json"}
    _io.atomic_write(paths["parquet"], lambda tmp: pq.write_table(table, tmp))
    _io.write_csv(df, paths["csv"], lineterminator="\n")
    _io.write_json(meta, paths["meta"])
    return {**paths, "metadata": meta}


def validate_plan(plan: pd.DataFrame, source: str, spec: EngineSpec | None = None) -> pd.DataFrame:
    """ValueError naming source, row, column and value for a plan that breaks the contract."""
    from engine_model.sim.simulate import validate_points

    missing = [c for c in PLAN_COLUMNS if c not in plan.columns]
    if missing:
        raise ValueError(f"{source}: missing required plan column(s) {missing}; required: {list(PLAN_COLUMNS)}")
    ids = plan["point_id"]
    for i, v in enumerate(ids):
        if pd.isna(v) or str(v).strip() == "":
            raise ValueError(f"{source}: row {i}, column 'point_id': value {v!r} is empty")
    dup = ids.astype(str).duplicated(keep="first").to_numpy()
    if dup.any():
        i = int(np.flatnonzero(dup)[0])
        j = int(np.flatnonzero(ids.astype(str).to_numpy() == str(ids.iloc[i]))[0])
        raise ValueError(f"{source}: row {i}, column 'point_id': value {ids.iloc[i]!r} duplicates row {j}")
    # validate_points checks the contract columns; a plan needs no Wiebe columns, so give it valid stand-ins
    probe = plan.copy()
    for col, val in (("bdur_10_90_deg", BDUR_REF_DEG), ("wiebe_m", WIEBE_M_REF)):
        if col not in probe.columns:
            probe[col] = val
    validate_points(default_spec() if spec is None else spec, probe, source=source)
    return plan


def load_plan(path: str | Path, spec: EngineSpec | None = None) -> pd.DataFrame:
    """Read and validate a plan from CSV or Parquet.

    Parameters
    ----------
    path : str or Path
        ``.csv`` (metadata from a sibling ``<stem>.meta.json`` if present) or
        ``.parquet`` (metadata from the ``b'mbc_plan'`` schema entry).
    spec : EngineSpec, optional
        Sets the speed limit; default :func:`engine_model.default_spec`.

    Returns
    -------
    DataFrame
        The plan, metadata in ``attrs`` (empty dict if none).  A warning is
        issued when the content no longer matches the stored ``plan_hash``.

    Raises
    ------
    ValueError
        Naming the file, the (0-based data) row, the column and the value:
        unreadable file, missing columns, empty or duplicate ``point_id``,
        non-finite or out-of-range operating-point values.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: file not found")
    suffix = p.suffix.lower()
    meta = {}
    try:
        if suffix == ".csv":
            head = pd.read_csv(p, nrows=0).columns
            exact = {"float_precision": "round_trip"} if int(pd.__version__.split(".")[0]) < 3 else {}  # pandas 3: default
            df = pd.read_csv(p, dtype={c: str for c in _TEXT_COLUMNS if c in head}, **exact)
            side = p.with_name(p.name[: -len(p.suffix)] + ".meta.json")
            if side.is_file():
                meta = json.loads(side.read_text())
        elif suffix in (".parquet", ".pq"):
            table = pq.read_table(p)
            raw = (table.schema.metadata or {}).get(_META_KEY)
            meta = json.loads(raw) if raw else {}
            df = table.to_pandas()
        else:
            raise ValueError(f"{p}: unsupported file type {suffix!r}; expected .csv or .parquet")
    except ValueError as exc:
        if str(exc).startswith(str(p)):
            raise
        raise ValueError(f"{p}: could not be read as {suffix[1:]}: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - any parser failure is reported with the file name
        raise ValueError(f"{p}: could not be read as {suffix[1:]}: {exc}") from None
    for c in _TEXT_COLUMNS:
        if c in df.columns and c != "point_id":
            df[c] = df[c].astype(object).where(df[c].notna(), "").astype(str)
    validate_plan(df, str(p), spec)
    df.attrs = dict(meta)
    stored = meta.get("plan_hash")
    if stored and stored != plan_hash(df):
        warnings.warn(f"{p}: content differs from the plan_hash stored at save time (edited by hand?)",
                      stacklevel=2)
    return df


def write_example_plans(directory: str | Path = "doe_plans", spec: EngineSpec | None = None) -> dict:
    """Write the two example plans of ``doe_plans/``.

    ``r6_full_factorial``: coarse ECU grid, throttle 5, 10, 20, 40, 60, 80,
    100 % x 3000-13000 rpm in 2000 rpm steps (42 points), spark and lambda
    from the priors, flagged by :func:`feasibility` with the quick model (not
    dropped), in bench order.  ``r6_sobol_64``: 64 scrambled Sobol' points
    over :data:`DEFAULT_BOUNDS`, seed 2012, in bench order.  Both carry the
    Wiebe columns of :func:`combustion_estimate` (:func:`with_combustion`), so
    ``mbc sweep`` runs them as they are.  Takes ~10 s.

    Returns
    -------
    dict
        name -> :func:`save_plan` result.
    """
    ff = full_factorial(speed_rpm=range(3000, 13001, 2000), throttle_pct=(5, 10, 20, 40, 60, 80, 100))
    ff = with_combustion(bench_order(feasibility(ff, spec=spec)))
    sb = with_combustion(bench_order(sobol(64, seed=2012)))
    return {"r6_full_factorial": save_plan(ff, "r6_full_factorial", directory),
            "r6_sobol_64": save_plan(sb, "r6_sobol_64", directory)}
