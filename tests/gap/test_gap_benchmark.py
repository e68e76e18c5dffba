"""Small CI version of the withheld-effect benchmark (real virtual bench, real simulations).

Cost control (2-core CI): a 12-point DOE, three withheld effects at their realistic magnitude, one
noise seed, a 5-effect candidate library, 2 base-calibration iterations, 1 deg crank steps (the same
solver for the truth and the model, so the comparison is about physics).  348 simulations, ~75 s on an
idle 2-core machine.  Achieved when written: 3/3 named, null and out-of-library case not attributed.
With the bench operator's knock back-off (2-3 of the 12 points re-run later per case; the 12 points do
not carry the base's spark slope, see ``choose_base``): again 3/3 named, null and out-of-library not
attributed; 21 s fixture on a lightly loaded machine.
"""

import numpy as np
import pandas as pd
import pytest

from engine_model.gap.benchmark import BENCHMARK_COLUMNS, OOL_EFFECT, run_benchmark
from engine_model.gap.report import write_benchmark_report

WITHHELD = ["transmission_efficiency", "restrictor", "intake_air_temperature"]
LIBRARY = WITHHELD + ["heat_transfer", "friction"]


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    # Sobol' points, not the default discriminating plan: that plan's 160-point candidate pool alone costs
    # 3 520 simulations, and 12 points chosen to separate the library's effects need not see the
    # out-of-library bump at 9500 rpm (measured: held-out gap 1.04 vs 1.01 in the null case)
    res = run_benchmark(seeds=1, magnitudes=(1.0,), effects=WITHHELD, candidates=LIBRARY, n_points=12,
                        base_iterations=2, k_folds=4, n_noise=60, verify=False, design="sobol")
    out = tmp_path_factory.mktemp("gapbench")
    paths = write_benchmark_report(res, out)
    return res, paths


def test_benchmark_csv_has_exactly_the_issue_columns(bench):
    res, paths = bench
    df = pd.read_csv(paths["csv"])
    assert tuple(df.columns) == BENCHMARK_COLUMNS
    assert len(df) == len(WITHHELD) + 2          # + null case + out-of-library case
    assert set(df["effect_withheld"]) == set(WITHHELD) | {"none", OOL_EFFECT}
    assert df["seed"].eq(0).all()
    assert np.isfinite(df["gap_before"]).all()


def test_benchmark_accuracy_and_null(bench):
    res, _ = bench
    t = res["table"]
    lib = t[t["effect_withheld"].isin(WITHHELD)]
    # achieved when written: 3/3 named correctly; allow one miss (seeded, can fail)
    assert lib["top1_correct"].sum() >= 2, lib[["effect_withheld", "effect_named", "top3"]]
    assert lib["top3_correct"].all()
    null = t[t["effect_withheld"] == "none"].iloc[0]
    assert null["effect_named"] == "none"
    named = lib[lib["top1_correct"]]
    assert (named["gap_reduction_pct"] >= 50).all(), named
    # out-of-library VE resonance: not attributed (achieved when written), yet the gap is seen
    ool = t[t["effect_withheld"] == OOL_EFFECT].iloc[0]
    assert ool["effect_named"] == "none"
    assert ool["gap_before"] > null["gap_before"] + 0.5
