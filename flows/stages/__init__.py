"""The stages of ``mbc run``, one module each, all with the signature ``run(ctx: StageContext) -> dict``.

    calibration   airflow match + Wiebe identification on the bench data; the calibrated engine
    model         virtual-bench campaign + the global map-wide combustion model
    maps          ECU tables from the global model
    gap           sim-to-real gap diagnosis of the bench data

A stage only calls public functions of :mod:`engine_model` and writes their results into the run folder;
the standalone commands (``mbc calibrate``, ``mbc maps``, ``mbc gap``) call the same stage functions.
"""
