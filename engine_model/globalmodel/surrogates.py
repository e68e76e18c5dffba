"""Response-surface families for the global map-wide model (numpy/scipy only).

Two families, both on coded inputs (each factor scaled to -1..1 over the
training range) and one output at a time:

* :class:`PolynomialRSM` -- polynomial response surface up to a given total
  degree with greedy forward term selection by PRESS (the leave-one-out
  prediction error sum of squares, computed exactly from the hat matrix).
* :class:`GaussianProcess` -- GP regression with a linear trend (universal
  kriging light: the trend is fitted by least squares first, the GP models the
  residual), an anisotropic Matern-5/2 kernel, a fitted noise variance, and
  per-point noise from given uncertainties; hyperparameters by maximum
  marginal likelihood (L-BFGS-B, several starts).

Both follow scikit-learn's habit: settings in ``__init__``, ``fit`` returns
self, learned state ends in ``_``; ``predict(x) -> (mean, std)`` where std is
the standard deviation of the predicted *mean* (model uncertainty, without
the measurement noise).  ``to_dict`` / ``from_dict`` give a JSON-able form.

References
----------
.. [MM] D.C. Montgomery, Design and Analysis of Experiments, Wiley, ch. 11
   (response surfaces; PRESS statistic).
.. [RW] C.E. Rasmussen, C.K.I. Williams, Gaussian Processes for Machine
   Learning, MIT Press 2006, alg. 2.1 (prediction via Cholesky), eq. 4.17
   (Matern 5/2), sec. 5.4 (marginal likelihood).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

__all__ = ["PolynomialRSM", "GaussianProcess", "monomials", "FAMILIES", "make_family"]


def monomials(n_factors: int, max_degree: int) -> list[tuple[int, ...]]:
    """All exponent tuples of total degree 0..max_degree (intercept first), by degree then lexically."""
    out = []
    for deg in range(max_degree + 1):
        for combo in itertools.combinations_with_replacement(range(n_factors), deg):
            e = [0] * n_factors
            for i in combo:
                e[i] += 1
            out.append(tuple(e))
    return out


def _design(x: np.ndarray, terms) -> np.ndarray:
    x = np.atleast_2d(x)
    cols = [np.prod(x ** np.asarray(t, dtype=float), axis=1) for t in terms]
    return np.column_stack(cols)


def _press(f: np.ndarray, y: np.ndarray) -> float:
    """PRESS = sum (e_i / (1 - h_ii))^2 of a least-squares fit (inf if rank-deficient or h_ii ~ 1)."""
    q, r = np.linalg.qr(f)
    d = np.abs(np.diag(r))
    if d.size == 0 or d.min() < 1e-10 * max(d.max(), 1e-300):
        return math.inf
    h = np.einsum("ij,ij->i", q, q)
    if np.any(h > 1 - 1e-8):
        return math.inf
    e = y - q @ (q.T @ y)
    return float(np.sum((e / (1.0 - h)) ** 2))


class PolynomialRSM:
    """Polynomial response surface with greedy forward term selection by PRESS.

    Parameters
    ----------
    max_degree : int
        Highest total degree of a candidate term (3: cubic, 35 candidates in
        4 factors).
    max_terms : int or None
        Cap on the number of terms; default ``n_points // 2``.
    min_gain : float
        Stop when the best candidate lowers PRESS by less than this fraction.

    Notes
    -----
    Start with the intercept; at each step add the candidate term whose model
    has the lowest PRESS; stop at ``max_terms``, ``n - 2`` terms, or when the
    relative gain drops below ``min_gain``.  PRESS is the leave-one-out error
    of each candidate model, computed exactly as sum (e_i / (1 - h_ii))^2
    [MM], so the selection is a cross-validation without refits.
    """

    family = "poly"

    def __init__(self, *, max_degree: int = 3, max_terms: int | None = None, min_gain: float = 0.01):
        self.max_degree = max_degree
        self.max_terms = max_terms
        self.min_gain = min_gain

    def fit(self, x: np.ndarray, y: np.ndarray, y_std: np.ndarray | None = None) -> "PolynomialRSM":
        """Fit on coded inputs ``x`` (n, d) and output ``y`` (n,); ``y_std`` is not used (OLS)."""
        x = np.atleast_2d(np.asarray(x, float))
        y = np.asarray(y, float)
        n, d = x.shape
        cand = monomials(d, self.max_degree)
        fall = _design(x, cand)
        cap = min(self.max_terms or n // 2, n - 2, len(cand))
        chosen = [0]
        best = _press(fall[:, chosen], y)
        while len(chosen) < cap:
            trial = [(j, _press(fall[:, chosen + [j]], y)) for j in range(len(cand)) if j not in chosen]
            j, val = min(trial, key=lambda t: t[1])
            if not (val < best * (1.0 - self.min_gain)):
                break
            chosen.append(j)
            best = val
        self.terms_ = [cand[j] for j in chosen]
        f = fall[:, chosen]
        coef, *_ = np.linalg.lstsq(f, y, rcond=None)
        resid = y - f @ coef
        dof = max(n - len(chosen), 1)
        self.coef_ = coef
        self.sigma2_ = float(resid @ resid / dof)
        self.cov_unscaled_ = np.linalg.pinv(f.T @ f)
        self.press_rmse_ = math.sqrt(best / n)
        return self

    def noise_variance(self) -> float:
        """Estimated variance of one observation about the surface (residual mean square)."""
        return self.sigma2_

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std of the mean at coded inputs ``x`` (m, d)."""
        f = _design(np.asarray(x, float), self.terms_)
        var = self.sigma2_ * np.einsum("ij,jk,ik->i", f, self.cov_unscaled_, f)
        return f @ self.coef_, np.sqrt(np.maximum(var, 0.0))

    def to_dict(self) -> dict:
        return {"family": self.family, "max_degree": self.max_degree, "max_terms": self.max_terms,
                "min_gain": self.min_gain, "terms": [list(t) for t in self.terms_],
                "coef": self.coef_.tolist(), "sigma2": self.sigma2_,
                "cov_unscaled": self.cov_unscaled_.tolist(), "press_rmse": self.press_rmse_}

    @classmethod
    def from_dict(cls, d: dict) -> "PolynomialRSM":
        obj = cls(max_degree=d["max_degree"], max_terms=d["max_terms"], min_gain=d["min_gain"])
        obj.terms_ = [tuple(t) for t in d["terms"]]
        obj.coef_ = np.asarray(d["coef"], float)
        obj.sigma2_ = float(d["sigma2"])
        obj.cov_unscaled_ = np.asarray(d["cov_unscaled"], float)
        obj.press_rmse_ = float(d["press_rmse"])
        return obj


