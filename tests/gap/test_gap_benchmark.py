"""Small CI version of the withheld-effect benchmark (real virtual bench, real simulations).

Cost control (2-core CI): a 12-point DOE, three withheld effects at their realistic magnitude, five
noise seeds (the truth is simulated once; seeds only redraw the bench noise), a 5-effect candidate
library, 2 base-calibration iterations, 1 deg crank steps at the linearisation tolerance (the same solver
for the truth and the model, so the comparison is about physics).  ~360 simulations, ~30 s.

Rates measured on this design over 40 seeds (0-39), identical with the code compiled for the host CPU
and for a generic x86-64 (``NUMBA_CPU_NAME=generic``): top-1 97.5 % (intake air temperature), 97.5 %
(restrictor), 67.5 % (transmission efficiency: on 12 points it is often claimed as another torque loss
of the 5-effect library); a false claim in the null case 2.5 %; the out-of-library bump claimed in 0 of
40.  With the claim rule that needs the remainder within noise (no 50 % path) these replace the earlier
100/100/90 %, null 20 % and bump 2.5 %; the thresholds below follow from them and hold except with a
probability below 1 % each (binomial tails; docs/testing.md).
"""

import numpy as np
import pandas as pd
import pytest

from engine_model import default_spec
from engine_model.gap.bench_procedure import BENCH_SOLVER
from engine_model.gap.benchmark import BENCHMARK_COLUMNS, OOL_EFFECT, run_benchmark
from engine_model.gap.report import write_benchmark_report
from engine_model.sim import simulate

from conftest import SIM_WORKERS

pytestmark = pytest.mark.slow

WITHHELD = ["transmission_efficiency", "restrictor", "intake_air_temperature"]
LIBRARY = WITHHELD + ["heat_transfer", "friction"]
SEEDS = 5


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    # Sobol' points, not the default discriminating plan: that plan's 160-point candidate pool alone costs
    # 3 520 simulations, and 12 points chosen to separate the library's effects need not see the
    # out-of-library bump at 9500 rpm (measured: held-out gap 1.04 vs 1.01 in the null case)
    spec = default_spec()
    res = run_benchmark(seeds=SEEDS, magnitudes=(1.0,), effects=WITHHELD, candidates=LIBRARY, n_points=12,
                        base_iterations=2, k_folds=4, n_noise=60, verify=False, design="sobol", spec=spec,
                        evaluate=lambda p: simulate(spec, p, BENCH_SOLVER, workers=SIM_WORKERS))
    out = tmp_path_factory.mktemp("gapbench")
    paths = write_benchmark_report(res, out)
    return res, paths


def test_benchmark_csv_has_exactly_the_issue_columns(bench):
    res, paths = bench
    df = pd.read_csv(paths["csv"])
    assert tuple(df.columns) == BENCHMARK_COLUMNS
    assert len(df) == (len(WITHHELD) + 2) * SEEDS          # + null case + out-of-library case, per seed
    assert set(df["effect_withheld"]) == set(WITHHELD) | {"none", OOL_EFFECT}
    assert sorted(set(df["seed"])) == list(range(SEEDS))
    assert np.isfinite(df["gap_before"]).all()


def test_benchmark_accuracy_and_null(bench):
    res, _ = bench
    t = res["table"]
    lib = t[t["effect_withheld"].isin(WITHHELD)]
    # 15 library trials at rates 67.5/97.5/97.5 %: at least 10 named (P(fewer) = 0.2 %; at least 12, the
    # earlier threshold for rates of 90-100 %, would fail with 8.5 % at today's transmission rate)
    assert lib["top1_correct"].sum() >= 10, lib[["effect_withheld", "seed", "effect_named", "top3"]]
    assert lib["top3_correct"].mean() >= 0.9
    named = lib[lib["top1_correct"]]
    assert (named["gap_reduction_pct"] >= 50).all(), named
    # null case: a false claim in 2.5 % of trials -> at most 1 of 5 (P(more) = 0.6 %)
    null = t[t["effect_withheld"] == "none"]
    assert (null["effect_named"] != "none").sum() <= 1, null[["seed", "effect_named"]]
    assert set(t["category"]) <= {"no significant gap", "explained", "sensor fault", "indistinguishable",
                                  "partly explained", "not in the library"}
    # out-of-library VE resonance: the gap is seen (its attribution rate: the next test)
    ool = t[t["effect_withheld"] == OOL_EFFECT]
    assert ool["gap_before"].median() > null["gap_before"].median() + 0.5


def test_out_of_library_effect_is_rarely_attributed(bench):
    res, _ = bench
    t = res["table"]
    ool = t[t["effect_withheld"] == OOL_EFFECT]
    # claimed in 0 of 40 seeds (< 7.2 % at 95 % confidence) -> at most 1 of 5 (P(more) < 5 % even at that bound)
    # it is seen, and refused as "partly explained" (what the best candidate leaves is above noise)
    assert (ool["effect_named"] != "none").sum() <= 1, ool[["seed", "effect_named"]]
