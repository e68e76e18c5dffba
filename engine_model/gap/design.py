"""Model-discrimination design: choose the few bench points on which the candidate effects differ most.

A test engineer with a handful of dyno points plans them so that the hypotheses in question predict
DIFFERENT readings.  Here the hypotheses are the library's effects (and "no effect").  For a plan, the
evidence that effect *i* (at its realistic magnitude) is not effect *j* is the noiseless chi2 that effect
*j* plus a refitted base calibration cannot remove when *i* is the truth:

    d2(i | j) = || s_i - P_[B, J_j] s_i ||^2

where ``s_i`` is the whitened (measurement + model-error sigma) change of every reading that *i* makes,
``B`` the base parameters' whitened sensitivities and ``J_j`` the sensitivities of *j*'s parameters.  It is
the noncentrality of the likelihood-ratio test of *j* against *i*: the T-optimality criterion of
Atkinson & Fedorov (1975, Biometrika 62, 57-70, "The design of experiments for discriminating between two
rival models"), here with linearised models and the maximin over all ordered pairs of the library plus
the null hypothesis ``d2(i | none) = || s_i - P_B s_i ||^2`` (how far the effect stands out of noise).

Everything comes from the base model alone (one linearisation batch of a candidate pool about the DOE
prior, :func:`engine_model.gap.linear.linearise`); no bench data and no knowledge of which effect is
present is used, so this is a product feature: plan the bench session before it happens.

Selection (:func:`select_discriminating`) is a greedy forward pass followed by exchange passes
(Fedorov-style) on the per-point Gram matrices of the whitened columns, which add over points, so each
candidate's criterion is a batch of small solves.  Default objective (``"error"``): the sum over the
ordered pairs of ``Phi(-d/2)``, the Bayes error of telling two equiprobable Gaussian hypotheses a
Mahalanobis distance ``d`` apart, i.e. a union bound on the probability of naming the wrong one.  The
alternative ``"maximin"`` (largest smallest ``d2``) was measured worse by its own yardstick: on the
benchmark's 151 converged pool points (without burn scatter) the greedy+exchange maximin plan reached
min d2 = 19.7, the error-bound plan 21.4 (and a bound of 0.027 against 0.050); a 32-point Sobol'-like
subset of the pool has min d2 = 9.8 (blow-by vs transmission efficiency in both).  On the benchmark the
maximin plan also claimed an effect in 3 of 5 null trials (docs/sections/gap.md).

Coverage.  Left to the criterion alone the plan goes where the linearised effects differ most, the ends
of the speed range: the 32-point plan for the default pool had 16 points at 5000-7000 rpm, 9 above
11000 rpm and none between 8369 and 9978 rpm, inside the band of the real WOT bench data (8000-11000
rpm), so an effect localised there was invisible.  The selection therefore takes a coverage constraint
(:class:`engine_model.gap.coverage.AxisCoverage`, by default on speed, 1000 rpm): no gap between
neighbouring planned speeds, nor between an end of the range and the nearest planned speed, wider than
the limit.  A greedy step may only take a candidate after which the points still to choose can close
every remaining gap (the exact fewest points needed, a one-dimensional covering), and an exchange may only
swap in a candidate that keeps the plan covered; among covered plans the criterion still decides, so the
coverage points land where, within their gap, the effects differ most.  Too few points for the range at
the limit are refused with the minimum named (no automatic widening).  The candidate pool gets Sobol'
points of its own in any half-limit speed band with fewer than two (none needed by the 160-point pool).
Throttle coverage can be required the same way (``max_throttle_gap_pct``); by default it is reported
(throttle range per speed band, :func:`engine_model.gap.coverage.coverage_summary`), not constrained.
Measured 2026-11-26 with ``mbc gap-plan --out plan.csv`` (default pool, 147 of 160 candidates converged;
it prints both plans' figures): largest speed gap 843 rpm against 1609 rpm without the constraint,
misnaming bound 0.107 against 0.102, smallest d2 14.4 against 14.5 (blow-by vs heat transfer in both).

Measured limitation (on the plan before the coverage constraint; the benchmark, which now plans with
it, is to be re-measured): the distances are linear and assume the base's misfit is white noise of the
stated size; the 32-point plan this makes for the benchmark (13 points at 5000-6000 rpm) names 90.8 % of
the withheld effects at realistic magnitude (Sobol' 87.1 %) but claims an effect in 25 % of the null
trials with the diagonal error model, because the base misfits the hidden engine more at those extremes.
With the burn-scatter error model and a base that carries the burn's speed curvature the same plan names
91-93 % and claims an effect in 9 % of 340 null trials (docs/sections/gap.md), and since 2026-11-25 that
combination is the benchmark's default (``mbc gap-benchmark``) as well as a planning aid (``mbc gap-plan``).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import pandas as pd

from engine_model import doe
from engine_model.spec import EngineSpec, default_spec
from engine_model.gap.covariance import BURN_SCATTER_DEG, whiten_blocks   # the scatter the plan guards against, shared with diagnose
from engine_model.gap.covariance import MODEL_ERROR
from engine_model.gap.residuals import UNCERTAINTY, sigma_of
from engine_model.effects import EFFECTS, get_effect
from engine_model.gap.bench_procedure import BENCH_SOLVER, knock_backoff
from engine_model.gap.linear import SWEEP_BASE, BaseModel, Linearisation, linearise
from engine_model.gap.coverage import MAX_SPEED_GAP_RPM, AxisCoverage, coverage_summary, min_points_to_cover

__all__ = ["DesignProblem", "design_problem", "pair_distances", "select_discriminating", "candidate_pool",
           "discrimination_plan", "DESIGN_OUTPUTS", "CRITERIA"]

#: Readings the design counts on (the benchmark's bench: airflow, torque, exhaust T, fuel flow; BSFC is
#: redundant with fuel flow and torque, as in :func:`engine_model.gap.diagnose.check_bench_outputs`).
DESIGN_OUTPUTS = ("air_mass_flow_kg_h", "brake_torque_nm", "exhaust_temp_k", "fuel_mass_flow_kg_h")


class DesignProblem:
    """Whitened per-point blocks of the base and effect columns.

    Attributes
    ----------
    blocks : ndarray (n, o, q)
        Per candidate point, whitened sensitivities (rows: outputs; columns: base params then effect params,
        every column scaled to its FD step, effect steps = realistic magnitude).
    base_cols : list of int
    effect_cols : dict {effect: list of int}
    gram : ndarray (n, q, q)
        ``blocks[p].T @ blocks[p]``.
    """

    def __init__(self, blocks: np.ndarray, base_cols: Sequence[int], effect_cols: dict):
        blocks = np.asarray(blocks, dtype=float)
        if blocks.ndim != 3:
            raise ValueError(f"DesignProblem: blocks must be (points, outputs, columns), got shape {blocks.shape}")
        if not np.all(np.isfinite(blocks)):
            raise ValueError("DesignProblem: blocks contain non-finite values (drop points that did not converge)")
        self.blocks = blocks
        self.base_cols = list(base_cols)
        self.effect_cols = {k: list(v) for k, v in effect_cols.items()}
        if len(self.effect_cols) < 1:
            raise ValueError("DesignProblem: need at least one effect")
        self.gram = np.einsum("noq,nor->nqr", blocks, blocks)

    @property
    def n(self) -> int:
        return self.blocks.shape[0]

    def hypotheses(self) -> list[tuple[str, str | None]]:
        """Ordered pairs (true effect, rival) incl. the rival ``None`` (base alone)."""
        names = list(self.effect_cols)
        return [(i, j) for i in names for j in [None] + names if j != i]


def design_problem(lin: Linearisation, outputs: Sequence[str] = DESIGN_OUTPUTS, effects: Sequence[str] | None = None,
                   uncertainty: dict | None = None, model_error: dict | None = MODEL_ERROR,
                   burn_scatter_deg: float = 0.0) -> DesignProblem:
    """Whitened blocks of a :class:`~engine_model.gap.linear.Linearisation` (points that are not ok are zeroed).

    Sigma per reading as in the diagnosis (measurement + structural model error), evaluated at the
    model's own reference outputs.  ``burn_scatter_deg`` > 0 adds, per point, a correlated error along
    the point's BDUR10-90 sensitivity (a burn that deviates from the smooth base law at that point, which
    moves torque and exhaust T together; needs the base column ``bdur_offset_deg``): the covariance per
    point becomes ``I + tau^2 u u^T`` in sigma units and the blocks are whitened by its inverse square
    root (:func:`engine_model.gap.covariance.whiten_blocks`, the same whitening as the diagnosis'
    ``burn_scatter_deg``), so the design does not count on contrasts that such a burn deviation can mimic.
    """
    unc = dict(UNCERTAINTY)
    unc.update(uncertainty or {})
    oi = [lin.outputs.index(c) for c in outputs if c in lin.outputs]
    outs = [lin.outputs[k] for k in oi]
    sig = np.column_stack([sigma_of(c, lin.y_ref[:, k], unc, model_error) for c, k in zip(outs, oi)])
    blocks = lin.jac[:, oi, :] / sig[:, :, None] * lin.steps[None, None, :]
    blocks = np.where(np.isfinite(blocks) & lin.ok[:, None, None], blocks, 0.0)
    if burn_scatter_deg > 0:
        j = [k for k, c in enumerate(lin.columns) if c == ("base", "bdur_offset_deg")]
        if not j:
            raise ValueError("design_problem: burn_scatter_deg needs the base column bdur_offset_deg")
        u = np.where(lin.ok[:, None], lin.jac[:, oi, j[0]] / sig, 0.0)     # (n, o) sigma per deg
        blocks = whiten_blocks(blocks, np.where(np.isfinite(u), u, 0.0), burn_scatter_deg)
    names = lin.effect_names() if effects is None else [get_effect(e).name for e in effects]
    return DesignProblem(blocks, lin.column_index("base"), {e: lin.column_index(e) for e in names})


def pair_distances(prob: DesignProblem, gram: np.ndarray, ridge: float = 1e-9) -> dict:
    """``d2(i | j)`` for every hypothesis pair at Gram matrix/matrices ``gram`` ((q, q) or (m, q, q)).

    Returns
    -------
    dict {(i, j): float or ndarray (m,)}
    """
    g = np.asarray(gram, dtype=float)
    single = g.ndim == 2
    if single:
        g = g[None]
    q = g.shape[-1]
    scale = np.maximum(np.einsum("mkk->mk", g).mean(axis=1), 1e-30)
    out = {}
    for i, j in prob.hypotheses():
        w = np.zeros(q)
        w[prob.effect_cols[i]] = 1.0                      # s_i = effect i at its realistic magnitude
        ss = np.einsum("q,mqr,r->m", w, g, w)
        m_cols = prob.base_cols + ([] if j is None else prob.effect_cols[j])
        if m_cols:
            gmm = g[:, m_cols][:, :, m_cols] + ridge * scale[:, None, None] * np.eye(len(m_cols))
            b = g[:, m_cols, :] @ w
            proj = np.einsum("mk,mk->m", b, np.linalg.solve(gmm, b[..., None])[..., 0])
            d2 = np.maximum(ss - proj, 0.0)
        else:
            d2 = ss
        out[(i, j)] = float(d2[0]) if single else d2
    return out


def _score(prob: DesignProblem, gram: np.ndarray, criterion: str = "maximin") -> tuple[np.ndarray, np.ndarray]:
    """Two keys to maximise (lexicographically) per Gram matrix in ``gram`` (m, q, q).

    ``"maximin"``: (min d2, -sum 1/d2).  ``"error"``: (-sum Phi(-d/2), min d2), the union bound of the
    pairwise misnaming probabilities (Bayes error of two equiprobable Gaussian hypotheses a Mahalanobis
    distance d apart is Phi(-d/2)).
    """
    from scipy.special import ndtr

    d = np.stack(list(pair_distances(prob, gram).values()), axis=1)      # (m, pairs)
    if criterion == "maximin":
        return d.min(axis=1), -(1.0 / np.maximum(d, 1e-12)).sum(axis=1)
    if criterion == "error":
        return -ndtr(-0.5 * np.sqrt(d)).sum(axis=1), d.min(axis=1)
    raise ValueError(f"design criterion {criterion!r} unknown; valid: {list(CRITERIA)}")


#: Selection criteria of :func:`select_discriminating`.
CRITERIA = ("maximin", "error")


def _better(k1, k2, b1, b2, rel=1e-9) -> np.ndarray:
    tol1 = rel * abs(b1) + 1e-15
    return (k1 > b1 + tol1) | ((k1 >= b1 - tol1) & (k2 > b2 + rel * abs(b2) + 1e-15))


def _check_coverage(coverage: list, n: int, chosen: list, n_points: int) -> None:
    """Refuse, before any selection, a coverage the candidates or the number of points cannot meet."""
    for c in coverage:
        if c.n != n:
            raise ValueError(f"select_discriminating: coverage {c.name} has {c.n} values, the candidates {n}")
        if not np.isfinite(c.deficit(chosen)):
            a, b = c.uncoverable_gap() or (c.low, c.high)
            raise ValueError(f"select_discriminating: no candidate between {c.name} {a:g} and {b:g} "
                             f"(a gap wider than the limit {c.max_gap:g}); add candidates there or widen the limit")
    need = len(chosen) + sum(int(c.deficit(chosen)) for c in coverage)
    if need > n_points:
        axes = "; ".join(f"{c.name} {c.low:g}-{c.high:g} with gaps <= {c.max_gap:g}" for c in coverage)
        raise ValueError(f"select_discriminating: covering {axes} needs at least {need} points of these "
                         f"candidates, n_points = {n_points}; ask for {need} points or widen the limit")


def select_discriminating(prob: DesignProblem, n_points: int, start: Sequence[int] | None = None,
                          exchange_passes: int = 3, criterion: str = "error",
                          coverage: Sequence[AxisCoverage] = ()) -> tuple[np.ndarray, dict]:
    """Indices of ``n_points`` distinct candidate points maximising the smallest ``d2(i | j)``.

    Greedy forward selection (from ``start``, default empty), then up to ``exchange_passes`` passes in which
    every chosen point is swapped for the unchosen candidate that improves the criterion most, if any.
    ``criterion`` (:data:`CRITERIA`): ``"maximin"`` maximises the smallest ``d2`` (ties broken by the smaller
    sum of ``1/d2``); ``"error"`` minimises the sum over pairs of ``Phi(-sqrt(d2)/2)``.

    ``coverage`` (:class:`engine_model.gap.coverage.AxisCoverage`, one per axis, values per candidate):
    a greedy step may only take a candidate after which the remaining steps can still close every gap
    wider than the axis' limit (the sum of the axes' :meth:`~AxisCoverage.deficit` at most the points left),
    and an exchange may only make a swap after which every axis is still covered.  So the plan returned
    covers every axis, and among such plans the criterion still chooses.

    Raises
    ------
    ValueError
        ``n_points`` too few to cover the axes with these candidates (the message names the minimum), or
        a stretch of an axis no candidate can bridge.

    Returns
    -------
    idx : ndarray of int
    info : dict
        ``min_d2`` (criterion), ``pairs`` ({(i, j): d2}), ``closest`` (the pair attaining the minimum),
        ``swaps`` (exchange moves made).
    """
    n_points = int(n_points)
    if not 1 <= n_points <= prob.n:
        raise ValueError(f"select_discriminating: n_points = {n_points} must be within 1..{prob.n} (the candidates)")
    chosen = [] if start is None else [int(i) for i in start]
    if len(set(chosen)) != len(chosen) or any(not 0 <= i < prob.n for i in chosen) or len(chosen) > n_points:
        raise ValueError(f"select_discriminating: start {chosen} must be distinct candidate indices, at most n_points")
    coverage = list(coverage)
    _check_coverage(coverage, prob.n, chosen, n_points)
    deficit = lambda sel: sum(c.deficit(sel) for c in coverage)
    gsum = prob.gram[chosen].sum(axis=0) if chosen else np.zeros(prob.gram.shape[1:])
    while len(chosen) < n_points:
        free = np.setdiff1d(np.arange(prob.n), chosen)
        left = n_points - len(chosen) - 1            # points still to choose after this one
        if coverage and deficit(chosen) > left:      # tight: only a candidate that closes a gap will do
            free = free[np.array([deficit(chosen + [int(k)]) <= left for k in free])]
        k1, k2 = _score(prob, gsum[None] + prob.gram[free], criterion)
        order = np.lexsort((-k2, -k1))          # largest first key, then largest second key
        k = int(free[order[0]])
        chosen.append(k)
        gsum = gsum + prob.gram[k]
    swaps = 0
    for _ in range(max(0, exchange_passes)):
        moved = False
        for pos in range(len(chosen)):
            c1, c2 = _score(prob, gsum[None], criterion)
            free = np.setdiff1d(np.arange(prob.n), chosen)
            g_wo = gsum - prob.gram[chosen[pos]]
            k1, k2 = _score(prob, g_wo[None] + prob.gram[free], criterion)
            good = _better(k1, k2, c1[0], c2[0])
            rest = chosen[:pos] + chosen[pos + 1:]
            if coverage and good.any() and not all(c.holds(rest) for c in coverage):
                good &= np.array([all(c.holds(rest + [int(k)]) for c in coverage) for k in free])
            if good.any():
                cand = np.flatnonzero(good)
                best = cand[np.lexsort((-k2[cand], -k1[cand]))[0]]
                k = int(free[best])
                gsum = g_wo + prob.gram[k]
                chosen[pos] = k
                swaps += 1
                moved = True
        if not moved:
            break
    pairs = pair_distances(prob, gsum)
    closest = min(pairs, key=pairs.get)
    from scipy.special import ndtr

    err = float(sum(ndtr(-0.5 * np.sqrt(v)) for v in pairs.values()))
    return np.array(chosen, dtype=int), {"min_d2": float(pairs[closest]), "pairs": pairs, "closest": closest,
                                         "swaps": swaps, "error_bound": err, "criterion": criterion}


def candidate_pool(n: int = 160, seed: int = 0, spec: EngineSpec | None = None, evaluate: Callable | None = None,
                   speed_rpm: tuple[float, float] = (5000.0, 12500.0), throttle_pct: tuple[float, float] = (30.0, 100.0),
                   spark_below_mbt: tuple[float, float] = (0.0, 8.0), knock_target: float = 0.85,
                   retards: Sequence[float] = (0.0, 4.0, 8.0, 12.0, 16.0),
                   max_speed_gap_rpm: float | None = MAX_SPEED_GAP_RPM, per_band: int = 2) -> pd.DataFrame:
    """Candidate bench points: Sobol' over speed x throttle, spark ``spark_below_mbt`` below the MBT prior,
    retarded in 4 deg steps where the model (prior burn) predicts knock (as :func:`benchmark_plan`).

    With ``max_speed_gap_rpm`` [rpm], the speed range is cut into bands of at most half that width and every
    band holding fewer than ``per_band`` Sobol' points gets Sobol' points of its own (speed within the band,
    throttle over ``throttle_pct``), so a plan drawn from the pool can cover the range at that limit even if
    a point per band fails to converge.  The 160-point default pool needs none (>= 8 per 500 rpm band).
    """

    spec = default_spec() if spec is None else spec
    if evaluate is None:
        raise ValueError("candidate_pool: an evaluate(plan) callable is needed for the knock back-off")
    pool = doe.sobol(n, bounds={"speed_rpm": speed_rpm, "throttle_pct": throttle_pct}, seed=seed)
    if max_speed_gap_rpm is not None:
        nb = 2 * int(np.ceil((speed_rpm[1] - speed_rpm[0]) / max_speed_gap_rpm))
        edges = np.linspace(speed_rpm[0], speed_rpm[1], nb + 1)
        have = np.histogram(pool["speed_rpm"].to_numpy(float), edges)[0]
        extra = [doe.sobol(per_band - int(h), bounds={"speed_rpm": (edges[b], edges[b + 1]),
                                                      "throttle_pct": throttle_pct}, seed=seed + 1 + b)
                 for b, h in enumerate(have) if h < per_band]
        pool = pd.concat([pool] + extra, ignore_index=True)
    rng = np.random.default_rng(seed + 17)
    spark0 = pool["spark_deg_btdc"].to_numpy(float) - rng.uniform(*spark_below_mbt, len(pool))
    chosen = knock_backoff(pool.assign(spark_deg_btdc=spark0), spark0, evaluate, knock_target, retards)
    pool["spark_deg_btdc"] = np.round(spark0 - chosen, 1)
    pool["knock_retard_deg"] = chosen
    pool["point_id"] = [f"disc-{i:04d}" for i in range(len(pool))]
    pool["op_id"] = pool["point_id"]
    return pool


def discrimination_plan(n_points: int = 32, spec: EngineSpec | None = None, evaluate: Callable | None = None,
                        candidates: pd.DataFrame | None = None, n_candidates: int = 160, seed: int = 0,
                        effects: Sequence[str] | None = None, base: BaseModel = BaseModel(params=SWEEP_BASE),
                        candidate_lin: Linearisation | None = None,
                        outputs: Sequence[str] = DESIGN_OUTPUTS, criterion: str = "error",
                        burn_scatter_deg: float = BURN_SCATTER_DEG,
                        speed_rpm: tuple[float, float] | None = None,
                        max_speed_gap_rpm: float | None = MAX_SPEED_GAP_RPM,
                        throttle_pct: tuple[float, float] | None = None,
                        max_throttle_gap_pct: float | None = None,
                        compare_free: bool = True) -> tuple[pd.DataFrame, dict]:
    """Propose ``n_points`` bench points that tell the library's effects apart (before any bench run).

    Parameters
    ----------
    n_points : int
        Points to run on the bench.
    evaluate : callable(plan) -> results
        Simulator (``simulate`` contract); one knock check of the pool and one linearisation batch
        (``len(pool) * (1 + base + simulated effect params)`` simulations).
    candidates : DataFrame, optional
        Candidate pool (plan columns); default :func:`candidate_pool` (``n_candidates`` points over
        ``speed_rpm`` x ``throttle_pct``).
    effects : sequence of str, optional
        Hypotheses to separate (default: the whole library).
    base : BaseModel
        Base parameters projected out (default with the burn's spark slope: the more conservative
        projection; the diagnosis may use fewer).
    candidate_lin : Linearisation, optional
        A linearisation of ``candidates`` already made (skips the simulations).
    criterion : str
        See :func:`select_discriminating`.
    burn_scatter_deg : float
        See :func:`design_problem` and :data:`engine_model.gap.covariance.BURN_SCATTER_DEG`.
    speed_rpm : (float, float), optional
        Speed range [rpm] of the pool and of the coverage; default 5000-12500 rpm for a pool made here,
        the candidates' own range for ``candidates``.
    max_speed_gap_rpm : float or None
        Largest gap [rpm] between neighbouring planned speeds, and between the range's ends and the
        nearest planned speed (:data:`engine_model.gap.coverage.MAX_SPEED_GAP_RPM`); None: no constraint.
    throttle_pct : (float, float), optional
        Throttle range [%] of the pool and of the throttle coverage; default 30-100 % / the candidates' range.
    max_throttle_gap_pct : float or None
        Largest throttle gap [%-points] over the whole plan; None (default): reported, not constrained.
    compare_free : bool
        Also select without the coverage constraints, to report what the coverage costs in criterion
        (``info['free']``); a second selection on the same linearisation, no simulations.

    Raises
    ------
    ValueError
        ``n_points`` below what the coverage needs (:func:`engine_model.gap.coverage.min_points_to_cover`
        before any simulation; the pool's own minimum after the linearisation), naming the minimum.

    Returns
    -------
    plan : DataFrame
        The chosen rows of the pool (``design = 'discriminating'``).
    info : dict
        ``min_d2`` and ``closest`` pair, ``pairs``, ``error_bound``, ``coverage``
        (:func:`engine_model.gap.coverage.coverage_summary`: largest speed gap, speed and throttle covered,
        throttle range per speed band, single-point bands), ``free`` (``min_d2``, ``error_bound``,
        ``closest``, ``coverage`` of the unconstrained plan, if ``compare_free``), the pool, its
        linearisation and its simulations.
    """
    from engine_model.sim.simulate import simulate

    spec = default_spec() if spec is None else spec
    if candidates is not None:
        sp0, th0 = candidates["speed_rpm"].astype(float), candidates["throttle_pct"].astype(float)
        speed_rpm = (float(sp0.min()), float(sp0.max())) if speed_rpm is None else speed_rpm
        throttle_pct = (float(th0.min()), float(th0.max())) if throttle_pct is None else throttle_pct
    speed_rpm = (5000.0, 12500.0) if speed_rpm is None else (float(speed_rpm[0]), float(speed_rpm[1]))
    throttle_pct = (30.0, 100.0) if throttle_pct is None else (float(throttle_pct[0]), float(throttle_pct[1]))
    axes = [(c, r, g) for c, r, g in (("speed_rpm", speed_rpm, max_speed_gap_rpm),
                                      ("throttle_pct", throttle_pct, max_throttle_gap_pct)) if g is not None]
    need = sum(min_points_to_cover(r[0], r[1], g) for _, r, g in axes)
    if need > n_points:
        raise ValueError(f"discrimination_plan: {n_points} points cannot cover " + "; ".join(
            f"{c} {r[0]:g}-{r[1]:g} with gaps <= {g:g}" for c, r, g in axes) + f": that needs at least {need} "
            "points; ask for more points, a narrower range or a wider gap limit")
    ev = evaluate or (lambda p: simulate(spec, p, BENCH_SOLVER))
    names = list(EFFECTS) if effects is None else [get_effect(e).name for e in effects]
    pool = (candidate_pool(n_candidates, seed, spec, ev, speed_rpm=speed_rpm, throttle_pct=throttle_pct,
                           max_speed_gap_rpm=max_speed_gap_rpm)
            if candidates is None else candidates.reset_index(drop=True))
    lin = candidate_lin if candidate_lin is not None else linearise(pool, ev, base, effects=names, spec=spec)
    if len(lin.points) != len(pool):
        raise ValueError(f"discrimination_plan: candidate_lin has {len(lin.points)} points, the pool {len(pool)}")
    ok = np.flatnonzero(lin.ok)
    if ok.size < n_points:
        raise ValueError(f"discrimination_plan: only {ok.size} of {len(pool)} candidates converged; need {n_points}")
    prob = design_problem(lin.select(list(lin.points["point_id"].iloc[ok])), outputs, names,
                          burn_scatter_deg=burn_scatter_deg)
    cover = [AxisCoverage(c, pool[c].to_numpy(float)[ok], r[0], r[1], g) for c, r, g in axes]
    idx, info = select_discriminating(prob, n_points, criterion=criterion, coverage=cover)
    plan = pool.iloc[ok[idx]].reset_index(drop=True)
    plan["design"] = "discriminating"
    gap_limit = MAX_SPEED_GAP_RPM if max_speed_gap_rpm is None else max_speed_gap_rpm
    info["coverage"] = coverage_summary(plan, speed_rpm, gap_limit, throttle_pct)
    if compare_free and cover:
        fidx, free = select_discriminating(prob, n_points, criterion=criterion)
        info["free"] = {k: free[k] for k in ("min_d2", "error_bound", "closest")}
        info["free"]["coverage"] = coverage_summary(pool.iloc[ok[fidx]], speed_rpm, gap_limit, throttle_pct)
    info.update({"pool": pool, "linearisation": lin, "simulations": lin.n_simulations})
    return plan, info
