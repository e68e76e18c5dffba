"""Identifiability: known (BDUR10-90, m, eta_trans) recovered from noisy model-generated bench data.

Two WOT truths (9000 and 10500 rpm), MBT spark, eta_trans 0.93, exhaust temperature
measured; noise torque 0.5 %, airflow 1 % (propagated to power), exhaust T 5 K;
60 draws; 7 x 7 grid at 1 deg (one sweep, reused by every draw).

Measured over 10 seeds of 20 draws, host build and generic x86-64 build alike: bias of BDUR10-90
+0.31 / +0.16 deg, of m +0.02 / +0.01 (truth00 / truth01), spread 3.1 / 2.6 deg and 0.88 / 0.55; eta bias
within 0.005, spread 0.007-0.013.
"""

import pandas as pd
import pytest

from engine_model import SolverSettings, default_spec

from engine_model.sim import simulate
from engine_model import calibration as cal

from conftest import SIM_WORKERS

pytestmark = pytest.mark.slow

ETA = 0.93


@pytest.fixture(scope="module")
def check():
    spec = default_spec()
    ev = lambda plan: simulate(spec, plan, SolverSettings(step_deg=1.0), workers=SIM_WORKERS)  # noqa: E731
    truths = pd.DataFrame({"speed_rpm": [9000.0, 10500.0], "throttle_pct": 100.0, "lambda": 0.9,
                           "bdur_10_90_deg": [26.0, 31.0], "wiebe_m": [5.6, 4.6]})
    return cal.identifiability_check(truths, ev, eta_trans=ETA, n_draws=60, seed=3, n_bdur=7, n_m=7)


def test_burn_parameters_recovered_at_known_eta(check):
    s = check["summary"]
    n = check["draws"]["draw"].nunique()
    # Unbiased: |mean error| within 4 standard errors of the mean (four checks: a chance failure < 0.03 %)
    # plus the 7 x 7 spline's interpolation error (1 deg, 0.15; see test_calibrate_identify).  The spread
    # itself is the finding: near MBT the power surface is flat along the CA50 line, so ~1.3 % power noise
    # (torque 0.5 % + airflow 1 % propagated) and 5 K exhaust noise leave about +-3 deg / +-0.9 (1 sigma).
    # The bounds (5 deg, 1.3) stay below the spread of an estimate that carries no information (uniform
    # over the plane: 8.7 deg, 1.7).
    assert (s["bdur_bias"].abs() < 4 * s["bdur_std"] / n ** 0.5 + 1.0).all(), s
    assert (s["m_bias"].abs() < 4 * s["m_std"] / n ** 0.5 + 0.15).all(), s
    assert (s["bdur_std"] < 5.0).all() and (s["m_std"] < 1.3).all(), s


def test_eta_recovered_by_joint_fit(check):
    s = check["summary"]
    # exhaust temperature pins (BDUR, m) on the CA50 line, power then fixes eta: 2 points, 20 draws
    # measured: bias within 0.005, spread 0.007-0.013 (10 seeds of 20 draws); power noise ~1.3 % maps ~1:1
    # onto eta per point
    assert abs(s["eta_bias"].iloc[0]) < 0.01, s
    assert s["eta_std"].iloc[0] < 0.02, s
    assert check["draws"]["eta_identifiable"].mean() > 0.5
