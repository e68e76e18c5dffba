"""What every stage of a run receives: the run folder, the calibrated engine, the cluster, the bench data."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from engine_model.calibrated import CalibratedEngine
from flows.evaluate import SweepEvaluator
from flows.settings import RunSettings

#: File name of the calibrated engine in a run folder (a TOML engine spec ``--spec`` accepts).
ENGINE_FILE = "engine.toml"
#: File name of the run's copy of the bench data it was calibrated on (as read, before validation).
BENCH_FILE = "bench.parquet"


@dataclass(frozen=True)
class StageContext:
    """Inputs shared by the stages of one run.

    Attributes
    ----------
    work : Path
        Run folder being written.
    engine : CalibratedEngine
        The engine every simulation uses (calibrated after the calibration stage).
    engine_file : str or None
        TOML file the sweep workers load that engine from (None: the embedded default spec).
    address : str
        Dask scheduler address.
    settings : RunSettings
    bench : DataFrame or None
        Validated bench data.
    bench_source : str
        Where the bench data came from (for reports).
    progress : bool
        Progress output on stderr.
    stage : str
        Name of the stage being run (progress lines say which stage a sweep belongs to).
    """

    work: Path
    engine: CalibratedEngine
    engine_file: str | None
    address: str
    settings: RunSettings
    bench: pd.DataFrame | None = None
    bench_source: str = ""
    progress: bool = True
    stage: str = ""

    def evaluator(self, label: str, step_deg: float | None = None, tolerance: float = 1e-3) -> SweepEvaluator:
        """``evaluate(plan) -> results`` running each batch as a resumable sweep under ``work/sweeps/``."""
        return SweepEvaluator(self.work / "sweeps", self.address, spec=self.engine_file,
                              step_deg=self.settings.step_deg if step_deg is None else step_deg,
                              tolerance=tolerance, label=label, progress=self.progress,
                              title=f"{self.stage} {label}".strip())

    def with_engine(self, engine: CalibratedEngine) -> "StageContext":
        """The context with ``engine`` written into the run folder and used by every later sweep."""
        path = engine.write(self.work / ENGINE_FILE)
        return dataclasses.replace(self, engine=engine, engine_file=str(path))
