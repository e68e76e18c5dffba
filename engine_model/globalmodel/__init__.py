"""The global map-wide combustion model (BDUR10-90, m) = f(throttle, speed, spark, lambda) and what a DOE is worth.

    surrogates  polynomial response surfaces with PRESS term selection, Gaussian process
    mapmodel    MapModel (chosen per output by K-fold CV), fit_map_model, load
    load_table  engine load from the calibrated simulator, an optional model input
    learning    the DOE learning curve (designs against a full grid)
    campaign    the virtual-bench campaign: plan, measure, identify, fit, score against the hidden truth
"""

from engine_model.globalmodel.mapmodel import MapModel, fit_map_model, load

__all__ = ["MapModel", "fit_map_model", "load"]
