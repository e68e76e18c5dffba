"""The ``sweep`` flow: simulate a plan of operating points in chunks on Dask workers, into Parquet.

    plan (CSV/Parquet) --validate--> chunks of consecutive points --Dask--> part-NNNNN.parquet

* Chunks are consecutive rows of the plan (the simulator reuses the converged
  state between consecutive rows of one operating condition, so a Wiebe grid
  keeps its points together), sized so that a Dask task runs a few seconds
  (Prefect's per-task overhead is ~0.1 s; docs/stack.md).
* The driver (this flow) writes each part atomically as soon as its chunk
  finishes; workers only compute and return a small DataFrame, so no shared
  file system is needed between the driver and a remote cluster.
* Re-running with the same output folder resumes: parts whose metadata hash
  matches are kept, the rest are computed.  A folder that holds a different
  plan or spec is refused, never mixed.
* Failed tasks are retried by Prefect (and re-scheduled by Dask when a worker
  dies); a point that fails or does not converge inside the simulator is a row
  with ``converged = False`` and a ``status`` saying why; a chunk that still
  fails after its retries is listed in the manifest with the error, and the
  flow ends Failed so that a re-run computes it.
* The task calls ``engine_model.simulate`` from the installed package, which
  reaches the numba kernels through their module, so workers load compiled
  kernels from numba's on-disk cache instead of recompiling (docs/stack.md).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import pandas as pd

from flows import prefect_env  # noqa: F401  (quiet/offline Prefect defaults before prefect is imported)
from flows import store
from flows.lifeline import checkpoint, deferred_stops, hush_workers, is_stop

import dask  # noqa: E402
from prefect import flow, task  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402
from distributed import as_completed as dask_as_completed  # noqa: E402

from engine_model import SolverSettings, load_spec  # noqa: E402
from engine_model.version import package_version  # noqa: E402
from engine_model.sim.simulate import simulate, spec_columns, validate_points  # noqa: E402  (installed module: pickled by reference)
from engine_model.doe import validate_plan  # noqa: E402
from engine_model.contracts import throttle_to_pct  # noqa: E402
from engine_model.io import read_table, write_json, write_parquet  # noqa: E402

DEFAULT_WORKERS = 2
TARGET_CHUNK_S = 5.0   # wall time aimed at per Dask task [s]: the top of the 1-5 s, since each task
                       # costs ~0.15-0.3 s of Prefect/Dask overhead (benchmarks/bench_sweep.py: 3 s gave +13 %)
EST_POINT_S = 0.09     # median cost of one point at 0.5 deg (benchmarks/bench_cycle.py) [s]
IN_FLIGHT_PER_THREAD = 3  # chunks submitted ahead per worker thread
POLL_S = 0.05  # [s] wait between looks for a finished chunk (a stop is acted on within it)
LOW_LEVEL_LOG_LENGTH = 20  # Dask's debug logs of recent messages (see dask_runner)


# ----------------------------------------------------------------------------- plan handling
def prepare_plan(plan: pd.DataFrame, spec, source: str = "plan") -> pd.DataFrame:
    """Validate a plan and give it a unique text ``point_id`` and a ``plan_row`` (0..n-1).

    Raises
    ------
    ValueError
        Naming ``source``, the row, the column and the value (missing columns,
        NaN, out-of-range values, duplicate ``point_id``).
    """
    if len(plan) == 0:
        raise ValueError(f"{source}: the plan has no rows")
    pts = validate_points(spec, plan, source=source)
    if "point_id" not in pts.columns:
        width = max(5, len(str(len(pts))))
        pts.insert(0, "point_id", [f"p{i:0{width}d}" for i in range(len(pts))])
    validate_plan(pts, source, spec)   # point_id: present, unique
    ids = pts["point_id"].astype(str)
    pts["point_id"] = ids.to_numpy(dtype=object)
    pts["plan_row"] = range(len(pts))
    return pts


def state_groups(pts: pd.DataFrame) -> list[tuple]:
    """Per row, the key under which consecutive rows share a converged state in ``simulate``."""
    cols = ["speed_rpm", "throttle_pct", "lambda", "p_amb_pa", "t_amb_k"] + spec_columns(pts)
    return list(pts[cols].itertuples(index=False, name=None))


def auto_chunk_size(n_points: int, workers: int, step_deg: float = 0.5) -> int:
    """Points per chunk: about ``TARGET_CHUNK_S`` of work, but at least two chunks per worker.

    The cost of a point scales with the number of crank-angle steps (1/``step_deg``).
    """
    size = max(1, round(TARGET_CHUNK_S / (EST_POINT_S * 0.5 / step_deg)))
    per_worker = math.ceil(n_points / max(2 * workers, 1))
    return max(1, min(size, per_worker))


# ----------------------------------------------------------------------------- worker side
def run_points(spec, points: pd.DataFrame, solver: SolverSettings) -> pd.DataFrame:
    """Simulate a chunk; an exception inside one point becomes that point's ``status``, not a lost chunk."""
    try:
        res = simulate(spec, points, solver)
    except Exception:  # noqa: BLE001 - fall back to point by point to isolate the bad one
        rows = []
        for i in range(len(points)):
            one = points.iloc[[i]]
            try:
                rows.append(simulate(spec, one, solver))
            except Exception as exc:  # noqa: BLE001 - recorded with its reason, never dropped
                r = one.copy()
                r["converged"] = False
                r["cycles_run"] = 0
                r["status"] = f"error: {type(exc).__name__}: {exc}"
                rows.append(r)
        res = pd.concat(rows, ignore_index=True)
    # wall-clock time is not a result: it would make two identical runs differ
    return res.drop(columns=["sim_time_s"], errors="ignore")


