"""Bench data: measured tables (load, validate; the packaged Table 2) and the virtual bench with its hidden truths.

    measured    load_bench, validate_bench, packaged_bench_path
    virtual     VirtualBench (truth engine + hidden burn law + effects + noise), NoiseModel, run_virtual_bench
    burnlaw     BurnLaw, the virtual bench's hidden combustion law
"""

from engine_model.bench.burnlaw import BurnLaw
from engine_model.bench.measured import load_bench, packaged_bench_path, validate_bench
from engine_model.bench.virtual import NoiseModel, VirtualBench, run_virtual_bench

__all__ = ["BurnLaw", "NoiseModel", "VirtualBench", "load_bench", "packaged_bench_path", "run_virtual_bench",
           "validate_bench"]
