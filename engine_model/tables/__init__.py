"""ECU tables: spark advance (MBT or knock-limited), injection time, target lambda, and their export.

    grid        EcuGrid (throttle % x rpm breakpoints), LambdaTable, parse_breakpoints
    settings    MapSettings, MapResult, PriorModel, load_model
    search      the per-cell spark search (batched over all cells)
    build       build_maps(spec, model, grid, evaluate=...) -> MapResult
    smoothing   bounded-curvature smoothing of a table
    injection   injector pulse width from airflow and lambda
    export      long-form Parquet, wide CSV, heatmaps, maps/ecu/ (write_maps)
    ecu_table   EcuTable (one table on its breakpoints), resample, to_map_kpa, fuel mass / injection / VE
    ecu_files   TunerStudio .table, format detection, read_table / read_axes / write_table
    ecu_msq     Speeduino and rusEFI .msq; ecu_dcm DCM 2.0; ecu_csv units-header CSV; ecu_text number text
    ecu_compare a proposed table against the current one (cell by cell, heatmap)
    ecu_export  a build's tables on the ECU's breakpoints and load axis, in every format
"""

from engine_model.tables.build import build_maps
from engine_model.tables.export import TABLES, long_form, write_maps
from engine_model.tables.grid import EcuGrid, LambdaTable, parse_breakpoints
from engine_model.tables.injection import injection_time_ms
from engine_model.tables.settings import MapResult, MapSettings, PriorModel, load_model
from engine_model.tables.smoothing import second_differences, smooth_table

__all__ = ["EcuGrid", "LambdaTable", "MapResult", "MapSettings", "PriorModel", "TABLES", "build_maps",
           "injection_time_ms", "load_model", "long_form", "parse_breakpoints", "second_differences",
           "smooth_table", "write_maps"]