@task(name="simulate-chunk", task_run_name="chunk-{chunk}", retries=2, retry_delay_seconds=1,
      cache_policy=NO_CACHE, persist_result=False)
def simulate_chunk(spec, points: pd.DataFrame, solver: SolverSettings, chunk: int, sweep_dir: str):
    """Prefect task: simulate one chunk on a Dask worker; returns (chunk, results, seconds)."""
    store.record_attempt(Path(sweep_dir), chunk)
    t0 = time.perf_counter()
    res = run_points(spec, points, solver)
    return chunk, res, time.perf_counter() - t0


# ----------------------------------------------------------------------------- driver side
class Progress:
    """A one-line progress bar on stderr: ``label``, chunks, points, throughput, ETA.

    ``keep``: end with a newline when done (a top-level sweep); otherwise the line is overwritten by the
    next one (the many small sweeps of a run's stage, labelled with the stage and their purpose).
    """

    def __init__(self, total_chunks: int, total_points: int, label: str = "sweep", enabled: bool = True,
                 keep: bool = True):
        self.tc, self.tp, self.label, self.enabled, self.keep = total_chunks, total_points, label, enabled, keep
        self.c = self.p = 0
        self.t0 = time.perf_counter()
        self.width = 0

    def update(self, points: int) -> None:
        self.c += 1
        self.p += points
        if not self.enabled:
            return
        el = time.perf_counter() - self.t0
        rate = self.p / el if el > 0 else 0.0
        eta = f"eta {(self.tp - self.p) / rate:4.0f} s" if rate > 0 else "eta ?"
        w = 20
        f = int(w * self.p / max(self.tp, 1))
        line = (f"{self.label} [{'#' * f}{'.' * (w - f)}] {self.p}/{self.tp} points, {self.c}/{self.tc} chunks, "
                f"{rate:5.1f} pt/s, {eta}")
        self.width = max(self.width, len(line))
        sys.stderr.write("\r" + line.ljust(self.width))
        if self.c == self.tc:
            sys.stderr.write("\n" if self.keep else "\r")
        sys.stderr.flush()


def _manifest_base(spec, spec_path, plan_hash, solver, chunk_size, n_points, n_chunks) -> dict:
    return {
        "kind": "sweep", "package_version": package_version(), "engine": spec.name, "spec": spec_path or "embedded",
        "spec_hash": spec.spec_hash(), "plan_hash": plan_hash, "solver": solver.__dict__,
        "solver_hash": store.solver_hash(solver), "chunk_size": chunk_size, "points": n_points,
        "chunks": n_chunks,
    }


def _check_compatible(man_path: Path, base: dict) -> None:
    """Refuse to resume into a folder that holds a different plan, spec or solver."""
    if not man_path.exists():
        return
    try:
        old = json.loads(man_path.read_text())
    except (OSError, ValueError):
        return   # torn manifest: parts carry their own hashes
    for key in ("spec_hash", "plan_hash", "solver_hash"):
        if key in old and old[key] != base[key]:
            raise ValueError(f"{man_path.parent}: holds a sweep with a different {key.split('_')[0]} "
                             f"({old[key][:12]} vs {base[key][:12]}); use another --out folder")


