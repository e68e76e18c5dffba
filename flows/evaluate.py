"""Model evaluations for the calibration science, routed through the sweep pipeline.

The calibration code in ``engine_model`` takes an ``evaluate(plan) -> results``
callable.  Here that callable runs each batch as a ``sweep`` subflow on Dask
into its own folder (``<root>/<label>-NNN/``), so every simulation of a
calibration is a resumable Parquet sweep like any other: re-running the same
calibration into the same folder reads finished batches back instead of
recomputing them.  One Dask cluster serves all batches of a run (starting a
local cluster per batch would cost seconds each).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import pandas as pd

from flows.lifeline import hush_workers
from flows.store import read_results
from flows.sweep import DEFAULT_WORKERS, dask_runner, local_cluster_kwargs, sweep_flow

from engine_model.io import write_parquet  # noqa: E402


@contextlib.contextmanager
def shared_cluster(workers: int = DEFAULT_WORKERS, address: str | None = None):
    """Yield a scheduler address: ``address`` as given, or a local cluster of ``workers`` x 1 thread."""
    if address:
        yield address
        return
    from distributed import LocalCluster

    with LocalCluster(**local_cluster_kwargs(workers)) as cluster:
        try:
            yield cluster.scheduler_address
        finally:   # the workers' own reports of the close that follows are expected: hush them first
            hush_workers([getattr(n.process, "pid", None) for n in cluster.workers.values()
                          if getattr(n, "process", None) is not None])


class SweepEvaluator:
    """``evaluate(plan) -> results`` through ``sweep`` subflows on one Dask scheduler.

    Parameters
    ----------
    root : path
        Folder under which each batch gets ``<label>-NNN/`` (plan, manifest, parts).
    address : str
        Dask scheduler address (see :func:`shared_cluster`).
    spec : str, optional
        Engine spec TOML path (None: embedded default); a run's calibrated engine is its ``engine.toml``.
    step_deg, tolerance : float
        Solver settings [deg], [-].
    label : str
        Folder prefix of the batches.
    progress : bool
        Progress bar per batch.
    title : str, optional
        What the progress line calls these batches (e.g. ``calibration airflow``); ``label`` by default.
    """

    def __init__(self, root, address: str, spec: str | None = None, step_deg: float = 0.5,
                 tolerance: float = 1e-3, label: str = "batch", progress: bool = True, title: str | None = None):
        self.root = Path(root)
        self.address = address
        self.spec = spec
        self.step_deg = step_deg
        self.tolerance = tolerance
        self.label = label
        self.progress = progress
        self.title = title or label
        self.calls = 0
        self.points = 0

    def __call__(self, plan: pd.DataFrame) -> pd.DataFrame:
        out = self.root / f"{self.label}-{self.calls:03d}"
        self.calls += 1
        self.points += len(plan)
        plan = plan.reset_index(drop=True)
        if "point_id" not in plan.columns:
            plan = plan.assign(point_id=[f"q{i:06d}" for i in range(len(plan))])
        src = write_parquet(plan, out / "plan_input.parquet")
        flow = sweep_flow.with_options(task_runner=dask_runner(address=self.address),
                                       flow_run_name=f"{self.label}-{self.calls - 1:03d}")
        flow(plan=str(src), out=str(out), spec=self.spec, step_deg=self.step_deg, tolerance=self.tolerance,
             progress=self.progress, label=f"{self.title} #{self.calls}")
        res = read_results(out)
        if list(res["point_id"]) != list(plan["point_id"].astype(str)):
            raise RuntimeError(f"{out}: the sweep did not return every planned point exactly once")
        return res.drop(columns=["plan_row"], errors="ignore")
