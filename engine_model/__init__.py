"""Model-based calibration of a restricted race engine.

The public API is here; the pipeline's stages are sub-packages::

    spec, calibrated   the engine (frozen, validated, SI) and the calibrated engine every stage takes
    contracts          column names and units of every table that crosses a boundary
    priors             physical first guesses (burn, MBT spark, lambda)
    cycle/             numba kernels (the cycle model)
    sim/               spec + operating points -> results table
    doe/               test plans
    bench/             measured data; the virtual bench and its hidden truths
    effects            unmodelled effects (shared by the virtual bench and the gap diagnosis)
    calibration/       airflow matching, Wiebe identification, transmission efficiency
    globalmodel/       the map-wide combustion model and the DOE learning curve
    tables/            ECU tables and their export
    gap/               sim-to-real gap diagnosis
"""

from engine_model.version import __version__
from engine_model.contracts import RESULT_COLUMNS
from engine_model.sim.prepare import OperatingPoint, SolverSettings
from engine_model.sim.simulate import simulate, simulate_point, validate_points
from engine_model.spec import EngineSpec, default_spec, load_spec
from engine_model.thermo import FuelSpec, gas_set

__all__ = [
    "EngineSpec", "FuelSpec", "OperatingPoint", "RESULT_COLUMNS", "SolverSettings", "default_spec",
    "gas_set", "load_spec", "simulate", "simulate_point", "validate_points", "__version__",
]
