"""Sim-to-real gap diagnosis: candidate effects library, residual analysis, attribution, benchmark.

Public API::

    from engine_model.gap import (EFFECTS, get_effect, apply_effects, post_effects,     # effects library
                                  linearise, calibrate_base, BaseModel,                 # one-batch linearisation
                                  diagnose, GapDiagnosis, diagnose_bench,               # the diagnosis
                                  write_gap_report, run_benchmark, write_benchmark_report,
                                  discrimination_plan,                                   # bench planning
                                  best_pair)                                             # two effects at once
"""

from engine_model.effects import (EFFECTS, ETA_TRANS_BASE, Effect, EffectParam, apply_effects, check_effects, effect_names,
                      get_effect, post_effects)
from engine_model.gap.linear import BaseModel, Linearisation, calibrate_base, linearise
from engine_model.gap.covariance import MODEL_ERROR
from engine_model.gap.diagnose import NO_CANDIDATE, GapDiagnosis, diagnose
from engine_model.gap.residuals import UNCERTAINTY
from engine_model.gap.api import choose_base, diagnose_bench
from engine_model.gap.benchmark import BENCHMARK_COLUMNS, run_benchmark
from engine_model.gap.design import discrimination_plan, select_discriminating
from engine_model.gap.pairs import NO_PAIR, PairSearch, best_pair
from engine_model.gap.report import write_benchmark_report, write_gap_report

__all__ = ["EFFECTS", "ETA_TRANS_BASE", "Effect", "EffectParam", "apply_effects", "check_effects",
           "effect_names", "get_effect", "post_effects", "BaseModel", "Linearisation", "calibrate_base",
           "linearise", "MODEL_ERROR", "NO_CANDIDATE", "UNCERTAINTY", "GapDiagnosis", "diagnose", "choose_base",
           "diagnose_bench", "BENCHMARK_COLUMNS", "run_benchmark", "write_benchmark_report", "write_gap_report",
           "discrimination_plan", "select_discriminating", "NO_PAIR", "PairSearch", "best_pair"]
