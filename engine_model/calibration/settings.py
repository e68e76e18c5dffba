"""Settings of a calibration on bench data (airflow match + Wiebe identification)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CalibrationSettings", "QUICK_CALIBRATION"]


@dataclass(frozen=True)
class CalibrationSettings:
    """Knobs of one calibration run (defaults: the full run on Table 2).

    Attributes
    ----------
    eta_trans : float
        Transmission efficiency assumed between crank and brake [-] (paper: 0.95).
    step_deg : float
        Crank-angle step of the identification sweep [deg].
    airflow_step_deg : float
        Crank-angle step of the airflow match [deg].  1 deg: airflow within 0.22 % (mean 0.03 %) of
        0.5 deg on the matched R6 (3 speeds x 9 burns); brake power differs up to 1 %, hence 0.5 deg
        for the identification.
    airflow_grid : tuple of int
        Coarse-search points per airflow parameter.
    airflow_starts, airflow_max_nfev : int
        Local least-squares runs and their iteration cap.
    n_bdur, n_m : int
        Identification grid (>= 7 x 7 for the response surface).
    surface : str
        'spline' (full) or 'cubic' (cheap, coarse grid).
    """

    eta_trans: float = 0.95
    step_deg: float = 0.5
    airflow_step_deg: float = 1.0
    airflow_grid: tuple = (6, 6, 3)
    airflow_starts: int = 2
    airflow_max_nfev: int = 12
    n_bdur: int = 11
    n_m: int = 13
    surface: str = "spline"

    def __post_init__(self):
        if not 0.5 <= self.eta_trans <= 1.0:
            raise ValueError(f"CalibrationSettings.eta_trans = {self.eta_trans!r} must lie in [0.5, 1]")
        if self.surface not in ("spline", "cubic"):
            raise ValueError(f"CalibrationSettings.surface = {self.surface!r}: choose 'spline' or 'cubic'")
        object.__setattr__(self, "airflow_grid", tuple(int(v) for v in self.airflow_grid))


#: The small calibration of ``mbc run --quick`` (tests, smoke runs): 1 deg, a 2 x 2 x 1 airflow search, 7 x 7 grid.
QUICK_CALIBRATION = CalibrationSettings(step_deg=1.0, airflow_grid=(2, 2, 1), airflow_starts=1, airflow_max_nfev=2,
                                        n_bdur=7, n_m=7, surface="cubic")