def dask_runner(workers: int = DEFAULT_WORKERS, address: str | None = None):
    """A DaskTaskRunner: an existing scheduler at ``address``, or a local cluster of ``workers`` x 1 thread."""
    from prefect_dask import DaskTaskRunner

    # Dask's BatchedSend keeps its last `low-level-log-length` (default 1000) messages for debugging; every
    # task submission is one, holding the pickled chunk (~0.25 MB here), so the driver grew by ~240 MB over
    # the first 1000 chunks (benchmarks/bench_sweep.py).  A short log keeps the driver flat.
    dask.config.set({"distributed.admin.low-level-log-length": LOW_LEVEL_LOG_LENGTH})
    if address:
        return DaskTaskRunner(address=address)
    # The workers' statistical profiler (a thread sampling every 10 ms, for the dashboard) competes with the
    # kernels, which hold the GIL for a whole point; the local cluster's nannies pass this config to their
    # workers.  An external cluster keeps its own settings.
    dask.config.set({"distributed.worker.profile.enabled": False})
    return DaskTaskRunner(cluster_kwargs=local_cluster_kwargs(workers))


def local_cluster_kwargs(workers: int) -> dict:
    """``LocalCluster`` options of a run's own cluster: ``workers`` x 1 thread, everything on 127.0.0.1.

    The scheduler, the workers, their nannies and the dashboard listen on the loopback interface only
    (Dask's ``dashboard_address=":0"`` would listen on every interface); the workers ignore Ctrl-C, which
    the driver handles by closing the cluster (``flows.lifeline``).
    """
    if workers < 1:
        raise ValueError(f"workers = {workers} must be >= 1")
    return {"n_workers": workers, "threads_per_worker": 1, "processes": True, "host": "127.0.0.1",
            "dashboard_address": "127.0.0.1:0", "preload": ["flows.lifeline"]}


def env_runner():
    """The runner of served (deployed) sweeps: ``MBC_DASK_ADDRESS`` or ``MBC_WORKERS`` local workers."""
    return dask_runner(int(os.environ.get("MBC_WORKERS", DEFAULT_WORKERS)), os.environ.get("MBC_DASK_ADDRESS"))


@flow(name="sweep", log_prints=False, validate_parameters=False, task_runner=env_runner())
def sweep_flow(plan: str, out: str, spec: str | None = None, step_deg: float = 0.5, tolerance: float = 1e-3,
               chunk_size: int | None = None, progress: bool = True, label: str | None = None) -> dict:
    """Simulate every point of the plan file ``plan`` into ``out``/sweep/ (resumable).

    Parameters
    ----------
    plan : str
        CSV or Parquet operating-point table (contract columns, Wiebe columns included).
    out : str
        Output folder (created; re-using it resumes).
    spec : str, optional
        Engine spec TOML; the embedded Yamaha R6 FS by default.
    step_deg, tolerance : float
        Solver crank-angle step [deg] and cycle-convergence tolerance [-].
    chunk_size : int, optional
        Points per Dask task; automatic (a few seconds of work) by default,
        taken from the manifest when resuming.
    progress : bool
        Show a progress bar on stderr.
    label : str, optional
        What this sweep is for, on its progress line (e.g. ``model campaign-003``); a labelled sweep's
        line is overwritten by the next one.  None: ``sweep``, and the line stays.

    Returns
    -------
    dict
        The manifest written to ``out``/manifest.json.
    """
    t_start = time.perf_counter()
    eng = load_spec(spec)
    solver = SolverSettings(step_deg=step_deg, tolerance=tolerance)
    pts = prepare_plan(read_table(plan), eng, source=str(plan))
    out_dir = Path(out)
    sweep_dir = out_dir / "sweep"
    man_path = out_dir / "manifest.json"
    plan_h = store.frame_hash(pts)
    if chunk_size is None and man_path.exists():
        try:
            chunk_size = int(json.loads(man_path.read_text())["chunk_size"])
        except (OSError, ValueError, KeyError):
            chunk_size = None
    if chunk_size is None:
        chunk_size = auto_chunk_size(len(pts), _worker_count(), step_deg)
    bounds = store.chunk_bounds(len(pts), chunk_size, groups=state_groups(pts))
    base = _manifest_base(eng, spec, plan_h, solver, chunk_size, len(pts), len(bounds))
    _check_compatible(man_path, base)
    sweep_dir.mkdir(parents=True, exist_ok=True)
    if not (out_dir / "plan.parquet").exists():
        write_parquet(pts, out_dir / "plan.parquet")
    started = _dt.datetime.now().isoformat(timespec="seconds")
    write_json({**base, "status": "running", "started": started}, man_path)

    schema = store.result_schema(pts)
    todo, skipped, counts = _resume_state(sweep_dir, pts, bounds, eng.spec_hash(), store.solver_hash(solver))
    bar = Progress(len(todo), sum(b - a for _, a, b, _ in todo), label=label or "sweep", enabled=progress,
                   keep=label is None)
    if progress and skipped and label is None:
        print(f"resuming: {skipped} of {len(bounds)} chunks already done", file=sys.stderr)

    keys = {c: key for c, _, _, key in todo}
    failed, timing = {}, {"compute_s": 0.0, "first_result_s": None, "t_start": t_start}
    # Completion order via the Dask futures; each is released as soon as its part is on disk, so that a
    # worker lost later does not make Dask recompute a finished chunk (Dask recomputes lost results that a
    # client still holds), and the driver holds nothing for finished chunks.
    # A sliding window of submitted chunks (a few per worker thread) keeps the driver's memory flat in the
    # size of the plan and brings the first results early.
    window = max(2, IN_FLIGHT_PER_THREAD * _worker_count())
    queue = iter(todo)
    pending = {}

    def submit_next() -> bool:
        item = next(queue, None)
        if item is None:
            return False
        c, a, b, _ = item
        fut = simulate_chunk.submit(eng, pts.iloc[a:b], solver, c, str(sweep_dir))
        pending[fut.wrapped_future] = (c, fut)
        return True

    try:
        _collect(pending, submit_next, window, keys, sweep_dir, schema, bar, counts, failed, timing)
    except BaseException as exc:   # Ctrl-C / SIGTERM or a driver error: say so on disk
        state = "interrupted" if is_stop(exc) else "failed"
        if state == "interrupted":
            hush_workers()   # they are about to be stopped: their reports of it are expected
        write_json({**base, "status": state, "started": started, "error": repr(exc)[:300],
                    "counts": counts, "missing_points": len(pts) - counts["points"]}, man_path)
        raise
    compute_s, t_first = timing["compute_s"], timing["first_result_s"]

    wall = time.perf_counter() - t_start
    complete = not failed and counts["points"] == len(pts)
    man = {**base, "status": "complete" if complete else "incomplete", "started": started,
           "finished": _dt.datetime.now().isoformat(timespec="seconds"),
           "chunks_computed": len(todo) - len(failed), "chunks_skipped": skipped,
           "chunks_failed": {str(k): v for k, v in sorted(failed.items())},
           "counts": counts, "missing_points": len(pts) - counts["points"],
           "timings": {"wall_s": round(wall, 2), "compute_s": round(compute_s, 2),
                       "first_result_s": None if t_first is None else round(t_first, 2),
                       "points_per_s": round(sum(b - a for _, a, b, _ in todo) / wall, 2) if todo else 0.0},
           "dask": _dask_description()}
    write_json(man, man_path)
    if failed:
        raise RuntimeError(f"{len(failed)} chunk(s) failed after retries ({sorted(failed)}); their points are "
                           f"listed as missing in {man_path}; run the same command again to compute them")
    return man


