"""Transmission efficiency in the identification: sensitivity, the paper's eq-6 relation, joint fit.

The bench measures torque behind the gearbox, so the crank target is
P_meas / eta_trans with eta_trans unknown (~0.95 in the paper).  eta only
scales the target, so everything here is post-processing of the response
surfaces built by :func:`engine_model.calibration.identify.identify` (no re-simulation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from engine_model.calibration.identify import CHI2_95_1DOF, Identification, chi2_terms, identify_point, terms_used

DEFAULT_ETAS = tuple(np.round(np.arange(0.85, 1.0001, 0.01), 3))


def eta_sensitivity(ident: Identification, etas=DEFAULT_ETAS) -> pd.DataFrame:
    """Identified parameters versus the assumed eta_trans (post-processing; eta only scales the target).

    Returns one row per (bench point, eta_trans) with the columns of :func:`identify_point`.
    """
    rows = []
    for pid, ps in ident.surfaces.items():
        for eta in etas:
            r = identify_point(ps, float(eta), ident.tol)
            rows.append({"point_id": pid, "speed_rpm": float(ps.row["speed_rpm"]),
                         "throttle_pct": float(ps.row["throttle_pct"]), "eta_trans": float(eta), **r})
    return pd.DataFrame(rows)


def power_isolines(ident: Identification, etas=DEFAULT_ETAS, branch: str = "late") -> pd.DataFrame:
    """Samples of the measured-power isoline ``P_sim(b, m) = P_meas / eta`` on one side of the ridge.

    For each m of the fine mesh the BDUR10-90 where simulated power crosses the
    target on the ``branch`` side ('late': BDUR beyond the ridge).  Returns
    ``point_id, eta_trans, wiebe_m, bdur_10_90_deg``.
    """
    rows = []
    for pid, ps in ident.surfaces.items():
        P = ps.fine["brake_power_kw"]
        dpdb = np.gradient(P, ps.fine_b, axis=0)
        for eta in etas:
            target = float(ps.row["brake_power_kw"]) / float(eta)
            for j, m in enumerate(ps.fine_m[::5]):
                col = P[:, 5 * j] - target
                side = dpdb[:, 5 * j] < 0 if branch == "late" else dpdb[:, 5 * j] >= 0
                s = np.flatnonzero(side[:-1] & side[1:] & (np.sign(col[:-1]) != np.sign(col[1:])))
                if s.size:
                    k = int(s[0])
                    bb = ps.fine_b[k] + (ps.fine_b[k + 1] - ps.fine_b[k]) * col[k] / (col[k] - col[k + 1])
                    rows.append({"point_id": pid, "eta_trans": float(eta), "wiebe_m": float(m), "bdur_10_90_deg": bb})
    return pd.DataFrame(rows, columns=["point_id", "eta_trans", "wiebe_m", "bdur_10_90_deg"])


ETA_RELATION_TERMS = ("1", "eta", "m", "m*eta", "m^2")   # the paper's eq 6


def fit_eta_relation(isolines: pd.DataFrame) -> pd.DataFrame:
    """Fit ``BDUR10-90 = c0 + c1 eta + c2 m + c3 m eta + c4 m^2`` (paper eq 6) per bench point.

    Returns one row per point: the coefficients ``c_1, c_eta, c_m, c_m*eta, c_m^2``, rms [deg], n and
    the m range covered.
    """
    rows = []
    for pid, g in isolines.groupby("point_id", sort=False):
        e, m, b = (g[c].to_numpy(float) for c in ("eta_trans", "wiebe_m", "bdur_10_90_deg"))
        X = np.column_stack([np.ones_like(m), e, m, m * e, m * m])
        if len(g) < 8 or np.ptp(e) == 0:
            rows.append({"point_id": pid, "n": len(g), "status": "too few isoline samples"})
            continue
        c, *_ = np.linalg.lstsq(X, b, rcond=None)
        rms = float(np.sqrt(np.mean((X @ c - b) ** 2)))
        rows.append({"point_id": pid, **{f"c_{t}": float(v) for t, v in zip(ETA_RELATION_TERMS, c)},
                     "rms_deg": rms, "n": len(g), "m_min": float(m.min()), "m_max": float(m.max()), "status": "ok"})
    return pd.DataFrame(rows)


def relation_text(row) -> str:
    """The fitted eq-6 relation of one point as text."""
    return (f"BDUR10-90 = {row['c_1']:.2f} {row['c_eta']:+.2f} eta {row['c_m']:+.3f} m {row['c_m*eta']:+.3f} m eta "
            f"{row['c_m^2']:+.4f} m^2  (rms {row['rms_deg']:.2f} deg, m {row['m_min']:.1f}-{row['m_max']:.1f})")


# --------------------------------------------------------------------------- joint fit

@dataclass
class JointFit:
    """eta_trans shared by all points of one throttle: profile chi2 and the best value per group."""

    profile: pd.DataFrame      # throttle_pct, eta_trans, chi2 (sum over points of each point's minimum)
    table: pd.DataFrame        # throttle_pct, eta_best, eta_lo, eta_hi, identifiable, points, chi2_min

    def eta_by_throttle(self) -> dict:
        """``{throttle_pct: eta_best}`` (the profile minimum, also where it is not identified)."""
        return {float(r.throttle_pct): float(r.eta_best) for r in self.table.itertuples()}

    def summary(self) -> str:
        parts = []
        for r in self.table.itertuples():
            if r.identifiable:
                parts.append(f"throttle {r.throttle_pct:g} %: eta_trans = {r.eta_best:.3f} "
                             f"(95 % {r.eta_lo:.3f}-{r.eta_hi:.3f}, {r.points} points)")
            else:
                parts.append(f"throttle {r.throttle_pct:g} %: eta_trans not identified ({r.note}; profile "
                             f"minimum {r.eta_best:.3f}, chi2 within 3.84 over {r.eta_lo:.3f}-{r.eta_hi:.3f}; "
                             f"{r.points} points)")
        return "Joint fit with a shared eta_trans per throttle: " + "; ".join(parts) + "."


def joint_fit(ident: Identification, etas=None,
              power_meas: dict | None = None) -> JointFit:
    """Profile likelihood of a shared eta_trans across all points of each throttle setting.

    ``chi2(eta) = sum_i min_(b,m) chi2_i(b, m; eta)``; best eta at the minimum, 95 % interval where
    ``chi2 - min <= 3.84``.  If that interval spans the whole scanned range the data do not
    determine eta (e.g. power + CA50 alone: every eta has its own exact (b, m)).
    """
    etas = np.round(np.arange(0.85, 1.0001, 0.0025), 4) if etas is None else np.asarray(etas, float)
    rows = []
    for pid, ps in ident.surfaces.items():
        terms = terms_used(ps.row)
        pm = None if power_meas is None else power_meas[pid]
        for eta in etas:
            c = sum(chi2_terms(ps, float(eta), ident.tol, terms, pm).values())
            rows.append({"point_id": pid, "throttle_pct": float(ps.row["throttle_pct"]), "eta_trans": float(eta),
                         "chi2": float(np.nanmin(c))})
    per = pd.DataFrame(rows)
    prof = per.groupby(["throttle_pct", "eta_trans"], as_index=False).agg(chi2=("chi2", "sum"),
                                                                          points=("point_id", "nunique"))
    informative = {pid: bool(set(terms_used(ps.row)) - {"power", "pmax", "ca50"})
                   for pid, ps in ident.surfaces.items()}
    th_info = per.assign(info=per["point_id"].map(informative)).groupby("throttle_pct")["info"].any()
    out = []
    for th, g in prof.groupby("throttle_pct"):
        g = g.sort_values("eta_trans")
        k = int(np.argmin(g["chi2"].to_numpy()))
        inside = g["chi2"].to_numpy() <= g["chi2"].iloc[k] + CHI2_95_1DOF
        e = g["eta_trans"].to_numpy()
        ident_ = not (inside[0] and inside[-1])
        if not ident_:
            why = "flat profile: every eta has its own (BDUR10-90, m)"
        elif not th_info[th]:
            ident_ = False
            why = ("power, CA50 and Pmax only: the profile is bounded by the edges of the (BDUR10-90, m) plane, "
                   "not by data; needs exhaust temperature, BSFC or fuel flow")
        else:
            why = ""
        out.append({"throttle_pct": th, "eta_best": float(e[k]), "eta_lo": float(e[inside].min()),
                    "eta_hi": float(e[inside].max()), "identifiable": bool(ident_), "points": int(g["points"].iloc[0]),
                    "chi2_min": float(g["chi2"].iloc[k]), "note": why})
    return JointFit(prof, pd.DataFrame(out))


def identify_at_eta(ident: Identification, eta_trans) -> Identification:
    """Re-identify every point at another transmission efficiency (post-processing, no simulation).

    Parameters
    ----------
    ident : Identification
        From :func:`engine_model.calibration.identify.identify` (its surfaces are reused).
    eta_trans : float or dict
        One eta_trans [-] for all points, or ``{throttle_pct: eta}`` (e.g. from
        :meth:`JointFit.eta_by_throttle`); points whose throttle is missing keep ``ident.eta_trans``.

    Returns
    -------
    Identification
        Same table layout as ``ident.table`` (contract columns, 95 % bounds, ``power_ok``, ``ca50_ok``,
        ``fit_ok``, ``status``) with ``eta_trans`` set per row; skipped or failed rows are kept as they were.
    """
    def eta_of(throttle):
        if isinstance(eta_trans, dict):
            return float(eta_trans.get(float(throttle), ident.eta_trans))
        return float(eta_trans)

    rows = []
    for _, r in ident.table.iterrows():
        row = r.to_dict()
        eta = eta_of(row["throttle_pct"])
        row["eta_trans"] = eta
        ps = ident.surfaces.get(str(row["point_id"]))
        if ps is not None:
            row.update(identify_point(ps, eta, ident.tol))
        rows.append(row)
    table = pd.DataFrame(rows, columns=list(ident.table.columns) +
                         [c for c in ("power_ok", "ca50_ok") if c not in ident.table.columns])
    one = float(eta_trans) if not isinstance(eta_trans, dict) else float(np.mean(list(eta_trans.values())))
    return Identification(table, ident.surfaces, one, ident.tol)
