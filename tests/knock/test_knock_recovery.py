"""The knock calibration against a virtual knock bench whose truth has another structure (slow: ~700 cycles).

Seeds 201-240 are not the benchmark's (101-130, benchmarks/knock_recovery.py) and were not used to set
anything; the truth's constants were fixed before any trial.  The simulations are shared by all seeds (each
seed only redraws the bench's knock detection and torque noise), so 40 seeds cost little more than one.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from engine_model import default_spec
from engine_model.knock.recovery import prepare, trial

from conftest import SIM_WORKERS

pytestmark = pytest.mark.slow
SEEDS = tuple(range(201, 241))


@pytest.fixture(scope="module")
def trials():
    # the simulations and the seeds shared among the cores (the same numbers as in one process: rows and seeds
    # are independent)
    data = prepare(default_spec(), sparks=np.arange(0.0, 61.0, 4.0), workers=SIM_WORKERS)
    with ProcessPoolExecutor(SIM_WORKERS, mp_context=multiprocessing.get_context("spawn")) as ex:
        return list(ex.map(trial, [data] * len(SEEDS), SEEDS))


def test_sweeps_stay_within_forty_bench_points(trials):
    assert all(t["points"] <= 40 and t["knocking"] >= 1 for t in trials)
    assert all(t["evidence"] == "two-sided" for t in trials)


def test_a_sweep_knocking_at_its_start_is_retarded_until_it_runs_clean(trials):
    """Every sweep that knocks at its first step brackets its border (before: 4 retard steps, and the 3000 rpm
    sweeps, started 24 deg past the truth's border, knocked on every row they ran)."""
    assert all(t["unbracketed_sweeps"] == 0 for t in trials), [t["unbracketed_sweeps"] for t in trials]


def test_calibrated_border_recovers_the_hidden_truth(trials):
    """Spark at the median multiplier within 2 deg of the truth's at >= 90 % of the 30 cells, on most seeds.

    Measured: 32 of 40 seeds here (83-97 % of cells; 201-205 alone gave 1 of 5), 22 of 30 on the benchmark's
    seeds 101-130.  The misses are one cell family or the other: a multiplier drawn low (0.71) puts the 9000 rpm
    WOT borders 2.4-4.3 deg early, one drawn high (0.79) the 3000 rpm borders 2.3-5.7 deg late, because the
    multiplier that puts the model's border on the truth's is 0.64-0.72 at 3000 rpm and 0.78-0.79 at 9000 rpm WOT
    (the truth's two-branch delay against one Arrhenius line; docs/sections/knock.md).  With the bench's
    retard steps capped at four (the 3000 rpm sweeps never ran clean) it was 24 of 40.  Asserted: >= 70 % of
    the seeds (28 of 40; the seeds are fixed and the multiplier's posterior moves in steps, so the figure is
    reproducible; on fresh seeds a rate near 75 % would fall below 70 % of 40 with probability ~20 %) and no
    seed below 80 %.
    """
    within = [t["within_tol_pct"] for t in trials]
    assert sum(w >= 90.0 for w in within) >= 0.7 * len(within) and min(within) >= 80.0, within


def test_a_speed_dependent_multiplier_recovers_the_truth_on_almost_every_seed(trials):
    """The second knock parameter (ln m = a + b ln(n/6000), engine_model.knock.speed_term) on the same bench rows.

    Measured: 38 of 40 seeds here with >= 90 % of cells within 2 deg (one multiplier: 32), 94 of 100 on the
    benchmark's seeds 101-200 (one multiplier: 78).  Its prior and reference speed were set before any trial.
    Asserted: >= 85 % of the seeds (34 of 40; a rate near 94 % falls below with probability ~2 %) and at least
    as many seeds as the one multiplier.
    """
    one = sum(t["within_tol_pct"] >= 90.0 for t in trials)
    two = sum(t["within_tol_pct_speed_term"] >= 90.0 for t in trials)
    assert two >= 0.85 * len(trials) and two >= one, (one, two, [t["within_tol_pct_speed_term"] for t in trials])


def test_table_multiplier_is_safe_on_the_truth_and_costs_little_torque(trials):
    assert np.mean([t["table_knocks_pct"] for t in trials]) <= 2.0
    assert np.mean([t["torque_vs_best_safe_mean"] for t in trials]) >= 0.95


def test_the_table_as_the_maps_build_it_is_safe_with_the_speed_term_where_the_data_support_it(trials):
    """The maps stage takes the speed term only where the data inform its slope (62 of 100 benchmark seeds);
    that table, judged on the truth, keeps the one-multiplier table's bars (knocks <= 2 %, torque >= 95 %)."""
    used = sum(t["speed_term_used"] for t in trials)
    assert used >= len(trials) // 4, used        # the path is exercised on these seeds, not only the fallback
    assert np.mean([t["table_speed_term_knocks_pct"] for t in trials]) <= 2.0
    assert np.mean([t["torque_vs_best_safe_mean_speed_term"] for t in trials]) >= 0.95