def _collect(pending: dict, submit_next, window: int, keys: dict, sweep_dir: Path, schema, bar: "Progress",
             counts: dict, failed: dict, timing: dict) -> None:
    """Keep ``window`` chunks in flight; write each finished chunk's part as it arrives (driver side)."""
    checkpoint()   # SIGTERM stops like Ctrl-C inside the flow too (flows/lifeline.py)
    with deferred_stops():   # a stop must not land inside Dask's or Prefect's locks: it is raised at a checkpoint
        _collect_loop(pending, submit_next, window, keys, sweep_dir, schema, bar, counts, failed, timing)


def _next_done(done_iter):
    """The next finished future of ``done_iter`` (None when none is left), waiting in short steps.

    Between the steps :func:`checkpoint` raises a stop that arrived meanwhile (the wait runs inside
    :func:`flows.lifeline.deferred_stops`, so the stop cannot land inside ``as_completed``'s lock).
    """
    while not done_iter.has_ready():
        checkpoint()
        if done_iter.is_empty():
            return None
        time.sleep(POLL_S)
    return next(done_iter)


def _collect_loop(pending: dict, submit_next, window: int, keys: dict, sweep_dir: Path, schema, bar: "Progress",
                  counts: dict, failed: dict, timing: dict) -> None:
    while len(pending) < window and submit_next():
        pass
    done_iter = dask_as_completed(list(pending), loop=_runner_client().loop)
    while (dfut := _next_done(done_iter)) is not None:
        if submit_next():
            done_iter.add(next(reversed(pending)))
        c, fut = pending.pop(dfut)
        try:
            c, res, secs = fut.result()
        except Exception as exc:  # noqa: BLE001 - reported in the manifest; a re-run computes it
            if is_stop(exc):   # a stop that a library wrapped in an ordinary error
                raise
            failed[c] = f"{type(exc).__name__}: {exc}"
            traceback.print_exception(exc, file=sys.stderr, limit=3)
            bar.update(0)
            continue
        finally:
            dfut.release()
            del fut
        store.write_part(res, store.part_path(sweep_dir, c), schema,
                         {"key": keys[c], "chunk": c, "rows": len(res), "seconds": round(secs, 3)})
        timing["compute_s"] += secs
        if timing["first_result_s"] is None:
            timing["first_result_s"] = time.perf_counter() - timing["t_start"]
        bar.update(len(res))
        _add_counts(counts, store.summarize(res))
        del res
        checkpoint()   # a stop whose exception a library lost is acted on once this chunk is on disk


