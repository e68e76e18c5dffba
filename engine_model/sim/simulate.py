"""Python face of the cycle model: ``simulate(spec, points) -> DataFrame``.

Inputs and outputs follow the data contract of engine_model.contracts (column names carry
units).  All rows are validated before anything is computed, so a bad table
raises a ValueError naming the row, the column and the value, and no partial
result exists.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import pandas as pd

from engine_model import thermo, wiebe
from engine_model.cycle import engine as _engine
from engine_model.cycle import friction as _friction
from engine_model.cycle import layout as L
from engine_model.sim.prepare import OperatingPoint, SolverSettings, initial_state, kernel_inputs
from engine_model.contracts import OPERATING_POINT_COLUMNS, RESULT_COLUMNS
from engine_model.spec import EngineSpec


# Plausible-range checks per column: (low, high, open_low) -- what a physical point can take.
_RANGES = {
    "throttle_pct": (0.0, 100.0, False),
    "spark_deg_btdc": (-30.0, 90.0, False),
    "lambda": (0.0, 3.0, True),
    "bdur_10_90_deg": (0.0, 180.0, True),
    "wiebe_m": (-1.0, 20.0, True),
    "wiebe_a": (0.0, 50.0, True),
    "p_amb_pa": (5e4, 1.2e5, False),
    "t_amb_k": (230.0, 340.0, False),
}


SPEC_PREFIX = "spec."   # plan columns "spec.<section>.<field>" override the engine spec for that row


def spec_columns(points: pd.DataFrame) -> list[str]:
    """The spec-override columns of a table (``spec.<section>.<field>``)."""
    return [c for c in points.columns if isinstance(c, str) and c.startswith(SPEC_PREFIX)]


def _row_label(points: pd.DataFrame, i: int) -> str:
    pid = f" (point_id {points['point_id'].iloc[i]!r})" if "point_id" in points.columns else ""
    return f"row {i}{pid}"


def _finite_column(pts: pd.DataFrame, raw: pd.DataFrame, col: str, source: str) -> np.ndarray:
    """Column ``col`` as float64; ValueError naming the first row that is not a finite number."""
    vals = pd.to_numeric(pts[col], errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(~np.isfinite(vals))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{source}: {_row_label(pts, i)}, column '{col}': value {raw[col].iloc[i]!r} "
                         "is not a finite number")
    return vals


def validate_points(spec: EngineSpec, points: pd.DataFrame, source: str = "points") -> pd.DataFrame:
    """Check an operating-point table against the contract; return it with optional columns filled.

    Raises
    ------
    ValueError
        Naming the source, row, column and value, and what was expected.
    """
    if not isinstance(points, pd.DataFrame):
        raise ValueError(f"{source}: expected a pandas DataFrame, got {type(points).__name__}")
    missing = [c for c in OPERATING_POINT_COLUMNS if c not in points.columns]
    if missing:
        raise ValueError(f"{source}: missing required column(s) {missing}; required: {list(OPERATING_POINT_COLUMNS)}")
    pts = points.reset_index(drop=True).copy()
    defaults = {"wiebe_a": wiebe.WIEBE_A_999, "p_amb_pa": spec.ambient.pressure_pa,
                "t_amb_k": spec.ambient.temperature_k}
    for col, val in defaults.items():
        if col not in pts.columns:
            pts[col] = val
    for col in list(OPERATING_POINT_COLUMNS) + list(defaults):
        vals = _finite_column(pts, points, col, source)
        if col == "speed_rpm":
            lo, hi, open_lo = 0.0, spec.geometry.max_speed_rpm, True
        else:
            lo, hi, open_lo = _RANGES[col]
        bad = np.flatnonzero(((vals <= lo) if open_lo else (vals < lo)) | (vals > hi))
        if bad.size:
            i = int(bad[0])
            lb = "(" if open_lo else "["
            raise ValueError(f"{source}: {_row_label(pts, i)}, column '{col}': value {vals[i]:g} is outside "
                             f"{lb}{lo:g}, {hi:g}]")
        pts[col] = vals
    ov_cols = spec_columns(pts)
    for col in ov_cols:
        pts[col] = _finite_column(pts, points, col, source)
    if ov_cols:
        seen = set()
        for i, vals in enumerate(pts[ov_cols].itertuples(index=False, name=None)):
            if vals not in seen:
                seen.add(vals)
                try:
                    spec.with_values(dict(zip((c[len(SPEC_PREFIX):] for c in ov_cols), vals)))
                except ValueError as exc:
                    raise ValueError(f"{source}: {_row_label(pts, i)}: {exc}") from None
    return pts


def _volume_name(k: int, ncyl: int, nseg_in: int = 1, nseg_ex: int = 1, pipes: bool = False) -> str:
    names = ["cylinder", "intake port", "exhaust port"]
    if k < 3 * ncyl:
        return f"{names[k // ncyl]} {k % ncyl + 1}"
    if pipes:
        return ["plenum", "throttle body", "exhaust merge", "silencer"][k - 3 * ncyl] if k < 3 * ncyl + 4 \
            else f"volume {k}"
    if k < 3 * ncyl + 3:
        return ["plenum", "throttle body", "exhaust collector"][k - 3 * ncyl]
    j = k - 3 * ncyl - 3
    for side, nseg in (("intake", nseg_in), ("exhaust", nseg_ex)):
        nj = nseg - 1
        if j < ncyl * nj:
            return f"{side} runner {j // nj + 1}, joint {j % nj + 1}"
        j -= ncyl * nj
    return f"volume {k}"


def _pipe_name(cell: int, ncyl: int, net) -> str:
    for ip in range(net.npipe):
        if net.first_cell(ip) <= cell <= net.last_cell(ip):
            name = (f"intake runner {ip + 1}" if ip < ncyl else f"exhaust primary {ip - ncyl + 1}" if ip < 2 * ncyl
                    else ("exhaust collector pipe" if ip == 2 * ncyl else "tailpipe"))
            return f"{name}, cell {cell - net.first_cell(ip) + 1} of {net.pipes[ip, 1]}"
    return f"pipe cell {cell}"


def failure_text(code: int, ncyl: int, nseg_in: int = 1, nseg_ex: int = 1, net=None) -> str:
    """Kernel failure code -> words: 100+k temperature out of range in volume k, 200+k negative mass,
    300+i a pipe cell i with a non-physical state (1D)."""
    if code >= 300 and net is not None:
        return f"mass or temperature out of range in {_pipe_name(int(code) - 300, ncyl, net)}"
    kind, k = divmod(int(code), 100)
    what = {1: "temperature left the 150-4400 K range", 2: "negative mass"}.get(kind, f"code {code}")
    return f"{what} in {_volume_name(k, ncyl, nseg_in, nseg_ex, net is not None)}"


def _result_row(spec: EngineSpec, op: OperatingPoint, out: np.ndarray, gas: thermo.GasSet,
                burn: dict, net=None) -> dict:
    g = spec.geometry
    vd_tot = g.total_displacement_m3
    cycles_per_s = op.speed_rpm / 120.0
    r_air = float(gas.r_specific[L.SP_A])
    rho_amb = op.p_amb_pa / (r_air * op.t_amb_k)
    fail = int(out[L.O_FAIL])
    row = {c: math.nan for c in RESULT_COLUMNS}
    row["converged"] = bool(out[L.O_CONVERGED] > 0.5)
    row["cycles_run"] = int(out[L.O_CYCLES])
    row.update({k: burn[k] for k in ("ca10_deg_atdc", "ca50_deg_atdc", "ca90_deg_atdc")})
    if fail:
        nsi = spec.intake.runner_segments if spec.intake.runner_inertia else 1
        nse = spec.exhaust.runner_segments if spec.exhaust.runner_inertia else 1
        row["status"] = f"failed: {failure_text(fail, spec.geometry.n_cylinders, nsi, nse, net)}"
        row["converged"] = False
        return row
    row["status"] = "ok" if row["converged"] else "not converged"
    air, fuel = out[L.O_AIR], out[L.O_FUEL]
    wgross, wpump, q = out[L.O_WGROSS], out[L.O_WPUMP], out[L.O_QWALL]
    imep_g = wgross / vd_tot
    pmep = -wpump / vd_tot
    imep_n = imep_g - pmep
    sp = 2.0 * g.stroke_m * op.speed_rpm / 60.0
    fr = spec.friction
    fmep = _friction.chen_flynn_fmep(fr.a_pa, fr.b, fr.c_pa_s_per_m, fr.d_pa_s2_per_m2, out[L.O_PMAX], sp)
    bmep = imep_n - fmep
    torque = bmep * vd_tot / (4.0 * math.pi)
    power_kw = torque * 2.0 * math.pi * op.speed_rpm / 60.0 / 1e3
    fuel_kg_h = fuel * cycles_per_s * 3600.0
    fuel_energy = fuel * spec.fuel.lhv_j_per_kg
    e_in = out[L.O_HAIR] + out[L.O_HFUEL] + out[L.O_QPORT] + out[L.O_QPIPE]
    e_out = out[L.O_HOUT] + wgross + wpump + q
    e_scale = fuel_energy if fuel_energy > 0 else abs(wgross) + abs(wpump) + abs(q)
    row.update(
        air_mass_flow_kg_h=air * cycles_per_s * 3600.0,
        vol_eff=air / (rho_amb * vd_tot),
        fuel_mass_flow_kg_h=fuel_kg_h,
        imep_gross_bar=imep_g / 1e5, pmep_bar=pmep / 1e5, imep_net_bar=imep_n / 1e5,
        fmep_bar=fmep / 1e5, bmep_bar=bmep / 1e5,
        brake_torque_nm=torque, brake_power_kw=power_kw,
        bsfc_g_kwh=fuel_kg_h * 1e3 / power_kw if power_kw > 0 else math.nan,
        exhaust_temp_k=out[L.O_TEXH],
        pmax_bar=out[L.O_PMAX] / 1e5, pmax_deg_atdc=out[L.O_PMAX_ANG],
        residual_fraction=out[L.O_RES],
        heat_loss_fraction=q / fuel_energy if fuel_energy > 0 else math.nan,
        knock_index=out[L.O_KNOCK],
        mass_balance_error=out[L.O_MBAL],
        energy_balance_error=abs(e_in - e_out) / e_scale if e_scale > 0 else math.nan,
        trapped_mass_mg=out[L.O_MTRAP] / g.n_cylinders * 1e6,
        plenum_pressure_bar=out[L.O_PPLENUM] / 1e5,
    )
    return row


def simulate_point(spec: EngineSpec, op: OperatingPoint, solver: SolverSettings = SolverSettings(),
                   state=None, return_traces: bool = False, gas: thermo.GasSet | None = None):
    """Simulate one operating point to a converged cycle.

    Parameters
    ----------
    spec : EngineSpec
    op : OperatingPoint
    solver : SolverSettings
    state : tuple (vol, mr, ref, q, tcell), optional
        Gas-exchange state to start from (e.g. the converged state of a
        neighbouring point, as returned here); a cold-start estimate otherwise.
    return_traces : bool
        Also return the last cycle's traces (see ``run_engine``).
    gas : GasSet, optional
        Gas properties to use instead of ``thermo.gas_set(lambda, spec.fuel)``
        (e.g. a constant-cp set for analytic-limit tests).

    Returns
    -------
    dict
        Result columns of the contract (``RESULT_COLUMNS``), plus ``pipe_substeps`` (largest number of
        pipe sub-steps per crank step, 1D), ``port_heat_j_per_cycle`` and ``pipe_heat_j_per_cycle``.
    tuple
        The final (vol, mr, ref, q, tcell) state, reusable as ``state`` of a similar point.
    ndarray, optional
        Traces, shape (2*ncyl + NTR_EXTRA, nstep), if requested.
    """
    ki = kernel_inputs(spec, op, solver, gas)
    ref = np.zeros((ki.ncyl, 5))          # unknown: the kernel starts from defaults
    vol0, mr0, q0, tc0 = initial_state(spec, ki)
    if state is None:
        vol, mr, q, tcell = vol0, mr0, q0, tc0
    else:
        if len(state) != 5:
            raise ValueError("state: expected (vol, mr, ref, q, tcell) as returned by simulate_point")
        vol, mr, ref, q, tcell = (a.copy() for a in state)
        got = (vol.shape, mr.shape, ref.shape, q.shape, tcell.shape)
        want = (vol0.shape, mr0.shape, (ki.ncyl, 5), q0.shape, tc0.shape)
        if got != want:
            raise ValueError(f"state: shapes {got} do not fit this spec's gas-exchange network (expected {want}); "
                             "pass the state a run of the same network returned")
    out = np.zeros(L.NOUT)
    trace = np.zeros((2 * ki.ncyl + L.NTR_EXTRA, ki.nstep))
    hist = np.zeros((0, L.H_N0 + vol.shape[0] * (L.NVCOL - 1) + mr.shape[0] + q.size))
    pipes, geom, ends, endp = ki.pipe_arrays()
    _engine.run_engine(ki.par, ki.tab, ki.offs, ki.coeffs, ki.rsp, ki.fuel_c, vol, mr, ref, ki.vfix, out, trace, hist,
                       pipes, geom, q, tcell, ends, endp)
    if op.motored:
        burn = {"ca10_deg_atdc": math.nan, "ca50_deg_atdc": math.nan, "ca90_deg_atdc": math.nan}
    else:
        burn = wiebe.burn_angles(op.spark_deg_btdc, op.bdur_10_90_deg, op.wiebe_m, op.wiebe_a)
    row = _result_row(spec, op, out, ki.gas, burn, ki.net)
    row["fuel_burned_mg_per_cycle"] = out[L.O_FUEL_BURNED] * 1e6
    row["gross_work_j_per_cycle"] = out[L.O_WGROSS]
    row["pipe_substeps"] = int(out[L.O_SUBSTEPS])
    row["pipe_courant"] = out[L.O_COURANT]
    row["port_heat_j_per_cycle"] = out[L.O_QPORT]
    row["pipe_heat_j_per_cycle"] = out[L.O_QPIPE]
    st = (vol, mr, ref, q, tcell)
    if return_traces:
        return row, st, trace
    return row, st


def _gas_key(op: OperatingPoint, overrides: tuple = ()) -> tuple:
    return (op.speed_rpm, op.throttle_pct, op.lam, op.p_amb_pa, op.t_amb_k, overrides)


def simulate(spec: EngineSpec, points: pd.DataFrame, solver: SolverSettings = SolverSettings(),
             progress: Callable[[int, int], None] | None = None, workers: int = 1) -> pd.DataFrame:
    """Simulate every operating point of a table.

    Parameters
    ----------
    spec : EngineSpec
    points : DataFrame
        Contract columns ``speed_rpm, throttle_pct, spark_deg_btdc, lambda,
        bdur_10_90_deg, wiebe_m`` and optional ``wiebe_a, p_amb_pa, t_amb_k``;
        any other columns (``point_id``, effect parameters) are echoed.
    solver : SolverSettings
    progress : callable(done, total), optional
    workers : int
        Processes to share the rows among (1: this process).  Rows are split only where a
        warm-start chain breaks anyway (see Notes), so the result is the same as with one
        process, row for row (``sim_time_s`` aside).  Tables under :data:`MIN_ROWS_TO_SPLIT` rows
        stay in this process.

    Returns
    -------
    DataFrame
        One row per input row, inputs echoed, plus the result columns.  Points
        that fail or do not converge are kept, with ``converged=False`` and a
        ``status`` saying why.

    Notes
    -----
    Columns named ``spec.<section>.<field>`` (e.g. ``spec.intake.restrictor_cd``)
    override that field of the engine spec for their row (calibration and
    effect studies sweep spec values like operating conditions).

    Consecutive rows with the same speed, throttle, lambda, ambient state and
    spec overrides start from the previous row's converged gas-exchange state
    (a Wiebe sweep at one operating point then needs fewer cycles per row:
    median 17 instead of ~20 from cold at the default tolerance, because a
    Wiebe step moves the slow plenum-composition mode again).
    """
    pts = validate_points(spec, points)
    ov_cols = spec_columns(pts)
    specs: dict[tuple, EngineSpec] = {(): spec}
    for i, vals in enumerate(pts[ov_cols].itertuples(index=False, name=None) if ov_cols else []):
        if vals not in specs:
            try:
                specs[vals] = spec.with_values(dict(zip((c[len(SPEC_PREFIX):] for c in ov_cols), vals)))
            except ValueError as exc:
                raise ValueError(f"points: {_row_label(pts, i)}: {exc}") from None
    if workers > 1 and len(pts) >= MIN_ROWS_TO_SPLIT:
        return _simulate_split(spec, pts, solver, progress, workers)
    rows = []
    state, key = None, None
    n = len(pts)
    for i in range(n):
        r = pts.iloc[i]
        ov = tuple(r[c] for c in ov_cols)
        spec_i = specs[ov]
        op = _operating_point(r)
        k = _gas_key(op, ov)
        t0 = time.perf_counter()
        row, new_state = simulate_point(spec_i, op, solver, state if k == key else None)
        row["sim_time_s"] = time.perf_counter() - t0
        if row["status"].startswith("failed"):
            state, key = None, None
        else:
            state, key = new_state, k
        rows.append(row)
        if progress is not None:
            progress(i + 1, n)
    res = pd.DataFrame(rows, index=pts.index)
    return pd.concat([pts, res], axis=1)


def _operating_point(r: pd.Series) -> OperatingPoint:
    return OperatingPoint(speed_rpm=float(r["speed_rpm"]), throttle_pct=float(r["throttle_pct"]),
                          spark_deg_btdc=float(r["spark_deg_btdc"]), lam=float(r["lambda"]),
                          bdur_10_90_deg=float(r["bdur_10_90_deg"]), wiebe_m=float(r["wiebe_m"]),
                          wiebe_a=float(r["wiebe_a"]), p_amb_pa=float(r["p_amb_pa"]),
                          t_amb_k=float(r["t_amb_k"]))


def chain_starts(pts: pd.DataFrame) -> list[int]:
    """Rows of a validated table where a warm-start chain begins (the previous row has another gas key).

    Row 0 always; a chain may also break inside (a failed row), which only adds cold starts."""
    ov_cols = spec_columns(pts)
    keys = [_gas_key(_operating_point(r), tuple(r[c] for c in ov_cols)) for _, r in pts.iterrows()]
    return [i for i in range(len(keys)) if i == 0 or keys[i] != keys[i - 1]]


#: Smallest table :func:`simulate` shares among processes (a spawned process costs ~1 s, two or three rows).
MIN_ROWS_TO_SPLIT = 16

#: Chunks per worker in :func:`simulate` with ``workers > 1`` (several, so a worker that drew slow rows does
#: not leave the other idle at the end).
CHUNKS_PER_WORKER = 4


def _simulate_split(spec, pts, solver, progress, workers):
    starts = chain_starts(pts) + [len(pts)]
    target = len(pts) / (workers * CHUNKS_PER_WORKER)
    bounds, a = [], 0
    for b in starts[1:]:
        if b - a >= target or b == len(pts):
            bounds.append((a, b))
            a = b
    if len(bounds) == 1:
        return simulate(spec, pts, solver, progress)
    parts = map_in_processes(simulate, [pts.iloc[a:b] for a, b in bounds], workers, (spec,), (solver,), progress)
    out = pd.concat(parts, ignore_index=True)
    out.index = pts.index
    return out


def map_in_processes(fn, frames: list, workers: int, before: tuple = (), after: tuple = (),
                     progress: Callable[[int, int], None] | None = None) -> list:
    """``[fn(*before, frame, *after) for frame in frames]``, computed in ``workers`` fresh processes.

    The processes are spawned (a fresh interpreter; the numba cache loads in ~1 s), so a script that
    calls this must guard its top level with ``if __name__ == "__main__":`` (Python's rule for spawned
    processes), and it cannot run inside a daemonic process (a Dask worker): the flows parallelise through
    Dask instead.  ``progress(rows done, rows)`` as chunks finish.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    total = sum(len(f) for f in frames)
    out: list = [None] * len(frames)
    done = 0
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as ex:
        futs = {ex.submit(fn, *before, f, *after): k for k, f in enumerate(frames)}
        for fut in as_completed(futs):
            k = futs[fut]
            out[k] = fut.result()
            done += len(frames[k])
            if progress is not None:
                progress(done, total)
    return out
