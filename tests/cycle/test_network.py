"""Closed-form linearly implicit flow solves of the cycle kernel against a dense solve of the same system."""

import numpy as np
import pytest

from engine_model.cycle import network as nw
from engine_model.cycle import volumes as vo


def _props(rng, nvol):
    """Random but physical gas states for nvol volumes plus two fixed-pressure pseudo-volumes."""
    props = np.zeros((nvol + 2, vo.NPR))
    vols = rng.uniform(2e-5, 3e-3, nvol + 2)
    for k in range(nvol + 2):
        g, r, t = rng.uniform(1.25, 1.4), rng.uniform(280.0, 300.0), rng.uniform(300.0, 2500.0)
        props[k, vo.PR_P] = rng.uniform(0.4e5, 4e5)
        props[k, vo.PR_T], props[k, vo.PR_R], props[k, vo.PR_G] = t, r, g
        props[k, vo.PR_GV] = g / vols[k] if k < nvol else 0.0
        props[k, vo.PR_RT] = r * t
    return props, vols


def _dense(elements, E, props, vols, rate, nvol, dt):
    """Flows from the pressure-change form: unknown dP of every volume, m_e = m0 + a dP_i - b dP_j."""
    n = nvol
    M = np.eye(n)
    rhs = dt * rate[:n].copy()
    for e in elements:
        i, j, u = int(E[e, 0]), int(E[e, 1]), int(E[e, 5])
        m0, a, b = E[e, 2], E[e, 3], E[e, 4]
        for node, sgn in ((i, -1.0), (j, 1.0)):
            if node >= nvol:
                continue
            c = sgn * dt * props[node, vo.PR_G] * props[u, vo.PR_R] * props[u, vo.PR_T] / vols[node]
            rhs[node] += c * m0
            if i < nvol:
                M[node, i] -= c * a
            if j < nvol:
                M[node, j] += c * b
    dp = np.linalg.solve(M, rhs)
    out = {}
    for e in elements:
        i, j = int(E[e, 0]), int(E[e, 1])
        out[e] = E[e, 2] + (E[e, 3] * dp[i] if i < nvol else 0.0) - (E[e, 4] * dp[j] if j < nvol else 0.0)
    return out


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("dt", [1e-6, 1e-5, 1e-4])
def test_two_elements_in_series_match_the_dense_solve(seed, dt):
    """Volumes 0 -> 1 -> 2 (port, cylinder, port) and ambient -> 0 -> 1 (throttle, restrictor) shapes."""
    rng = np.random.default_rng(seed)
    nvol = 3
    props, vols = _props(rng, nvol)
    rate = np.concatenate([rng.normal(0.0, 3e7, nvol), [0.0, 0.0]])
    for i1, s, j2 in ((0, 1, 2), (nvol, 0, 1), (1, 2, nvol + 1)):
        E = np.zeros((2, 7))
        nw.lin_between(i1, s, rng.uniform(1e-5, 5e-4), 0.0, props, 1e-4, E, 0)
        nw.lin_between(s, j2, rng.uniform(1e-5, 5e-4), 0.0, props, 1e-4, E, 1)
        ref = _dense((0, 1), E, props, vols, rate, nvol, dt)
        nw.solve_two(0, 1, E, props, rate, nvol, dt)
        for e in (0, 1):
            assert E[e, 6] == pytest.approx(ref[e], rel=1e-9, abs=1e-12 * abs(E[e, 2]) + 1e-15)


@pytest.mark.parametrize("seed", range(5))
def test_single_element_matches_the_dense_solve(seed):
    rng = np.random.default_rng(100 + seed)
    nvol = 2
    props, vols = _props(rng, nvol)
    rate = np.concatenate([rng.normal(0.0, 3e7, nvol), [0.0, 0.0]])
    for i, j in ((0, 1), (1, 0), (0, nvol + 1), (nvol, 1)):
        E = np.zeros((1, 7))
        nw.lin_between(i, j, rng.uniform(1e-5, 5e-4), 0.0, props, 1e-4, E, 0)
        ref = _dense((0,), E, props, vols, rate, nvol, 1e-5)
        nw.solve_one(0, E, props, rate, nvol, 1e-5)
        assert E[0, 6] == pytest.approx(ref[0], rel=1e-9, abs=1e-15)


def test_stiff_flow_follows_the_demand():
    """Tiny downstream volume, huge step: the implicit flow carries what the rate demands, no overshoot."""
    rng = np.random.default_rng(3)
    nvol = 2
    props, vols = _props(rng, nvol)
    props[0, vo.PR_P], props[1, vo.PR_P] = 1.0e5, 0.999e5
    props[1, vo.PR_GV] = props[1, vo.PR_G] / 1e-7        # 0.1 cm^3
    vols[1] = 1e-7
    rate = np.array([0.0, -5e9, 0.0, 0.0])                # volume 1 expanding fast
    E = np.zeros((1, 7))
    nw.lin_between(0, 1, 1e-4, 0.0, props, 1e-4, E, 0)
    nw.solve_one(0, E, props, rate, nvol, 1e-3)
    c1 = props[1, vo.PR_GV] * props[0, vo.PR_RT]
    # the pressure of volume 1 then (almost) holds: flow ~ -rate_1 / c_1
    assert E[0, 6] == pytest.approx(5e9 / c1, rel=0.02)
