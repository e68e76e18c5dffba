"""Calibration on bench data: one import point for airflow matching and Wiebe identification.

    from engine_model import calibrate as cal
    match = cal.match_airflow(meas, evaluate, spec=spec)                 # global intake/exhaust parameters
    res = evaluate(cal.identification_plan(meas, match.spec_overrides()))
    ident = cal.identify(meas, res, eta_trans=0.95)                     # (BDUR10-90, m) per point
    eta = cal.eta_sensitivity(ident); rel = cal.fit_eta_relation(cal.power_isolines(ident))
    joint = cal.joint_fit(ident)                                        # eta_trans shared per throttle
    at_joint = cal.identify_at_eta(ident, joint.eta_by_throttle())      # (BDUR10-90, m) at that eta

Every function that simulates takes an ``evaluate(plan DataFrame) -> results
DataFrame`` callable (default: in-process :func:`engine_model.simulate`), so
the flows can route all simulations through the Dask sweep pipeline.  The
science lives in :mod:`engine_model.calibrate_airflow`,
:mod:`engine_model.identify`, :mod:`engine_model.identify_eta`,
:mod:`engine_model.identifiability`; figures in
:mod:`engine_model.calibrate_plots`.
"""

from __future__ import annotations

from .calibrate_airflow import (AIRFLOW_NOISE_PCT, DEFAULT_PARAMETERS, AirflowMatch,  # noqa: F401
                                Parameter, airflow_plan, ga_rel_pct, match_airflow, matching_burn)
from .calibrate_plots import plot_airflow_match, plot_eta_relation, plot_identification  # noqa: F401
from .identifiability import identifiability_check, synthetic_bench  # noqa: F401
from .identify import (Identification, Tolerances, grid_axes, identification_plan, identify,  # noqa: F401
                       identify_point, identify_quick, point_surfaces, quadratic_rs, terms_used)
from .identify_eta import (DEFAULT_ETAS, JointFit, eta_sensitivity, fit_eta_relation,  # noqa: F401
                           identify_at_eta, joint_fit, power_isolines, relation_text)
