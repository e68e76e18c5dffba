"""The diagnosis' verdict in words: category, candidate, how much of the gap it removes, where the gap is."""

from __future__ import annotations

import numpy as np
import pandas as pd

from engine_model.gap.localise import CHAIN_T_MIN
from engine_model.gap.rivals import RIVAL_ALPHA
from engine_model.gap.sensors import is_sensor, sensor_channel

__all__ = ["verdict_statement", "param_text", "kind_of", "rivals_of_another_kind"]


def param_text(name: str, value: float, se: float, prm) -> str:
    """``name = value +- s.e.`` of a fitted candidate parameter, flagged when the data do not determine it.

    A standard error wider than the parameter's whole documented range (``prm.lo`` .. ``prm.hi``) means
    the fitted value says nothing about the effect's size (typically: the parameter is nearly collinear
    with the base calibration), and the text says so rather than print a bare number.
    """
    txt = f"{name} = {value:.4g} +- {se:.2g}"
    if not (se <= prm.hi - prm.lo):
        txt += f" (s.e. wider than its range {prm.lo:g} .. {prm.hi:g}: not determined by these data)"
    return txt


def kind_of(name: str) -> str:
    """A sensor fault is its own kind per channel; all physical effects are one kind."""
    return name if is_sensor(name) else "physical effect"


def order_ranking(rank: pd.DataFrame, thr: float) -> pd.DataFrame:
    """Candidates best first: held-out chi2 decides which candidates are in the lead, AIC orders the lead.

    The lead is every candidate whose held-out chi2 is within the noise threshold ``thr`` of the lowest;
    it is ordered by AIC (in-sample chi2 + 2 k), the rest follows by held-out chi2 (BIC breaks ties).
    Why: the held-out score is what the threshold is calibrated on, so it says whether a candidate's
    improvement is real; but two candidates it cannot separate differ by less than the split noise of
    K-fold cross-validation, and the in-sample likelihood with AIC's parameter penalty compares them on
    all points at once with lower variance (AIC and leave-one-out cross-validation agree asymptotically,
    Stone 1977; single K-fold splits add selection variance, Shao 1993).  For candidates of equal size this
    is the likelihood ratio.  Measured on the in-library benchmark: fewer wrong claims among the torque-only
    losses (docs/sections/gap.md, results).
    """
    rank = rank.sort_values(["heldout_chi2", "bic"]).reset_index(drop=True)
    lead = (rank["heldout_chi2"] - rank["heldout_chi2"].iloc[0]) < thr
    order = np.lexsort((np.arange(len(rank)), np.where(lead, rank["aic"].to_numpy(float), 0.0), ~lead.to_numpy()))
    return rank.iloc[order].reset_index(drop=True)


def rivals_of_another_kind(rank: pd.DataFrame, thr: float) -> list[str]:
    """Candidates of another kind than the best (:func:`kind_of`) whose held-out chi2 is within ``thr`` of it."""
    if len(rank) < 2:
        return []
    best = rank.iloc[0]
    close = rank[(rank["rank"] > 1) & (rank["heldout_chi2"] - best["heldout_chi2"] < thr)]
    return [c for c in close["effect"] if kind_of(c) != kind_of(best["effect"])]


def _who(name: str) -> str:
    return f"a fault of the {sensor_channel(name)} reading" if is_sensor(name) else f"'{name}'"


