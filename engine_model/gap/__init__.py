"""Sim-to-real gap diagnosis: candidate effects library, residual analysis, attribution, benchmark.

Public API::

    from engine_model.gap import (EFFECTS, get_effect, apply_effects, post_effects,     # effects library
                                  linearise, calibrate_base, BaseModel,                 # one-batch linearisation
                                  diagnose, GapDiagnosis, diagnose_bench,               # the diagnosis
                                  write_gap_report, run_benchmark, write_benchmark_report,
                                  discrimination_plan,                                   # bench planning
                                  best_pair)                                             # two effects at once
"""

from .effects import (EFFECTS, ETA_TRANS_BASE, Effect, EffectParam, apply_effects, check_effects, effect_names,
                      get_effect, post_effects)
from .linear import BaseModel, Linearisation, calibrate_base, linearise
from .diagnose import MODEL_ERROR, NO_CANDIDATE, UNCERTAINTY, GapDiagnosis, diagnose
from .api import choose_base, diagnose_bench
from .benchmark import BENCHMARK_COLUMNS, run_benchmark
from .design import discrimination_plan, select_discriminating
from .pairs import NO_PAIR, PairSearch, best_pair
from .report import write_benchmark_report, write_gap_report

__all__ = ["EFFECTS", "ETA_TRANS_BASE", "Effect", "EffectParam", "apply_effects", "check_effects",
           "effect_names", "get_effect", "post_effects", "BaseModel", "Linearisation", "calibrate_base",
           "linearise", "MODEL_ERROR", "NO_CANDIDATE", "UNCERTAINTY", "GapDiagnosis", "diagnose", "choose_base",
           "diagnose_bench", "BENCHMARK_COLUMNS", "run_benchmark", "write_benchmark_report", "write_gap_report",
           "discrimination_plan", "select_discriminating", "NO_PAIR", "PairSearch", "best_pair"]