def _resume_state(sweep_dir: Path, pts: pd.DataFrame, bounds: list, spec_hash: str, solver_h: str):
    """Chunks still to compute ``[(chunk, first_row, end_row, key)]``, chunks already on disk, their counts.

    A part on disk counts as done only when its stored key matches the chunk's inputs (spec, solver,
    points); stale or torn parts, and parts of another chunking, are removed.
    """
    todo, skipped = [], 0
    counts = {"points": 0, "ok": 0, "not_converged": 0, "failed": 0}   # summed per part: no dataset read
    for stale in sweep_dir.glob(store.PART_GLOB):   # parts of another chunking (e.g. an older version)
        try:
            index = int(stale.stem.split("-")[1])
        except (IndexError, ValueError):
            continue
        if index >= len(bounds):
            stale.unlink()
    for c, (a, b) in enumerate(bounds):
        key = store.chunk_key(pts.iloc[a:b], spec_hash, solver_h)
        path = store.part_path(sweep_dir, c)
        if path.exists():
            meta = store.read_part_meta(path)
            if meta is not None and meta.get("key") == key:
                skipped += 1
                _add_counts(counts, store.summarize(pd.read_parquet(path, columns=["status"])))
                continue
            path.unlink()   # stale or torn: recompute
        todo.append((c, a, b, key))
    return todo, skipped, counts


def _add_counts(total: dict, part: dict) -> None:
    for k, v in part.items():
        total[k] = total.get(k, 0) + v


def _runner_client():
    from prefect.context import FlowRunContext

    ctx = FlowRunContext.get()
    runner = getattr(ctx, "task_runner", None) if ctx else None
    return getattr(runner, "_client", None) or getattr(runner, "client", None)


def _worker_count() -> int:
    try:
        client = _runner_client()
        return max(1, sum(client.nthreads().values())) if client is not None else DEFAULT_WORKERS
    except Exception:  # noqa: BLE001 - only used to size chunks
        return DEFAULT_WORKERS


def _dask_description() -> dict:
    try:
        client = _runner_client()
        info = client.scheduler_info()
        return {"scheduler": info.get("address"), "workers": len(info.get("workers", {})),
                "threads": sum(client.nthreads().values())}
    except Exception:  # noqa: BLE001 - descriptive only
        return {}


def run_sweep(plan, out, spec: str | None = None, workers: int = DEFAULT_WORKERS, dask_address: str | None = None,
              step_deg: float = 0.5, tolerance: float = 1e-3, chunk_size: int | None = None,
              progress: bool = True, throttle_unit: str = "pct") -> dict:
    """Validate, then run :func:`sweep_flow` on a Dask runner under one Prefect API for the whole run.

    ``plan`` may be a path or a DataFrame (then saved as ``out``/plan_input.parquet
    first).  Bad input raises ValueError before any folder is created.  A plan file whose
    ``throttle_pct`` lies all within 0-1 is refused; ``throttle_unit="fraction"`` converts it to percent
    (the converted plan is saved as ``out``/plan_input.parquet).
    """
    eng = load_spec(spec)
    out = Path(out)
    if not isinstance(plan, pd.DataFrame):
        converted = throttle_to_pct(read_table(plan), f"plan file {plan}", throttle_unit)
        if throttle_unit != "pct":
            plan = converted
    if isinstance(plan, pd.DataFrame):
        prepare_plan(plan, eng, source="plan")
        plan_path = out / "plan_input.parquet"
        write_parquet(plan, plan_path)
    else:
        plan_path = Path(plan)
        prepare_plan(read_table(plan_path), eng, source=str(plan_path))
    if chunk_size is not None and chunk_size < 1:
        raise ValueError(f"--chunk-size = {chunk_size} must be >= 1")
    with prefect_env.prefect_api(verbose=progress):
        runner_flow = sweep_flow.with_options(task_runner=dask_runner(workers, dask_address))
        return runner_flow(plan=str(plan_path), out=str(out), spec=spec, step_deg=step_deg, tolerance=tolerance,
                           chunk_size=chunk_size, progress=progress)
