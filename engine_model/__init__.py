"""Model-based calibration of a restricted race engine.

The public API lives here; physics kernels are in :mod:`engine_model.cycle`.
"""

from . import doe  # noqa: F401  DOE test plans: engine_model.doe.full_factorial, sobol, d_optimal, spark_sweeps, ...
from .prepare import OperatingPoint, SolverSettings
from .simulate import RESULT_COLUMNS, simulate, simulate_point, validate_points
from .spec import EngineSpec, default_spec, load_spec
from .thermo import FuelSpec, gas_set
from .burnlaw import BurnLaw  # noqa: E402  truth engine's hidden combustion law
from .mapmodel import MapModel, fit_map_model  # noqa: E402  global map-wide combustion model
from .virtual_bench import NoiseModel, VirtualBench, run_virtual_bench  # noqa: E402  the virtual bench

__version__ = "0.1.0"

__all__ = [
    "EngineSpec", "FuelSpec", "OperatingPoint", "RESULT_COLUMNS", "SolverSettings", "default_spec",
    "gas_set", "load_spec", "simulate", "simulate_point", "validate_points", "__version__",
    "BurnLaw", "MapModel", "NoiseModel", "VirtualBench", "fit_map_model", "run_virtual_bench",
]