def verdict_statement(category: str, claimed: str | None, best: str | None, rank: pd.DataFrame, thr: float,
                      gap_before: float, gap_after: float, reduction: float, q_chi2: float, chain: pd.DataFrame,
                      stages: pd.DataFrame, regions: pd.DataFrame, rival_p: dict | None = None) -> str:
    """One paragraph: the category and its evidence, indistinguishable rivals, where, the energy chain.

    ``rival_p``: p-values of the close rivals of another kind that were tested (:mod:`engine_model.gap.rivals`);
    a rival with p below :data:`~engine_model.gap.rivals.RIVAL_ALPHA` is named as rejected, not as a tie.
    """
    rival_p = rival_p or {}
    rejected = {c: p for c, p in rival_p.items() if p < RIVAL_ALPHA}
    parts = []
    row = rank.iloc[0] if len(rank) else None
    if category == "no significant gap":
        parts.append(f"No significant gap: the held-out residual of the base calibration ({gap_before:.2f} sigma "
                     "rms) is consistent with the measurement noise and the base's structural error, and no "
                     "candidate improves on the base and its structural level by more than noise would. No "
                     "candidate is claimed.")
        if row is not None and row["heldout_improvement"] > thr:
            close = rank[rank["heldout_chi2"] - row["heldout_chi2"] < thr]["effect"]
            parts.append(f"({' and '.join(_who(c) for c in close)} would each reduce it by more than noise alone, "
                         "and cannot be told apart here.)")
    elif category in ("explained", "sensor fault"):
        head = ("The gap is a sensor fault: " + _who(claimed) if category == "sensor fault"
                else f"The gap is explained by '{claimed}'")
        parts.append(f"{head} ({row['params']}); held-out gap {gap_before:.2f} -> {gap_after:.2f} sigma rms "
                     f"({reduction:.0f} % of the gap above noise removed, the rest within what noise leaves), "
                     f"weight {row['weight']:.2f} among the candidates.")
        if claimed == "transmission_efficiency":
            parts.append("A gain error of the torque meter reads the same (brake torque = eta x engine torque).")
        if claimed == "friction":
            parts.append("An offset of the torque meter reads like a change of the friction level (a constant "
                         "torque); only the friction's speed term tells them apart.")
        close = [c for c in rank[(rank["rank"] > 1) & (rank["heldout_chi2"] - row["heldout_chi2"] < thr)]["effect"]
                 if c not in rejected]
        if rejected:
            parts.append("Scored within the noise threshold but rejected by a parametric test of each as the truth: "
                         + ", ".join(f"{_who(c)} (p = {p:.3f})" for c, p in rejected.items()) + ".")
        if len(close):
            parts.append("Not distinguishable from it with these measurements (held-out chi2 within the noise "
                         f"threshold): {', '.join(_who(c) for c in close)}.")
        elif len(rank) > 1:
            r2 = rank.iloc[1]
            parts.append(f"Runner-up: {_who(r2['effect'])} (held-out chi2 {r2['heldout_chi2']:.1f} vs "
                         f"{row['heldout_chi2']:.1f}).")
    elif category == "indistinguishable":
        close = [c for c in rank[rank["heldout_chi2"] - row["heldout_chi2"] < thr]["effect"] if c not in rejected]
        parts.append(f"Indistinguishable, not claimed: {' or '.join(_who(c) for c in close)} explain the gap "
                     f"equally well within the noise threshold (best held-out gap {gap_before:.2f} -> "
                     f"{gap_after:.2f} sigma rms, {reduction:.0f} % of the gap above noise); another reading "
                     "or points that separate them would decide.")
    elif category == "partly explained":
        why = []
        if row["heldout_chi2"] > q_chi2:
            why.append(f"what it leaves (held-out chi2 {row['heldout_chi2']:.0f}) is more than noise and the "
                       f"base's structural error leave (99 % quantile {q_chi2:.0f})")
        if row["at_range_bound"]:
            why.append(f"{row['at_range_bound']} sits at the edge of its documented range (the data ask for "
                       "more than the effect can give)")
        parts.append(f"Partly explained, not claimed: the best candidate, {_who(best)} ({row['params']}), "
                     f"reduces the held-out gap {gap_before:.2f} -> {gap_after:.2f} sigma rms ({reduction:.0f} % "
                     f"of the gap above noise), but {' and '.join(why)}: a larger or another cause is at work.")
    else:
        txt = (f"Not in the library: a gap of {gap_before:.2f} sigma rms held out, more than noise leaves, that "
               "no candidate reduces by more than noise would")
        if row is not None:
            txt += f" (best: {_who(best)}, {gap_before:.2f} -> {gap_after:.2f} sigma rms)"
        parts.append(txt + ".")
    if len(regions):
        sig = regions[regions["significant"]].copy()
        if len(sig):
            sig = sig.reindex(sig["stat"].abs().sort_values(ascending=False).index).head(6)
            parts.append("Where (beats pure noise on this plan): " + "; ".join(
                f"{r.output} at {r.region}: {r.mean_z:+.1f} +- {r.se_z:.1f} sigma" for r in sig.itertuples()) + ".")
        elif category != "no significant gap":
            parts.append("Where: no single channel and region stands out from noise on this plan.")
    ch = chain[(chain["stage"] != "brake at dyno (total)")]
    booked = ch[ch["booked"]] if "booked" in ch.columns else ch.iloc[0:0]
    if len(booked):
        parts.append("Energy chain (share of the torque gap, mean +- s.e., significant shares only): " + "; ".join(
            f"{r.stage} {r.mean_pct:+.1f} +- {r.se_pct:.1f} %" for r in booked.itertuples()) + ".")
    tot = chain[chain["stage"] == "brake at dyno (total)"]
    if len(tot) and "booked" in tot.columns and not bool(tot["booked"].iloc[0]):
        off = ch[(ch["t"] >= CHAIN_T_MIN)]["stage"].tolist() if "t" in ch.columns else []
        if off:
            parts.append("Torque agrees with the model within noise, so no share of a torque gap is booked; the "
                         f"residual behind {', '.join(off)} is not a torque loss (a reading, or effects that "
                         "cancel in torque).")
    if len(stages) and category in ("partly explained", "not in the library"):
        st = stages.iloc[0]
        if st["beats_noise"]:
            parts.append(f"Among the library's stages the largest held-out improvement comes from "
                         f"'{st['stage']}' candidates.")
    return " ".join(parts)
