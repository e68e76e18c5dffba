"""Settings of ``mbc run``: which stages run and the knobs of each, as one frozen, JSON-able object."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from engine_model.calibration.settings import QUICK_CALIBRATION, CalibrationSettings
from engine_model.globalmodel.campaign import CampaignSettings

#: The stages of ``mbc run``, in order.  'model' is the virtual-bench campaign and the global model.
STAGES = ("calibration", "model", "maps", "gap")
#: Earlier names a user may still type for a stage.
STAGE_ALIASES = {"virtual_bench": "model"}


def parse_stages(text: str | None) -> tuple[str, ...]:
    """'calibration,maps' -> ('calibration', 'maps') in pipeline order; ValueError naming an unknown stage."""
    if not text:
        return STAGES
    asked = [STAGE_ALIASES.get(s.strip(), s.strip()) for s in text.split(",") if s.strip()]
    bad = [s for s in asked if s not in STAGES]
    if bad:
        raise ValueError(f"--stages: unknown stage(s) {bad}; known: {','.join(STAGES)}")
    if not asked:
        raise ValueError(f"--stages {text!r}: names no stage; give some of {','.join(STAGES)}")
    return tuple(s for s in STAGES if s in asked)


@dataclass(frozen=True)
class RunSettings:
    """Knobs of ``mbc run`` (defaults: the full job; :data:`QUICK` is the small one the tests run).

    eta_trans [-]: transmission efficiency assumed between crank and brake (paper: 0.95).
    step_deg [deg]: crank-angle step of every simulation.
    calibration: airflow-match and identification settings (grid sizes, iterations).
    doe_points, doe_seed, spark_offsets, doe_bounds: operating points on the virtual bench (D-optimal over
        throttle x speed from screened candidates) and the spark sweep run at each, offsets from the MBT prior [deg].
    doe_fill_points: of doe_points, those placed where the D-optimal ones leave the largest gaps (default 0).
    ident_grid: (n_bdur, n_m) of the cheap identification at the DOE points.
    map_throttle, map_speed: ECU breakpoints ('0,5,10' or 'start:stop:step'; None = EcuGrid default).
    learning_sizes, learning_seeds: learning curve of DOE designs.
    holdout: keyword arguments of the hold-out grid the global model is scored on.
    stages: which stages run; a stage left out is taken from the run folder (it must be there).
    """

    eta_trans: float = 0.95
    step_deg: float = 0.5
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    doe_points: int = 16
    doe_fill_points: int = 0
    spark_offsets: tuple = (-15, -10, -5, 0, 5)
    doe_bounds: dict = field(default_factory=dict)
    doe_seed: int = 0
    ident_grid: tuple = (6, 6)
    map_throttle: str | None = None
    map_speed: str | None = None
    learning_sizes: tuple = (12, 16, 24, 32, 48, 64)
    learning_seeds: tuple = (0, 1, 2)
    holdout: dict = field(default_factory=dict)
    stages: tuple = STAGES
    quick: bool = False

    def __post_init__(self):
        stages = tuple(STAGE_ALIASES.get(s, s) for s in self.stages)
        bad = [s for s in stages if s not in STAGES]
        if bad:
            raise ValueError(f"RunSettings.stages: unknown stage(s) {bad}; known: {list(STAGES)}")
        object.__setattr__(self, "stages", tuple(s for s in STAGES if s in stages))
        if not 0.5 <= self.eta_trans <= 1.0:
            raise ValueError(f"RunSettings.eta_trans = {self.eta_trans!r} must lie in [0.5, 1]")
        self.campaign()   # the campaign's own checks (e.g. doe_points)

    def campaign(self) -> CampaignSettings:
        """The virtual-bench campaign's settings."""
        return CampaignSettings(eta_trans=self.eta_trans, step_deg=self.step_deg, doe_points=self.doe_points,
                                doe_fill_points=self.doe_fill_points, spark_offsets=tuple(self.spark_offsets),
                                doe_bounds=dict(self.doe_bounds),
                                doe_seed=self.doe_seed, ident_grid=tuple(self.ident_grid),
                                learning_sizes=tuple(self.learning_sizes), learning_seeds=tuple(self.learning_seeds),
                                holdout=dict(self.holdout))

    def calibration_settings(self) -> CalibrationSettings:
        """The calibration's settings with the run's eta_trans and step."""
        return dataclasses.replace(self.calibration, eta_trans=self.eta_trans, step_deg=self.step_deg)


#: A small run for tests and smoke checks: 1 deg step, coarse searches, a 3 x 3 ECU grid.
QUICK = RunSettings(
    step_deg=1.0, calibration=QUICK_CALIBRATION, doe_points=10, spark_offsets=(-10, -5, 0),
    # the small run stays where the (uncalibrated, pessimistic) knock model lets sweeps run
    doe_bounds={"throttle_pct": (30.0, 100.0), "speed_rpm": (6000.0, 13000.0)}, ident_grid=(5, 5),
    map_throttle="30,60,100", map_speed="6000,9000,12000", learning_sizes=(12, 16), learning_seeds=(0,),
    holdout={"throttle_pct": (20, 60, 100), "speed_rpm": (6000, 9000, 12000), "spark_offset": (-15, -5, 5)},
    quick=True)


def settings_to_dict(rs: RunSettings) -> dict:
    """Plain-JSON form of :class:`RunSettings` (flow parameters must serialise)."""
    return dataclasses.asdict(rs)


def settings_from_dict(d: dict | RunSettings | None) -> RunSettings:
    """Inverse of :func:`settings_to_dict`; ``None`` gives the defaults."""
    if d is None:
        return RunSettings()
    if isinstance(d, RunSettings):
        return d
    d = dict(d)
    cal = d.pop("calibration", None)
    tuples = {f.name for f in dataclasses.fields(RunSettings) if f.type == "tuple"}
    d = {k: tuple(v) if k in tuples and v is not None else v for k, v in d.items()}
    if cal is not None and not isinstance(cal, CalibrationSettings):
        cal = CalibrationSettings(**dict(cal))
    return RunSettings(**d, **({"calibration": cal} if cal is not None else {}))
