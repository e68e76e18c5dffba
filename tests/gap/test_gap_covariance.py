"""Burn-scatter covariance of the gap diagnosis: the whitening is exact GLS, and burn scatter is not an effect."""

import numpy as np
import pandas as pd
import pytest

from engine_model.gap.covariance import (BURN_SCATTER_DEG, ERROR_MODELS, HELDOUT_ERROR_FACTOR, MODEL_ERROR, ErrorModel,
                                        burn_whitener, get_error_model, whiten_blocks, whiten_observations)
from engine_model.gap.diagnose import diagnose
from engine_model.gap.residuals import UNCERTAINTY

from test_gap_diagnose import OUTS, _delta, _synthetic


def test_whitener_inverts_the_covariance():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(7, 4))
    u[3] = 0.0                                   # a point the burn does not move: identity
    w = burn_whitener(u, 0.4)
    for i in range(7):
        c = np.eye(4) + 0.16 * np.outer(u[i], u[i])
        np.testing.assert_allclose(w[i] @ c @ w[i].T, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(w[i], w[i].T, atol=1e-15)
    np.testing.assert_array_equal(w[3], np.eye(4))
    np.testing.assert_array_equal(burn_whitener(u, 0.0), np.broadcast_to(np.eye(4), (7, 4, 4)))
    with pytest.raises(ValueError, match="tau"):
        burn_whitener(u, -0.1)


def test_whitened_least_squares_equals_a_dense_gls_solve():
    """Per-point block whitening of readings and columns gives the GLS estimate with the full covariance,
    also when some readings are missing (they neither carry nor receive burn scatter)."""
    rng = np.random.default_rng(1)
    n, o, q, tau = 9, 3, 4, 0.5
    u = rng.normal(size=(n, o))
    present = rng.random((n, o)) > 0.2
    pidx, oidx = np.nonzero(present)
    a = rng.normal(size=(pidx.size, q))
    r = rng.normal(size=pidx.size)
    # dense covariance over the observations present
    cov = np.eye(pidx.size) + tau**2 * (pidx[:, None] == pidx[None, :]) * np.outer(u[pidx, oidx], u[pidx, oidx])
    ci = np.linalg.inv(cov)
    x_dense = np.linalg.solve(a.T @ ci @ a, a.T @ ci @ r)
    aw = whiten_observations(a, pidx, oidx, u, tau)
    rw = whiten_observations(r, pidx, oidx, u, tau)
    x_white = np.linalg.lstsq(aw, rw, rcond=None)[0]
    np.testing.assert_allclose(x_white, x_dense, rtol=1e-10)
    # the GLS chi2 is the whitened sum of squares
    res = r - a @ x_dense
    np.testing.assert_allclose(res @ ci @ res, np.sum((rw - aw @ x_white) ** 2), rtol=1e-10)


def test_whiten_blocks_matches_cholesky_gram():
    """Same Gram matrix as the lower Cholesky whitening the design used before (any square root will do)."""
    rng = np.random.default_rng(2)
    u = rng.normal(size=(5, 4))
    b = rng.normal(size=(5, 4, 6))
    cov = np.eye(4)[None] + 0.09 * np.einsum("no,np->nop", u, u)
    bc = np.linalg.solve(np.linalg.cholesky(cov), b)
    bw = whiten_blocks(b, u, 0.3)
    np.testing.assert_allclose(np.einsum("noq,nor->nqr", bw, bw), np.einsum("noq,nor->nqr", bc, bc), rtol=1e-10)


def _burn_scatter_measure(lin, tau_true, seed, effect=None):
    """Readings with ``effect`` at its realistic magnitude (None: base only), a per-point burn deviation
    (N(0, tau_true) deg along each point's BDUR10-90 sensitivity) and measurement noise."""
    rng = np.random.default_rng(seed)
    j = lin.columns.index(("base", "bdur_offset_deg"))
    dev = rng.normal(0.0, tau_true, len(lin.points))
    y = lin.predict(_delta(lin, effect)) + lin.jac[:, :, j] * dev[:, None]
    sig = np.column_stack([UNCERTAINTY[o][1] * np.abs(y[:, k]) if UNCERTAINTY[o][0] == "rel"
                           else np.full(len(y), UNCERTAINTY[o][1]) for k, o in enumerate(OUTS)])
    y = y + sig * rng.standard_normal(y.shape)
    return pd.DataFrame({"point_id": lin.points["point_id"], **{o: y[:, k] for k, o in enumerate(OUTS)}})


#: Measurement noise only, with and without 1 deg of per-point burn scatter in the covariance.
_WHITE = ErrorModel("white", {}, 0.0, None)
_BURN = ErrorModel("burn", {}, 1.0, None)


@pytest.mark.slow
def test_noise_quantile_covers_burn_scatter_only_with_its_covariance():
    """Data = base + 1 deg per-point burn scatter (0.75 % torque, 6 K per point, more than the noise) + noise.
    The pure-noise Monte Carlo of the burn-scatter model draws that covariance, so the base's held-out chi2
    stays below its 99 % quantile; a white-noise model sees a significant gap in most trials."""
    lin = _synthetic(n=24, seed=3)
    over_white = over_burn = 0
    for seed in range(12):
        m = _burn_scatter_measure(lin, 1.0, seed)
        dw = diagnose(lin, m, n_noise=100, seed=0, error_model=_WHITE)
        db = diagnose(lin, m, n_noise=100, seed=0, error_model=_BURN)
        over_white += dw.extra["heldout_chi2_base"] > dw.noise_chi2_q
        over_burn += db.extra["heldout_chi2_base"] > db.noise_chi2_q
        assert db.named is None, (seed, db.named)           # burn scatter alone is not an effect
        assert db.extra["error_model"] == "burn"
    assert over_white >= 9, over_white
    assert over_burn <= 1, over_burn


def test_planted_effect_is_named_through_burn_scatter():
    lin = _synthetic(n=24, seed=3)
    for effect in ("friction", "restrictor"):      # (transmission vs heat transfer: near-degenerate in this toy)
        named = [diagnose(lin, _burn_scatter_measure(lin, 1.0, s, effect), n_noise=100, seed=0,
                          error_model=_BURN).named for s in range(3)]
        assert named.count(effect) >= 2, (effect, named)


def test_error_models_and_their_errors():
    assert set(ERROR_MODELS) == {"diagonal", "burn_scatter"}
    # the diagnosis carries the in-sample scatter times the factor measured on the held-out statistic
    assert get_error_model("burn_scatter").burn_scatter_deg == pytest.approx(BURN_SCATTER_DEG * HELDOUT_ERROR_FACTOR)
    assert get_error_model("diagonal").model_error is MODEL_ERROR
    with pytest.raises(ValueError, match=r"error model 'gls' unknown; valid: \['burn_scatter', 'diagonal'\]"):
        get_error_model("gls")
    with pytest.raises(ValueError, match="burn_scatter_deg"):
        ErrorModel("bad", {}, -0.1)


def test_burn_scatter_needs_the_burn_column():
    lin = _synthetic()
    lin.columns = [("base", "other") if c == ("base", "bdur_offset_deg") else c for c in lin.columns]
    from test_gap_diagnose import _measure

    with pytest.raises(ValueError, match="bdur_offset_deg"):
        diagnose(lin, _measure(lin, np.zeros(len(lin.columns)), 0), error_model="burn_scatter")
