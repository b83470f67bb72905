"""Slow, plain-NumPy reference implementations for the relaxation tests and benchmark.

Everything here works on the FULL data (no QR compression, no JAX):

- `spline_basis`, `hysteresis_regressors`, `direction`, `scale_input`, `uniform_knots`:
  the paper's spline layer (5)-(9), written out term by term.
- `lag_matrix`: the explicit lagged-regressor matrix.
- `relax_reference`: the relaxation (15)-(16) of the high-order Hammerstein ARX model
  (13)-(14), with the explicit regression matrices of both steps over t = n..N-1,
  solved by `numpy.linalg.lstsq`; same initialisation (B = q^-1), same normalisation
  (std of x_hat = phi @ beta over t >= n equals 1 and sum(b) >= 0) and the same
  stopping rule as `optimistix.FixedPointIteration` (max-norm of the step, scaled by
  atol + rtol * |new|, below 1).

Model: y(t) + sum_k a_k y(t-k) = sum_{k=1..n} b_k x_hat(t-k) + e(t).
"""

from dataclasses import dataclass

import numpy as np


# --------------------------------------------------------------------------- spline


def scale_input(u, lo, hi):
    """Map [lo, hi] to [-1, 1]."""
    u = np.asarray(u, float)
    return 2.0 * (u - lo) / (hi - lo) - 1.0


def uniform_knots(m):
    """m equally spaced knots on [-1, 1]."""
    return np.array([-1.0 + 2.0 * k / (m - 1) for k in range(m)])


def direction(u, threshold=0.0):
    """Direction h(t): the paper's literal rule (5) (threshold 0) or the robust
    running-extreme rule (threshold > 0), one sample at a time."""
    u = np.asarray(u, float)
    N = len(u)
    h = np.empty(N)
    if threshold <= 0:
        h[0] = 1.0
        for t in range(1, N):
            h[t] = 1.0 if u[t] >= u[t - 1] else 0.0
        return h
    cur, ext = 1.0, u[0]
    for t in range(N):
        ext = max(ext, u[t]) if cur > 0 else min(ext, u[t])
        if cur > 0 and u[t] < ext - threshold:
            cur, ext = 0.0, u[t]
        elif cur == 0 and u[t] > ext + threshold:
            cur, ext = 1.0, u[t]
        h[t] = cur
    return h


def spline_basis(u, knots):
    """(7): |u - g_k|^3 for the interior knots g_2..g_{m-1}, then 1, u, u^2, u^3."""
    u = np.asarray(u, float)
    knots = np.asarray(knots, float)
    N, m = len(u), len(knots)
    out = np.empty((N, m + 2))
    for t in range(N):
        for k in range(1, m - 1):
            out[t, k - 1] = abs(u[t] - knots[k]) ** 3
        out[t, m - 2] = 1.0
        out[t, m - 1] = u[t]
        out[t, m] = u[t] ** 2
        out[t, m + 1] = u[t] ** 3
    return out


def hysteresis_regressors(u, h, knots):
    """Phi(t) = [h(t) basis(u(t)), (1 - h(t)) basis(u(t))] (ascent f1, descent f2)."""
    B = spline_basis(u, knots)
    h = np.asarray(h, float)[:, None]
    return np.concatenate([h * B, (1.0 - h) * B], axis=1)


# --------------------------------------------------------------------------- ARX


def lag_matrix(x, n):
    """Column k-1 holds x(t-k), k = 1..n, zero before the record. Shape (N, n)."""
    x = np.asarray(x, float)
    N = len(x)
    out = np.zeros((N, n))
    for k in range(1, n + 1):
        out[k:, k - 1] = x[: N - k]
    return out


