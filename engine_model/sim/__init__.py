"""From an engine spec and operating points to simulated results: kernel inputs (prepare) and simulate."""

from engine_model.sim.prepare import OperatingPoint, SolverSettings
from engine_model.sim.simulate import simulate, simulate_point, validate_points

__all__ = ["OperatingPoint", "SolverSettings", "simulate", "simulate_point", "validate_points"]
