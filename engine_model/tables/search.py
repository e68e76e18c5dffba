"""The spark search of :func:`engine_model.tables.build.build_maps`: candidate selection per cell and batched evaluation.

Per cell, :func:`decide_cell` looks at every point evaluated so far and either asks
for more spark values or resolves the cell (MBT, knock border, zones);
:class:`SparkRunner` turns the requests of all cells into one plan per stage, asks
the combustion model for (BDUR10-90, m) at every candidate spark, and calls the
``evaluate`` callable once.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from engine_model import priors, wiebe
from engine_model.globalmodel.mapmodel import ca50_offset_deg
from engine_model.tables.settings import MapSettings

__all__ = ["EVAL_COLUMNS", "SparkRunner", "cycle_knock", "decide_cell", "model_spark", "uncertainty_retard"]


def _predict(model, pts: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """(bdur_10_90, m) per row; NaN where the model's answer is missing or unphysical."""
    return _predict_frame(model, pts)[1:]


def _predict_frame(model, pts: pd.DataFrame) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """The model's whole prediction frame (stds included, if any) and the checked (bdur_10_90, m) of :func:`_predict`."""
    pred = model.predict(pts[["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]].reset_index(drop=True))
    if len(pred) != len(pts) or not {"bdur_10_90_deg", "wiebe_m"} <= set(pred.columns):
        raise ValueError(f"combustion model {type(model).__name__}.predict returned {len(pred)} rows / columns "
                         f"{list(pred.columns)}; expected {len(pts)} rows with bdur_10_90_deg, wiebe_m")
    b = pd.to_numeric(pred["bdur_10_90_deg"], errors="coerce").to_numpy(float).copy()
    m = pd.to_numeric(pred["wiebe_m"], errors="coerce").to_numpy(float).copy()
    bad = ~(np.isfinite(b) & np.isfinite(m) & (b > 0) & (b < 180) & (m > -1) & (m < 20))
    b[bad], m[bad] = np.nan, np.nan
    return pred, b, m


def _vertex(x, y) -> float:
    """Abscissa of the parabola through three points, kept within them; the middle point if not concave."""
    x = np.asarray(x, dtype=float)
    a, b, _c = np.polyfit(x - x[1], np.asarray(y, dtype=float), 2)   # centred on the middle point
    if not a < 0:
        return float(x[1])
    return float(min(max(x[1] - b / (2 * a), x[0]), x[2]))


def _peak(s: np.ndarray, t: np.ndarray, imax: int, window: float) -> float:
    """Spark of maximum torque: least-squares parabola through the points within ``window`` of the best one.

    Near MBT the torque curve is flat (0.1 % over +-2 deg) while converged-cycle
    torque carries ~0.05-0.1 % noise from the cycle-convergence tolerance and
    the warm start, so a 3-point vertex can wander by 2 deg; a least-squares
    fit over +-``window`` deg averages that noise.  Falls back to the 3-point
    vertex with fewer than 4 points or a non-concave fit.
    """
    near = np.abs(s - s[imax]) <= window + 1e-9
    x, y = s[near], t[near]
    if x.size >= 4 and np.any(x < s[imax]) and np.any(x > s[imax]):
        a, b, _c = np.polyfit(x - s[imax], y, 2)
        if a < 0:
            return float(np.clip(s[imax] - b / (2 * a), x.min(), x.max()))
    return _vertex(s[imax - 1:imax + 2], t[imax - 1:imax + 2])


def _knock_cross(s1, k1, s2, k2, limit) -> float:
    """Spark where the knock index reaches ``limit``, log-linear through two points (linear if not positive)."""
    if k1 > 0 and k2 > 0 and k1 != k2:
        return float(s1 + math.log(limit / k1) * (s2 - s1) / math.log(k2 / k1))
    if k2 != k1:
        return float(s1 + (limit - k1) * (s2 - s1) / (k2 - k1))
    return float(s1)


# --------------------------------------------------------------------------- knock of the fastest cycles

#: d ln(knock index)/d spark [1/deg] where a cell has a single evaluated point: 0.045-0.048 measured at WOT
#: 8000-11000 rpm on the default R6 model at Table 2's identified burns (spark +3 deg).
_KNOCK_SLOPE_FALLBACK = 0.05
#: Range of the end slopes used to extrapolate [1/deg]: a flatter slope would put the fastest cycles' knock
#: below the mean cycle's, a steeper one is outside anything the model gives.
_KNOCK_SLOPE_RANGE = (0.01, 0.3)


def cycle_knock(s: np.ndarray, k: np.ndarray, advance: float) -> np.ndarray:
    """Knock index of the fastest cycles at each spark of one cell [-].

    The fastest cycles burn ``advance`` deg earlier than the mean cycle; their knock index at spark
    ``s`` is taken as the mean cycle's at ``s + advance``: log-linear interpolation through the cell's
    evaluated points, extrapolated beyond them with the end segment's slope (clipped to
    ``_KNOCK_SLOPE_RANGE``; ``_KNOCK_SLOPE_FALLBACK`` for a single point).  NaN stays NaN; 0 stays 0.
    """
    s = np.asarray(s, float)
    k = np.asarray(k, float)
    out = k.copy()
    if advance <= 0:
        return out
    good = np.isfinite(s) & np.isfinite(k) & (k > 0)
    if not good.any():
        return out
    frame = pd.DataFrame({"s": s[good], "y": np.log(k[good])}).groupby("s")["y"].mean()
    xs, ys = frame.index.to_numpy(float), frame.to_numpy(float)
    lo, hi = _KNOCK_SLOPE_RANGE
    if xs.size == 1:
        slope_lo = slope_hi = _KNOCK_SLOPE_FALLBACK
    else:
        slope_lo = float(np.clip((ys[1] - ys[0]) / (xs[1] - xs[0]), lo, hi))
        slope_hi = float(np.clip((ys[-1] - ys[-2]) / (xs[-1] - xs[-2]), lo, hi))
    u = s[good] + advance
    y = np.interp(u, xs, ys)
    y = np.where(u > xs[-1], ys[-1] + slope_hi * (u - xs[-1]), y)
    y = np.where(u < xs[0], ys[0] + slope_lo * (u - xs[0]), y)
    out[good] = np.exp(y)
    return out


def with_cycle_knock(ev: pd.DataFrame, advance: float) -> pd.DataFrame:
    """``ev`` with ``knock_index_cycle``: :func:`cycle_knock` per cell over all of the cell's points."""
    ev = ev.copy()
    if ev.empty:
        ev["knock_index_cycle"] = pd.Series(dtype=float)
        return ev
    out = np.full(len(ev), np.nan)
    pos = np.arange(len(ev))
    # the uncertainty stage's rows ran another (pessimistic) burn: not part of the cell's spark sweep
    same_burn = ~ev["stage"].astype(str).str.startswith("u").to_numpy() if "stage" in ev.columns \
        else np.ones(len(ev), bool)
    for _c, idx in ev[same_burn].groupby("cell").indices.items():
        idx = pos[same_burn][idx]
        out[pos[idx]] = cycle_knock(ev["spark_deg_btdc"].to_numpy(float)[idx],
                                    ev["knock_index"].to_numpy(float)[idx], advance)
    ev["knock_index_cycle"] = out
    return ev


# --------------------------------------------------------------------------- the spark search

EVAL_COLUMNS = ("brake_torque_nm", "knock_index", "bmep_bar", "ca50_deg_atdc", "air_mass_flow_kg_h",
              "fuel_mass_flow_kg_h", "exhaust_temp_k", "plenum_pressure_bar", "trapped_mass_mg", "vol_eff",
              "cycles_run", "converged", "status")


def model_spark(model, cells: pd.DataFrame, st: MapSettings) -> np.ndarray:
    """Per cell, the spark [deg BTDC] at which the model's (BDUR10-90, m) put CA50 at the target (1 deg grid)."""
    sparks = np.arange(math.ceil(st.spark_min_deg_btdc), math.floor(st.spark_max_deg_btdc) + 1, 1.0)
    rep = cells.loc[np.repeat(cells.index.to_numpy(), sparks.size)].reset_index(drop=True)
    rep["spark_deg_btdc"] = np.tile(sparks, len(cells))
    b, m = _predict(model, rep)
    ok = np.isfinite(b)
    ca50 = np.full(len(rep), np.nan)
    ca50[ok] = wiebe.angle_at_fraction(0.5, rep["spark_deg_btdc"].to_numpy()[ok],
                                       wiebe.bdur_10_90_to_bdur(b[ok], m[ok]), m[ok])
    err = np.abs(ca50 - st.ca50_target_deg_atdc).reshape(len(cells), sparks.size)
    err = np.where(np.isfinite(err), err, np.inf)
    best = sparks[np.argmin(err, axis=1)]
    # no usable prediction at all: fall back to the DOE prior's spark
    none = ~np.isfinite(err).any(axis=1)
    if none.any():
        est = np.atleast_1d(priors.spark_estimate(cells["speed_rpm"].to_numpy(float)[none],
                                               cells["throttle_pct"].to_numpy(float)[none]))
        best[none] = np.clip(est, st.spark_min_deg_btdc, st.spark_max_deg_btdc)
    return best


def decide_cell(ev: pd.DataFrame, st: MapSettings) -> tuple[str, object]:
    """Next sparks to evaluate for one cell, or its resolution.

    ``ev``: the cell's evaluations (any order).  Returns ``('need', [spark, ...])``
    or ``('done', {status, mbt, border, raw, limited_by})``; spark values in deg BTDC.
    """
    lo, hi, lim = st.spark_min_deg_btdc, st.spark_max_deg_btdc, st.knock_limit
    ok = ev[np.isfinite(ev["brake_torque_nm"]) & np.isfinite(ev["knock_index"])].sort_values("spark_deg_btdc")
    ok = ok.drop_duplicates("spark_deg_btdc")
    s, tq, kn = (ok[c].to_numpy(float) for c in ("spark_deg_btdc", "brake_torque_nm", "knock_index"))
    kn = cycle_knock(s, kn, st.cycle_advance)    # knock-free means: the fastest cycles too
    eps = 1e-6
    if s.size == 0:
        return "done", {"status": "failed", "mbt": math.nan, "border": math.nan, "raw": math.nan,
                        "limited_by": "infeasible"}
    if kn[0] >= lim:   # knocks at the most retarded spark tried
        if s[0] <= lo + eps:
            return "done", {"status": "zone1", "mbt": math.nan, "border": lo, "raw": lo, "limited_by": "infeasible"}
        guess = _knock_cross(s[0], kn[0], s[1], kn[1], lim) if s.size > 1 else s[0] - 8.0
        return "need", sorted({max(lo, min(guess - 0.5, s[0] - 1.0)), max(lo, min(guess - 4.5, s[0] - 5.0))})
    bm = ok["bmep_bar"].to_numpy(float) if "bmep_bar" in ok.columns else np.full(s.size, np.inf)
    if np.all(bm < st.min_bmep_bar):   # zone 2: no spark gives a holdable load; no refinement spent here
        safe = kn < lim
        j = int(np.argmax(np.where(safe, tq, -np.inf)))
        return "done", {"status": "zone2", "mbt": math.nan, "border": s[safe].max() if safe.any() else lo,
                        "raw": s[j], "limited_by": "infeasible"}
    knocking = np.flatnonzero(kn >= lim)
    kk = int(knocking[0]) if knocking.size else s.size
    S, T = s[:kk], tq[:kk]
    s_knock = s[kk] if kk < s.size else None
    border = S[-1] if s_knock is not None else hi
    imax = int(np.argmax(T))
    if imax == S.size - 1:          # torque still rising at the top of the knock-safe range
        if s_knock is None:
            if S[-1] >= hi - eps:
                return "done", {"status": "ok", "mbt": hi, "border": hi, "raw": hi, "limited_by": "spark_max"}
            return "need", sorted({min(hi, S[-1] + 4.0), min(hi, S[-1] + 8.0)})
        cross = _knock_cross(S[-1], kn[kk - 1], s_knock, kn[kk], lim)
        if cross - S[-1] <= st.knock_tol_deg or s_knock - S[-1] <= st.knock_tol_deg:
            # MBT from all points (knocking ones too) if the peak is inside the sweep
            j = int(np.argmax(tq))
            mbt = _vertex(s[j - 1:j + 2], tq[j - 1:j + 2]) if 0 < j < s.size - 1 else math.nan
            if mbt < S[-1]:   # the parabola peaks before the last knock-free spark: MBT-limited after all
                return "done", _at_mbt(mbt, S[-1], st)
            return "done", {"status": "ok", "mbt": mbt, "border": S[-1], "raw": S[-1], "limited_by": "knock"}
        target = cross - 0.2 if cross - 0.2 < s_knock - 0.05 else 0.5 * (S[-1] + s_knock)
        return "need", [max(S[-1] + 0.05, target)]
    if imax == 0 and S[0] > lo + eps:   # torque falls from the most retarded spark: MBT further back
        return "need", sorted({max(lo, S[0] - 4.0), max(lo, S[0] - 8.0)})
    if imax == 0:
        mbt = lo
    else:
        mbt = _peak(S, T, imax, st.mbt_window_deg)
        h = st.refine_step_deg
        cand = [c for c in (mbt - h, mbt, mbt + h) if lo <= c <= min(hi, border)]
        cand = [c for c in cand if np.min(np.abs(s - c)) > 0.4 * h]
        if cand:
            return "need", sorted(cand)
    return "done", _at_mbt(mbt, border, st)


def _at_mbt(mbt: float, border: float, st: MapSettings) -> dict:
    """Resolution of an MBT-limited cell: spark MBT less the safety retard (not below the spark range)."""
    return {"status": "ok", "mbt": mbt, "border": border, "raw": max(st.spark_min_deg_btdc, mbt - st.safety_retard_deg),
            "limited_by": "retard" if st.safety_retard_deg > 0 else "mbt"}


class SparkRunner:
    """Batched evaluations: builds one plan per stage (rows of a cell consecutive, spark ascending)."""

    def __init__(self, model, cells: pd.DataFrame, evaluate, progress, advance: float = 0.0):
        self.model, self.cells, self.evaluate, self.progress = model, cells, evaluate, progress
        self.advance = float(advance)
        self.frames: list[pd.DataFrame] = []
        self.calls = 0
        self.points = 0

    def run(self, requests: dict[int, list[float]], tag: str) -> pd.DataFrame:
        rows = []
        for c in sorted(requests):
            for k, s in enumerate(sorted(set(round(float(x), 2) for x in requests[c]))):
                rows.append({"point_id": f"map-{tag}-c{c:04d}-{k:02d}", "cell": c, "stage": tag,
                             "throttle_pct": self.cells.at[c, "throttle_pct"],
                             "speed_rpm": self.cells.at[c, "speed_rpm"], "spark_deg_btdc": s,
                             "lambda": self.cells.at[c, "lambda"]})
        plan = pd.DataFrame(rows)
        if plan.empty:
            return plan
        b, m = _predict(self.model, plan)
        plan["bdur_10_90_deg"], plan["wiebe_m"] = b, m
        good = np.isfinite(b)
        out = plan.copy()
        for col in EVAL_COLUMNS:
            out[col] = np.nan
        out["converged"] = False
        out["status"] = np.where(good, "", "failed: no combustion prediction").astype(object)
        if good.any():
            send = plan[good].reset_index(drop=True)
            cols = ["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda", "bdur_10_90_deg", "wiebe_m"]
            res = self.evaluate(send[cols])
            self.calls += 1
            self.points += len(send)
            if len(res) != len(send):
                raise ValueError(f"evaluate returned {len(res)} rows for a plan of {len(send)} points")
            res = res.reset_index(drop=True)
            if "point_id" in res.columns and list(res["point_id"].astype(str)) != list(send["point_id"]):
                raise ValueError("evaluate returned the points in a different order than planned")
            idx = np.flatnonzero(good)
            for col in EVAL_COLUMNS:
                if col in res.columns:
                    vals = res[col].to_numpy(dtype=object if col == "status" else float)
                    if col == "converged":
                        vals = res[col].astype(bool).to_numpy()
                    out.loc[idx, col] = vals
        self.frames.append(out)
        if self.progress is not None:
            self.progress(tag, len(plan))
        return out

    def evaluations(self) -> pd.DataFrame:
        """All evaluations so far, with ``knock_index_cycle`` (the fastest cycles', :func:`cycle_knock`)."""
        ev = pd.concat(self.frames, ignore_index=True) if self.frames else pd.DataFrame(columns=["cell"])
        return with_cycle_knock(ev, self.advance)


# --------------------------------------------------------------------------- knock safety against model uncertainty

#: Half-step of the central difference of the knock index in the CA50 offset [deg] (the burn made this much faster
#: and slower, BDUR10-90 scaled, m kept).  The cycle model's knock index carries a +-1.5 % ripple against spark at
#: the maps' 0.5 deg crank step (gone at 0.25 deg; measured at 4000 rpm, 60 % throttle, docs/sections/tables.md), and
#: its slopes are 0.01-0.05 per deg: a one-sided 2 deg step gave gains of 0.14-3.0 between neighbouring cells and
#: 1.2 / 2.6 / 1.4 at one cell for 1 / 2 / 4 deg steps.  +-3 deg puts the ripple at ~5 % of the difference.
_PHASING_FD_DEG = 3.0
#: Spark window around the border for the knock index's spark slope [deg]: the search's points within it are fitted
#: by a line in ln K (>= 2 points; else the two points bracketing the border, else all points).
_SLOPE_WINDOW_DEG = 6.0
#: Gain used when the sensitivity cannot be measured (extra points failed, knock slope not positive): a shift of
#: the whole burn by 1 deg is then taken as worth 1 deg of spark (knock as a function of phasing alone).
_PHASING_GAIN_FALLBACK = 1.0


def _phasing_std(model, pts: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(bdur_10_90, m, CA50 offset, 1-sigma of the CA50 offset) per row [deg, -, deg, deg].

    The std is the model's ``ca50_offset_deg_std`` if it predicts one (phasing models), else the delta method on
    ``bdur_10_90_deg_std`` and ``wiebe_m_std`` with independent errors; 0 where the model gives no std at all.
    """
    pred, b, m = _predict_frame(model, pts)
    n = len(pred)
    ok = np.isfinite(b)
    off = np.full(n, np.nan)
    off[ok] = ca50_offset_deg(b[ok], m[ok])
    sig = np.zeros(n)
    if "ca50_offset_deg_std" in pred.columns:
        sig = pd.to_numeric(pred["ca50_offset_deg_std"], errors="coerce").to_numpy(float).copy()
    elif {"bdur_10_90_deg_std", "wiebe_m_std"} <= set(pred.columns):
        sb = pd.to_numeric(pred["bdur_10_90_deg_std"], errors="coerce").to_numpy(float)
        sm = pd.to_numeric(pred["wiebe_m_std"], errors="coerce").to_numpy(float)
        h = 1e-4
        d_m = np.full(n, np.nan)
        d_m[ok] = (ca50_offset_deg(b[ok], m[ok] + h) - ca50_offset_deg(b[ok], m[ok] - h)) / (2 * h)
        sig = np.hypot(off / b * sb, d_m * sm)     # offset is proportional to BDUR10-90 at fixed m
    sig = np.where(ok & np.isfinite(sig), np.maximum(sig, 0.0), 0.0)
    return b, m, off, sig


def _knock_slope(grp: pd.DataFrame, border: float) -> float:
    """d ln(knock index)/d spark [1/deg] at the border: a line through the evaluated points within
    ``_SLOPE_WINDOW_DEG`` of it, else the two points that bracket it, else a line through all."""
    g = grp[np.isfinite(grp["knock_index"]) & (grp["knock_index"] > 0)].sort_values("spark_deg_btdc")
    g = g.drop_duplicates("spark_deg_btdc")
    s, k = g["spark_deg_btdc"].to_numpy(float), np.log(g["knock_index"].to_numpy(float))
    near = np.abs(s - border) <= _SLOPE_WINDOW_DEG + 1e-6
    if near.sum() >= 2 and np.ptp(s[near]) > 1.0:
        slope = np.polyfit(s[near], k[near], 1)[0]
        if slope > 1e-3:
            return float(slope)
    below, above = s <= border + 1e-6, s > border + 1e-6
    if below.any() and above.any():
        i, j = np.flatnonzero(below)[-1], np.flatnonzero(above)[0]
        slope = (k[j] - k[i]) / (s[j] - s[i])
        if slope > 1e-3:
            return float(slope)
    if s.size >= 2:
        slope = np.polyfit(s, k, 1)[0]
        if slope > 1e-3:
            return float(slope)
    return math.nan


def uncertainty_retard(runner: "SparkRunner", ev: pd.DataFrame, cells: pd.DataFrame, st: "MapSettings") -> pd.DataFrame:
    """Per cell, the knock-border retard for the model's burn uncertainty (``MapSettings.knock_uncertainty_z``).

    For each cell with a resolved knock border (``spark_border_deg_btdc`` below spark_max), at the border spark:
    ``sigma`` = 1-sigma of the model's CA50 offset; ``g`` = (d ln K / d earlier CA50) / (d ln K / d spark), the
    first a central difference from two extra simulations with the burn made ``_PHASING_FD_DEG`` faster and slower
    (BDUR10-90 scaled, m kept), the second a line through the search's own points within ``_SLOPE_WINDOW_DEG`` of
    the border; a g that is an outlier among the measured gains around the cell is replaced by their median
    (:func:`neighbour_median_gain`);
    retard = z * sigma * |g| [deg]: the burn error
    has either sign, and which side knocks more depends on the cell (a faster burn advances CA50 but, with the
    knock integral ending at the end-gas burn fraction, also consumes the end gas sooner).  One batched evaluate call
    (stage ``u1``), only for the cells that need it.  Returns columns ``phasing_std_deg, knock_phasing_gain,
    knock_phasing_gain_measured, knock_phasing_gain_cell, knock_uncertainty_border_retard_deg`` indexed like
    ``cells`` (0 / NaN / False where not applicable; gain not measured: the fallback ``_PHASING_GAIN_FALLBACK``;
    ``knock_phasing_gain_cell`` is the cell's own value before the median).
    """
    out = pd.DataFrame({"phasing_std_deg": np.nan, "knock_phasing_gain": np.nan, "knock_phasing_gain_measured": False,
                        "knock_phasing_gain_cell": np.nan, "knock_uncertainty_border_retard_deg": 0.0},
                       index=cells.index)
    z = float(st.knock_uncertainty_z)
    border = cells["spark_border_deg_btdc"].to_numpy(float)
    need = cells["feasible"].to_numpy(bool) & np.isfinite(border) & (border < st.spark_max_deg_btdc - 1e-6)
    if z <= 0 or not need.any():
        return out
    idx = cells.index[need]
    pts = cells.loc[idx, ["throttle_pct", "speed_rpm", "lambda"]].copy()
    pts["spark_deg_btdc"] = border[need]
    b, m, off, sig = _phasing_std(runner.model, pts)
    out.loc[idx, "phasing_std_deg"] = sig
    go = np.isfinite(off) & (sig > 0)
    if not go.any():
        return out
    delta = np.minimum(_PHASING_FD_DEG, 0.5 * off)[go]
    base = pts[go].copy()
    fast, slow = base.copy(), base.copy()
    fast["bdur_10_90_deg"] = b[go] * (off[go] - delta) / off[go]
    slow["bdur_10_90_deg"] = b[go] * (off[go] + delta) / off[go]
    fast["wiebe_m"] = slow["wiebe_m"] = m[go]
    fast.insert(0, "point_id", [f"map-u1-c{int(c):04d}-fast" for c in base.index])
    slow.insert(0, "point_id", [f"map-u1-c{int(c):04d}-slow" for c in base.index])
    plan = pd.concat([fast, slow])
    cols = ["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda", "bdur_10_90_deg", "wiebe_m"]
    res = runner.evaluate(plan[cols].reset_index(drop=True))
    runner.calls += 1
    runner.points += len(plan)
    if len(res) != len(plan):
        raise ValueError(f"evaluate returned {len(res)} rows for a plan of {len(plan)} points")
    k = pd.to_numeric(res["knock_index"], errors="coerce").to_numpy(float)
    n_go = len(base)
    k_fast, k_slow = k[:n_go], k[n_go:]
    rec = plan.assign(cell=plan.index.to_numpy(), stage="u1").reset_index(drop=True)
    for col in EVAL_COLUMNS:
        rec[col] = res[col].to_numpy() if col in res.columns else np.nan
    rec["status"] = [f"burn {w} (CA50 {d:g} deg {e}) for the knock-uncertainty retard; {s}"
                     for (w, e), d, s in zip([("faster", "earlier")] * n_go + [("slower", "later")] * n_go,
                                             np.concatenate([delta, delta]), rec["status"].astype(str))]
    runner.frames.append(rec)
    for j, c in enumerate(base.index):
        grp = ev[ev["cell"] == c]
        slope = _knock_slope(grp, float(base.at[c, "spark_deg_btdc"]))
        gain = _PHASING_GAIN_FALLBACK
        if math.isfinite(slope) and k_fast[j] > 0 and k_slow[j] > 0 and math.isfinite(k_fast[j] * k_slow[j]):
            # central difference; magnitude: an error of either sign is as likely; > 3 deg/deg is not physical here
            gain = float(np.clip(abs(math.log(k_fast[j] / k_slow[j])) / (2.0 * delta[j]) / slope, 0.0, 3.0))
            out.at[c, "knock_phasing_gain_measured"] = True
        out.at[c, "knock_phasing_gain"] = gain
    out["knock_phasing_gain_cell"] = out["knock_phasing_gain"]
    if {"i", "j"} <= set(cells.columns):
        out["knock_phasing_gain"] = neighbour_median_gain(
            cells["i"].to_numpy(int), cells["j"].to_numpy(int), out["knock_phasing_gain_cell"].to_numpy(float),
            out["knock_phasing_gain_measured"].to_numpy(bool))
    out.loc[idx, "knock_uncertainty_border_retard_deg"] = (
        z * out.loc[idx, "phasing_std_deg"].to_numpy(float) * np.nan_to_num(out.loc[idx, "knock_phasing_gain"]))
    return out


#: Fewest measured gains in a cell's 3 x 3 neighbourhood (itself included) for the outlier test: with three, one
#: outlier can be told from the other two; with two the median is their mean and rejects nothing.
_GAIN_MEDIAN_MIN = 3
#: Hampel identifier: a gain is an outlier when it lies more than this many scaled median absolute deviations
#: (1.4826 MAD, the normal distribution's sigma) from its neighbourhood's median.  3 is the identifier's usual
#: threshold (F. R. Hampel, J. Am. Stat. Assoc. 69 (1974) 383-393; R. K. Pearson, IEEE Trans. Control Syst.
#: Technol. 10 (2002) 55-63, the window filter with t = 3).
_GAIN_OUTLIER_MADS = 3.0
_MAD_TO_SIGMA = 1.4826


def neighbour_median_gain(i: np.ndarray, j: np.ndarray, gain: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Each measured gain that is an outlier in its 3 x 3 grid neighbourhood replaced by the neighbourhood's median.

    ``i, j`` are the cells' throttle-row and speed-column indices.  The gain is a property of the engine's knock
    chemistry and phasing and varies smoothly over the map; a single cell's finite difference also carries the
    global burn model's local bends in spark (a burn that slows as the spark advances flattens the knock index's
    spark slope, the gain's denominator, in that cell alone; docs/sections/tables.md).  A gain is an outlier when
    it lies more than ``_GAIN_OUTLIER_MADS`` scaled median absolute deviations from the median of the measured gains
    around it (itself included; the Hampel identifier); a gain within the neighbourhood's own spread is the cell's
    information and is kept.  Cells with fewer than ``_GAIN_MEDIAN_MIN`` measured gains around them, and cells whose
    own gain was not measured (the fallback), keep their own value.
    """
    gain = np.asarray(gain, float)
    out = gain.copy()
    ok = np.asarray(measured, bool) & np.isfinite(gain)
    for c in np.flatnonzero(ok):
        near = ok & (np.abs(i - i[c]) <= 1) & (np.abs(j - j[c]) <= 1)
        if near.sum() >= _GAIN_MEDIAN_MIN:
            med = float(np.median(gain[near]))
            spread = _MAD_TO_SIGMA * float(np.median(np.abs(gain[near] - med)))
            if abs(gain[c] - med) > _GAIN_OUTLIER_MADS * spread:
                out[c] = med
    return out