def _matern52(x1: np.ndarray, x2: np.ndarray, ell: np.ndarray) -> np.ndarray:
    diff = (x1[:, None, :] - x2[None, :, :]) / ell
    r = np.sqrt(np.sum(diff * diff, axis=-1)) * math.sqrt(5.0)
    return (1.0 + r + r * r / 3.0) * np.exp(-r)


class GaussianProcess:
    """GP regression: linear trend + anisotropic Matern-5/2 residual, noise fitted.

    Parameters
    ----------
    n_restarts : int
        Starting points of the likelihood optimisation (the first is a fixed
        default, the others drawn with ``seed``).
    seed : int
        Seed of the restarts.
    min_noise : float
        Lower bound of the noise variance, as a fraction of the residual
        variance (jitter that keeps the Cholesky factor well conditioned).

    Notes
    -----
    ``y = b0 + b'x + g(x) + e``; b by least squares, then g ~ GP(0, s2 k(x, x'))
    with Matern-5/2 k over length scales l_1..l_d (in coded units) and
    e ~ N(0, s_n^2 + y_std_i^2).  log(s2, l, s_n^2) maximise the log marginal
    likelihood of the residual [RW sec. 5.4].  Prediction: mean
    ``trend + k*' K^-1 r``, variance ``s2 - k*' K^-1 k*`` [RW alg. 2.1]
    (the uncertainty of the trend coefficients is neglected).
    """

    family = "gp"

    def __init__(self, *, n_restarts: int = 3, seed: int = 0, min_noise: float = 1e-6):
        self.n_restarts = n_restarts
        self.seed = seed
        self.min_noise = min_noise

    @staticmethod
    def _trend_matrix(x):
        return np.column_stack([np.ones(len(x)), x])

    def _nll(self, theta, x, r, extra, sq):
        """Negative log marginal likelihood and its gradient w.r.t. log(s2, l_1..l_d, s_n^2) [RW eq. 5.9]."""
        from scipy import linalg
        s2, ell, sn2 = math.exp(theta[0]), np.exp(theta[1:-1]), math.exp(theta[-1])
        u = sq / ell**2                                   # (n, n, d) squared scaled differences
        rr = np.sqrt(5.0 * np.sum(u, axis=-1))            # sqrt(5) r
        e = np.exp(-rr)
        kbase = (1.0 + rr + rr * rr / 3.0) * e
        k = s2 * kbase
        k[np.diag_indices_from(k)] += sn2 + extra
        try:
            c = linalg.cho_factor(k, lower=True, check_finite=False)
        except linalg.LinAlgError:
            return 1e25, np.zeros_like(theta)
        a = linalg.cho_solve(c, r, check_finite=False)
        nll = float(0.5 * r @ a + np.sum(np.log(np.diag(c[0]))) + 0.5 * len(r) * math.log(2 * math.pi))
        w = linalg.cho_solve(c, np.eye(len(r)), check_finite=False) - np.outer(a, a)  # K^-1 - a a'
        g = np.empty_like(theta)
        g[0] = 0.5 * np.sum(w * (k - np.diag(np.full(len(r), sn2) + extra)))
        # dk/dlog(l_d) = s2 (5/3) (1 + sqrt5 r) exp(-sqrt5 r) (dx_d / l_d)^2
        common = s2 * (5.0 / 3.0) * (1.0 + rr) * e
        for j in range(len(ell)):
            g[1 + j] = 0.5 * np.sum(w * (common * u[:, :, j]))
        g[-1] = 0.5 * sn2 * np.trace(w)
        return nll, g

    def fit(self, x: np.ndarray, y: np.ndarray, y_std: np.ndarray | None = None) -> "GaussianProcess":
        """Fit on coded inputs ``x`` (n, d), output ``y`` (n,), optional per-point noise std ``y_std`` (n,)."""
        from scipy import linalg, optimize  # late import: scipy.optimize costs ~1 s at package import
        x = np.atleast_2d(np.asarray(x, float))
        y = np.asarray(y, float)
        n, d = x.shape
        t = self._trend_matrix(x)
        self.trend_, *_ = np.linalg.lstsq(t, y, rcond=None)
        r = y - t @ self.trend_
        scale = float(np.std(r)) or 1.0
        rs = r / scale
        extra = np.zeros(n) if y_std is None else (np.asarray(y_std, float) / scale) ** 2
        extra = np.where(np.isfinite(extra), extra, 0.0)
        lo = np.r_[math.log(1e-2), np.full(d, math.log(0.05)), math.log(self.min_noise)]
        hi = np.r_[math.log(1e2), np.full(d, math.log(20.0)), math.log(1.0)]
        rng = np.random.default_rng(self.seed)
        starts = [np.r_[0.0, np.full(d, math.log(0.7)), math.log(1e-2)]]
        starts += [rng.uniform(lo, hi) for _ in range(max(self.n_restarts - 1, 0))]
        sq = (x[:, None, :] - x[None, :, :]) ** 2
        best = None
        for s in starts:
            res = optimize.minimize(self._nll, s, args=(x, rs, extra, sq), method="L-BFGS-B", jac=True,
                                    bounds=list(zip(lo, hi)), options={"maxiter": 200})
            if best is None or res.fun < best.fun:
                best = res
        th = best.x
        self.signal_var_ = math.exp(th[0]) * scale**2
        self.length_scales_ = np.exp(th[1:-1])
        self.noise_var_ = math.exp(th[-1]) * scale**2
        self.x_train_ = x
        k = self.signal_var_ * _matern52(x, x, self.length_scales_)
        k[np.diag_indices_from(k)] += self.noise_var_ + extra * scale**2
        self.chol_ = linalg.cholesky(k, lower=True)
        self.alpha_ = linalg.cho_solve((self.chol_, True), r)
        self.nll_ = float(best.fun)
        return self

    def noise_variance(self) -> float:
        """Fitted homoscedastic noise variance (without the per-point ``y_std`` part)."""
        return self.noise_var_

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std of the latent mean function at coded inputs ``x`` (m, d)."""
        from scipy import linalg
        x = np.atleast_2d(np.asarray(x, float))
        ks = self.signal_var_ * _matern52(x, self.x_train_, self.length_scales_)
        mean = self._trend_matrix(x) @ self.trend_ + ks @ self.alpha_
        v = linalg.solve_triangular(self.chol_, ks.T, lower=True)
        var = self.signal_var_ - np.sum(v * v, axis=0)
        return mean, np.sqrt(np.maximum(var, 0.0))

    def to_dict(self) -> dict:
        return {"family": self.family, "n_restarts": self.n_restarts, "seed": self.seed,
                "min_noise": self.min_noise, "trend": self.trend_.tolist(),
                "signal_var": self.signal_var_, "length_scales": self.length_scales_.tolist(),
                "noise_var": self.noise_var_, "x_train": self.x_train_.tolist(),
                "chol": self.chol_.tolist(), "alpha": self.alpha_.tolist(), "nll": self.nll_}

    @classmethod
    def from_dict(cls, d: dict) -> "GaussianProcess":
        obj = cls(n_restarts=d["n_restarts"], seed=d["seed"], min_noise=d["min_noise"])
        obj.trend_ = np.asarray(d["trend"], float)
        obj.signal_var_ = float(d["signal_var"])
        obj.length_scales_ = np.asarray(d["length_scales"], float)
        obj.noise_var_ = float(d["noise_var"])
        obj.x_train_ = np.asarray(d["x_train"], float)
        obj.chol_ = np.asarray(d["chol"], float)
        obj.alpha_ = np.asarray(d["alpha"], float)
        obj.nll_ = float(d["nll"])
        return obj


#: Model families by name.
FAMILIES = {"poly": PolynomialRSM, "gp": GaussianProcess}


def make_family(name: str, seed: int = 0):
    """A fresh, unfitted estimator of family ``name`` ('poly' or 'gp')."""
    if name not in FAMILIES:
        raise ValueError(f"unknown model family {name!r}; choose from {sorted(FAMILIES)}")
    return GaussianProcess(seed=seed) if name == "gp" else PolynomialRSM()
