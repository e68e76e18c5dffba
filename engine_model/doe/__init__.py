"""Test plans (DOE): pure designs, plans screened by the model, plan files.

    designs     full_factorial, latin_hypercube, sobol, d_optimal, maximin_augment, d_efficiency, bench_order,
                wiebe_grid
    screening   QUICK_SOLVER, quick_evaluate, spark_sweeps (the paper's bench procedure), feasibility
    plans       plan_hash, save_plan, validate_plan, load_plan, write_example_plans

The physical first guesses the plans use (burn, MBT spark, lambda) are in
:mod:`engine_model.priors`.
"""

from engine_model.doe.designs import (DEFAULT_BOUNDS, FACTORS, bench_order, d_efficiency, d_optimal, full_factorial,
                                      latin_hypercube, maximin_augment, model_matrix, sobol, wiebe_grid)
from engine_model.doe.plans import load_plan, plan_hash, save_plan, validate_plan, write_example_plans
from engine_model.doe.screening import QUICK_SOLVER, feasibility, quick_evaluate, spark_sweeps

__all__ = ["DEFAULT_BOUNDS", "FACTORS", "QUICK_SOLVER", "bench_order", "d_efficiency", "d_optimal", "feasibility",
           "full_factorial", "latin_hypercube", "load_plan", "maximin_augment", "model_matrix", "plan_hash",
           "quick_evaluate", "save_plan", "sobol", "spark_sweeps", "validate_plan", "wiebe_grid", "write_example_plans"]
