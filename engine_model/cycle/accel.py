"""Acceleration of the cycle-to-cycle iteration: minimal polynomial extrapolation (MPE).

The converged cycle is the fixed point x* = F(x*) of the map F that integrates
one 720 deg cycle from the end-of-cycle state x (masses and energies of every
volume, runner flows or pipe cells).  Near x* the iterates approach it along a few slowly
decaying modes (ratios ~0.8-0.92 per cycle here: the burned-gas and fresh-mixture
content of the plenum and ports, fed by backflow), so plain iteration needs
20-50 cycles for 0.1 %.  MPE fits the last k+1 differences u_j = x_{j+1} - x_j
with a polynomial of degree k in F and returns the weighted combination of the
iterates that cancels it, which removes up to k geometric modes at once:

    min_c || sum_{j<k} c_j u_j + u_k ||,  c_k = 1,  gamma = c / sum(c),
    x* ~ sum_{j<=k} gamma_j x_j

(Cabay and Jackson 1976, SIAM J. Numer. Anal. 13, 734; Sidi, Ford and Smith
1986, SIAM J. Numer. Anal. 23, 178).  Applied cyclically (restarted from the
extrapolated state) it behaves like a secant method on the slow modes.

Kernels here are pure functions over float arrays (numba, no NRT).
"""

from numba import njit

from engine_model.cycle.layout import FASTMATH, NVCOL, V_U

U_SCALE = 1.0e6   # [J/kg] specific-energy scale that makes energies comparable to mass fractions


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def state_weights(vol, mr, q, w, ncyl):
    """Weights of the MPE fit: masses per volume (or cell) mass, energies per (mass * U_SCALE), manifolds only.

    The fit sees the volumes outside the cylinders (ports, plenum, throttle
    body, collector, runner joints) and the pipe cells, where the slow modes
    live; cylinders (caught mid-stroke at the cycle end), runner flows and cell
    momenta (fast acoustic modes) get weight 0 but are extrapolated with the
    same coefficients.  Tried on the 9000 rpm WOT point of the lumped model:
    this fits the slow plenum composition better than weighting every state
    (fewer cycles for the same accuracy).
    """
    nvol = vol.shape[0]
    j = 0
    for i in range(nvol):
        m = vol[i, 0] + vol[i, 1] + vol[i, 2]
        inv = 1.0 / m if m > 0.0 else 0.0
        if i < ncyl:
            inv = 0.0
        for c in range(NVCOL - 1):
            w[j] = inv / U_SCALE if c == V_U else inv
            j += 1
    for i in range(mr.shape[0]):
        w[j] = 0.0
        j += 1
    nq = q.shape[1]
    for i in range(q.shape[0]):
        m = q[i, 0] + q[i, 1] + q[i, 2]
        inv = 1.0 / m if m > 0.0 else 0.0
        for c in range(nq):
            w[j] = inv if c < 3 else (inv / U_SCALE if c == nq - 1 else 0.0)
            j += 1


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def pack_state(vol, mr, q, x):
    """Copy the end-of-cycle state (vol[:, :NVCOL-1] row by row, then mr, then the pipe cells q) into x."""
    j = 0
    for i in range(vol.shape[0]):
        for c in range(NVCOL - 1):
            x[j] = vol[i, c]
            j += 1
    for i in range(mr.shape[0]):
        x[j] = mr[i]
        j += 1
    for i in range(q.shape[0]):
        for c in range(q.shape[1]):
            x[j] = q[i, c]
            j += 1


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def unpack_state(x, vol, mr, q):
    """Inverse of ``pack_state`` (the temperature column of vol is left as it is: a Newton start)."""
    j = 0
    for i in range(vol.shape[0]):
        for c in range(NVCOL - 1):
            vol[i, c] = x[j]
            j += 1
    for i in range(mr.shape[0]):
        mr[i] = x[j]
        j += 1
    for i in range(q.shape[0]):
        for c in range(q.shape[1]):
            q[i, c] = x[j]
            j += 1


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def mpe(xs, n, w, xout, G, rhs):
    """MPE estimate of the fixed point from the n consecutive iterates xs[0..n-1] (n = k + 2).

    Parameters
    ----------
    xs : (>= n, nx) float64
        Iterates x_0 .. x_{n-1} of the cycle map.
    n : int
        Number of iterates used; k = n - 2 modes are removed.
    w : (nx,) float64
        Weights of the least-squares norm.
    xout : (nx,) float64
        Receives the estimate.
    G : (>= k, >= k) float64; rhs : (>= k,) float64
        Work space.

    Returns
    -------
    float
        The dominant ratio estimated from the fit (largest |root| is not
        computed; this is the ratio of the last two difference norms), or -1
        if the fit is singular (xout then holds x_{n-1}).
    """
    k = n - 2
    nx = xs.shape[1]
    # normal equations of min || U_{0..k-1} c + u_k ||_w
    for a in range(k):
        for b in range(k):
            s = 0.0
            for j in range(nx):
                wj = w[j] * w[j]
                s += (xs[a + 1, j] - xs[a, j]) * (xs[b + 1, j] - xs[b, j]) * wj
            G[a, b] = s
        s = 0.0
        for j in range(nx):
            wj = w[j] * w[j]
            s += (xs[a + 1, j] - xs[a, j]) * (xs[k + 1, j] - xs[k, j]) * wj
        rhs[a] = -s
    nlast = 0.0
    nprev = 0.0
    for j in range(nx):
        wj = w[j] * w[j]
        d = xs[k + 1, j] - xs[k, j]
        nlast += d * d * wj
        d = xs[k, j] - xs[k - 1, j] if k >= 1 else 0.0
        nprev += d * d * wj
    ratio = (nlast / nprev) ** 0.5 if nprev > 0.0 else -1.0
    # tiny Tikhonov term against collinear differences
    tr = 0.0
    for a in range(k):
        tr += G[a, a]
    for a in range(k):
        G[a, a] += 1e-12 * tr + 1e-300
    # Gaussian elimination with partial pivoting
    for a in range(k):
        piv = a
        for b in range(a + 1, k):
            if abs(G[b, a]) > abs(G[piv, a]):
                piv = b
        if piv != a:
            for c in range(k):
                t = G[a, c]
                G[a, c] = G[piv, c]
                G[piv, c] = t
            t = rhs[a]
            rhs[a] = rhs[piv]
            rhs[piv] = t
        if G[a, a] == 0.0:
            for j in range(nx):
                xout[j] = xs[n - 1, j]
            return -1.0
        for b in range(a + 1, k):
            f = G[b, a] / G[a, a]
            for c in range(a, k):
                G[b, c] -= f * G[a, c]
            rhs[b] -= f * rhs[a]
    for a in range(k - 1, -1, -1):
        s = rhs[a]
        for b in range(a + 1, k):
            s -= G[a, b] * rhs[b]
        rhs[a] = s / G[a, a]
    csum = 1.0
    for a in range(k):
        csum += rhs[a]
    if not (abs(csum) > 1e-8):
        for j in range(nx):
            xout[j] = xs[n - 1, j]
        return -1.0
    for j in range(nx):
        s = xs[k, j]               # c_k = 1
        for a in range(k):
            s += rhs[a] * xs[a, j]
        xout[j] = s / csum
    return ratio
