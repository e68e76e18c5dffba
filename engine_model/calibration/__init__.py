"""Calibration on bench data: one import point for airflow matching and Wiebe identification.

    from engine_model import calibration as cal
    match = cal.match_airflow(meas, evaluate, spec=spec)                 # global intake/exhaust parameters
    res = evaluate(cal.identification_plan(meas, match.spec_overrides()))
    ident = cal.identify(meas, res, eta_trans=0.95)                     # (BDUR10-90, m) per point
    eta = cal.eta_sensitivity(ident); rel = cal.fit_eta_relation(cal.power_isolines(ident))
    joint = cal.joint_fit(ident)                                        # eta_trans shared per throttle
    at_joint = cal.identify_at_eta(ident, joint.eta_by_throttle())      # (BDUR10-90, m) at that eta

Every function that simulates takes an ``evaluate(plan DataFrame) -> results
DataFrame`` callable (default: in-process :func:`engine_model.simulate`), so
the flows can route all simulations through the Dask sweep pipeline.

    settings          CalibrationSettings (grid sizes, steps, eta_trans)
    airflow           airflow matching of a few global intake/exhaust parameters
    screen            which global parameters can shape the airflow match
    identify          Wiebe identification per bench point (the paper's method)
    eta               transmission efficiency: sensitivity, the paper's eq-6 relation, joint fit
    sweeps            joint identification of spark sweeps
    identifiability   recovery of known parameters from model-generated noisy data
    plots             figures
"""

from __future__ import annotations

from engine_model.calibration.settings import QUICK_CALIBRATION, CalibrationSettings  # noqa: F401
from engine_model.calibration.airflow import (AIRFLOW_NOISE_PCT, DEFAULT_PARAMETERS, AirflowMatch,  # noqa: F401
                                Parameter, airflow_plan, ga_rel_pct, match_airflow, matching_burn)
from engine_model.calibration.plots import plot_airflow_match, plot_eta_relation, plot_identification  # noqa: F401
from engine_model.calibration.identifiability import identifiability_check, synthetic_bench  # noqa: F401
from engine_model.calibration.identify import BDUR_RANGE_DEG, M_RANGE  # noqa: F401
from engine_model.calibration.identify import (Identification, Tolerances, grid_axes, identification_plan, identify,  # noqa: F401
                       identify_point, identify_quick, point_surfaces, quadratic_rs, terms_used)
from engine_model.calibration.eta import (DEFAULT_ETAS, JointFit, eta_sensitivity, fit_eta_relation,  # noqa: F401
                           identify_at_eta, joint_fit, power_isolines, relation_text)
