"""Model-based calibration of a restricted race engine.

The public API lives here; physics kernels are in :mod:`engine_model.cycle`.
"""

from .prepare import OperatingPoint, SolverSettings
from .simulate import RESULT_COLUMNS, simulate, simulate_point, validate_points
from .spec import EngineSpec, default_spec, load_spec
from .thermo import FuelSpec, gas_set

__version__ = "0.1.0"

__all__ = [
    "EngineSpec", "FuelSpec", "OperatingPoint", "RESULT_COLUMNS", "SolverSettings", "default_spec",
    "gas_set", "load_spec", "simulate", "simulate_point", "validate_points", "__version__",
]