def arx_residual(y, x_hat, a, b):
    """e(t) = y(t) + sum_k a_k y(t-k) - sum_k b_k x_hat(t-k), for t = n..N-1."""
    y = np.asarray(y, float)
    x_hat = np.asarray(x_hat, float)
    n = len(a)
    N = len(y)
    e = np.empty(N - n)
    for t in range(n, N):
        s = y[t]
        for k in range(1, n + 1):
            s += a[k - 1] * y[t - k] - b[k - 1] * x_hat[t - k]
        e[t - n] = s
    return e


def arx_loss(y, phi, a, b, beta):
    """Mean square of the ARX residual over t = n..N-1 (criterion (14) / count)."""
    e = arx_residual(y, np.asarray(phi) @ np.asarray(beta), a, b)
    return float(np.mean(e**2))


@dataclass
class RefSolution:
    a: np.ndarray
    b: np.ndarray
    beta: np.ndarray
    loss: float
    num_steps: int
    converged: bool


def _solve(M, v, ridge):
    if ridge:
        k = M.shape[1]
        scale = np.sqrt(ridge) * (1.0 + np.max(np.abs(M)))
        M = np.vstack([M, scale * np.eye(k)])
        v = np.concatenate([v, np.zeros(k)])
    return np.linalg.lstsq(M, v, rcond=None)[0]


def relax_reference(
    y, phi, n, *, rtol=1e-7, atol=1e-9, max_steps=200, sweeps=None, ridge=0.0
):
    """The relaxation (15)-(16) on the full data.

    Step (15), fixed b: regress y(t) on [-y(t-k)]_k and sum_k b_k phi(t-k) (columns
    per spline parameter) -> a, beta.  Step (16), fixed beta: regress y(t) on
    [-y(t-k)]_k and [x_hat(t-k)]_k with x_hat = phi @ beta -> a, b.  Then normalise:
    std(x_hat over t >= n) = 1 and sum(b) >= 0.

    Initialisation as the paper: B = q^-1, one sweep.  Then sweeps until the
    optimistix FixedPointIteration rule is met (or `max_steps`), or exactly `sweeps`
    sweeps if given.  `ridge` > 0 adds Tikhonov rows like `jaxstiction.internal.lstsq`
    (default: plain least squares).
    """
    y = np.asarray(y, float)
    phi = np.asarray(phi, float)
    N, p = phi.shape
    rows = slice(n, N)
    Ylag = lag_matrix(y, n)[rows]  # (N-n, n)
    Plag = [lag_matrix(phi[:, j], n)[rows] for j in range(p)]  # p x (N-n, n)
    target = y[rows]
    phi_est = phi[rows]

    def sweep(a, b, beta):
        # (15): B fixed.  Column j of the spline block: sum_k b_k phi_j(t-k).
        Bphi = np.stack([Plag[j] @ b for j in range(p)], axis=1)
        th = _solve(np.hstack([-Ylag, Bphi]), target, ridge)
        a, beta = th[:n], th[n:]
        # (16): f fixed.  x_hat lags.
        Xlag = lag_matrix(phi @ beta, n)[rows]
        th = _solve(np.hstack([-Ylag, Xlag]), target, ridge)
        a, b = th[:n], th[n:]
        # normalisation
        s = np.std(phi_est @ beta)
        s = max(s, 1e-150)
        sign = -1.0 if np.sum(b) < 0 else 1.0
        return a, b * s * sign, beta / (s * sign)

    a, b, beta = np.zeros(n), np.eye(n)[0], np.zeros(p)
    a, b, beta = sweep(a, b, beta)
    steps, converged = 0, False
    limit = sweeps if sweeps is not None else max_steps
    while steps < limit:
        a1, b1, beta1 = sweep(a, b, beta)
        steps += 1
        new = np.concatenate([a1, b1, beta1])
        old = np.concatenate([a, b, beta])
        err = np.max(np.abs(new - old) / (atol + rtol * np.abs(new)))
        a, b, beta = a1, b1, beta1
        if sweeps is None and err < 1:
            converged = True
            break
    return RefSolution(a, b, beta, arx_loss(y, phi, a, b, beta), steps, converged)
