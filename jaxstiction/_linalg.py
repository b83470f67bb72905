r"""Small dense linear algebra in pure JAX: Householder QR, least squares, and a
polynomial stability test.

Why not LAPACK: on CPU, jaxlib (0.10) runs *batched* LAPACK kernels (QR, `ormqr`,
eigenvalues) with a parallel batch map on XLA's worker pool. Inside `vmap`ped
`while` loops, which XLA's CPU runtime runs as concurrent tasks, two such kernels can
each block a worker while waiting for sub-tasks queued behind each other: on a
2-core machine every worker is then blocked and the process hangs (seen here, with a
native stack in `ParallelBatchMap`). The estimators' problems are tall and thin
(tens of columns), where a Householder QR written with `lax.fori_loop` costs the
same $O(mn^2)$ flops and never calls out of XLA.
"""

from __future__ import annotations

from typing import Any

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import lineax as lx
from lineax._solver.misc import pack_structures, ravel_vector, unravel_solution


def _norm(x):
    """Euclidean norm with a finite derivative at 0 (masked, all-zero columns)."""
    sq = jnp.sum(x**2)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def householder(A):
    """Householder QR of a tall matrix `A` (m >= n): returns `(V, R)`, the unit
    reflector vectors (rows of `V`, shape (n, m)) and the upper-triangular factor
    `R` (n, n), with $Q^T A = [R; 0]$ and $Q^T = H_{n-1} \\cdots H_0$,
    $H_k = I - 2 v_k v_k^T$."""
    m, n = A.shape
    rows = jnp.arange(m)

    def step(k, carry):
        R, V = carry
        x = jnp.where(rows >= k, R[:, k], 0.0)
        norm = _norm(x)
        xk = R[k, k]
        alpha = -jnp.where(xk >= 0, 1.0, -1.0) * norm
        v = x - alpha * (rows == k)
        vn = _norm(v)
        v = jnp.where(vn > 0, v / jnp.where(vn > 0, vn, 1.0), 0.0)
        R = R - 2.0 * jnp.outer(v, v @ R)
        return R, V.at[k].set(v)

    R, V = jax.lax.fori_loop(0, n, step, (A, jnp.zeros((n, m), A.dtype)))
    return V, jnp.triu(R[:n])


def apply_qt(V, b):
    """$Q^T b$ for the reflectors `V` of [`householder`][]."""

    def step(k, b):
        v = V[k]
        return b - 2.0 * v * (v @ b)

    return jax.lax.fori_loop(0, V.shape[0], step, b)


def apply_q(V, b):
    """$Q b$ for the reflectors `V` of [`householder`][] (their reflections in
    reverse order): the inverse of [`apply_qt`][]."""
    n = V.shape[0]

    def step(j, b):
        v = V[n - 1 - j]
        return b - 2.0 * v * (v @ b)

    return jax.lax.fori_loop(0, n, step, b)


def solve_upper(R, c):
    """Back substitution $R x = c$ for an upper-triangular `R`."""
    n = R.shape[0]

    def step(j, x):
        i = n - 1 - j
        return x.at[i].set((c[i] - R[i] @ x) / R[i, i])

    return jax.lax.fori_loop(0, n, step, jnp.zeros_like(c))


def qr_r(A):
    """The triangular factor R of `A` (m >= n), as `jnp.linalg.qr(A, mode="r")` up to
    the signs of its rows."""
    return householder(A)[1]


def lstsq(M, v, ridge=1e-14):
    """Least squares $\\min_\\theta \\lVert M\\theta - v\\rVert$ by Householder QR,
    never by normal equations.

    Columns are scaled to unit norm first, then Tikhonov rows $\\sqrt{\\text{ridge}}\\,I$
    are appended: masked (all-zero) columns stay well posed (their coefficient is 0)
    while the solution moves by $O(\\text{ridge}/\\sigma_{min}^2)$ of the *scaled*
    problem only.
    """
    k = M.shape[1]
    norms = jax.vmap(_norm, in_axes=1)(M)
    scale = jnp.where(norms > 0, norms, 1.0)
    Ms = jnp.concatenate([M / scale, jnp.sqrt(ridge) * jnp.eye(k, dtype=M.dtype)], axis=0)
    vs = jnp.concatenate([v, jnp.zeros((k,), v.dtype)])
    V, R = householder(Ms)
    return solve_upper(R, apply_qt(V, vs)[:k]) / scale


class HouseholderQR(lx.QR):
    """`lineax.QR` computed by [`householder`][] in pure JAX (no batched LAPACK:
    see the module docstring), for the overdetermined, full-rank least-squares
    problems inside optimistix's Gauss–Newton and Levenberg–Marquardt steps."""

    def init(self, operator, options):
        del options
        matrix = operator.as_matrix()
        m, n = matrix.shape
        if n > m:
            raise ValueError("HouseholderQR handles overdetermined (tall) operators only")
        return householder(matrix), eqxi.Static(False), pack_structures(operator)

    def compute(self, state, vector, options: dict[str, Any]):
        (V, R), transpose, packed = state
        del options
        if transpose.value:
            raise NotImplementedError("HouseholderQR does not solve transposed systems")
        b = ravel_vector(vector, packed)
        x = solve_upper(R, apply_qt(V, b)[: R.shape[0]])
        return unravel_solution(x, packed), lx.RESULTS.successful, {}

    def conj(self, state, options):
        return state, {}


def is_stable(a, margin=0.0):
    """True when all roots of $z^{n} A(z^{-1})$ lie strictly inside the circle of
    radius `1 - margin`: the Schur–Cohn (step-down) test, in pure JAX.

    The polynomial is scaled to radius `1 - margin` ($a_k \\to a_k / r^k$), then
    reduced degree by degree; it is stable iff every reflection coefficient has
    modulus below 1.
    """
    a = jnp.asarray(a)
    n = a.shape[0] - 1
    if n <= 0:
        return jnp.asarray(True)
    r = 1.0 - margin
    a = a / a[0] * r ** (-jnp.arange(n + 1, dtype=a.dtype))
    ok = jnp.all(jnp.isfinite(a))
    for deg in range(n, 0, -1):
        k = a[deg]
        ok = ok & (jnp.abs(k) < 1.0)
        denom = jnp.where(jnp.abs(k) < 1.0, 1.0 - k**2, 1.0)
        a = ((a - k * a[::-1]) / denom)[:deg]
    return ok


def cholesky_upper(G, tol=None):
    """Upper-triangular $R$ with $R^T R = G$ for a symmetric positive-definite `G`,
    left-looking, in pure JAX (a pivot that is not positive is clamped to the
    smallest normal number: the caller regularises `G` first).

    With `tol` (for a unit-diagonal `G`), a pivot below `tol` marks a column that
    depends on the ones before it, to rounding: its pivot is set to `1 / tol`, so a
    solve with this factor gives that coordinate ~0 (as a dropped column) instead of
    dividing by a rounding error."""
    n = G.shape[0]
    idx = jnp.arange(n)
    tiny = jnp.finfo(G.dtype).tiny

    def step(j, R):
        col = jnp.where(idx < j, R[:, j], 0.0)  # R[:j, j]
        v = G[j, :] - col @ R  # G[j, :] - sum_{i<j} R[i, j] R[i, :]
        d = jnp.sqrt(jnp.maximum(v[j], tiny))
        if tol is not None:
            d = jnp.where(v[j] > tol, d, 1.0 / tol)
        return R.at[j, :].set(jnp.where(idx > j, v / d, jnp.where(idx == j, d, 0.0)))

    return jax.lax.fori_loop(0, n, step, jnp.zeros_like(G))


def gram_cholesky(G, ridge=1e-13):
    """The upper Cholesky factor of a Gram matrix `G`, computed on its column-scaled
    form (unit diagonal) plus `ridge` on the diagonal, then scaled back."""
    s = jnp.sqrt(jnp.diag(G))
    s = jnp.where(s > 0, s, 1.0)
    Gs = G / (s[:, None] * s[None, :]) + ridge * jnp.eye(G.shape[0], dtype=G.dtype)
    return cholesky_upper(Gs) * s[None, :]


def spd_solve(A, b, tol=None):
    """Solve $A x = b$ for a small symmetric positive-definite `A` by the pure-JAX
    Cholesky factor (`cholesky_upper`, with its `tol`) and two triangular sweeps."""
    R = cholesky_upper(A, tol)
    n = A.shape[0]
    idx = jnp.arange(n)

    def fwd(i, z):  # R^T z = b
        return z.at[i].set((b[i] - jnp.where(idx < i, R[:, i], 0.0) @ z) / R[i, i])

    def back(k, x):  # R x = z
        i = n - 1 - k
        return x.at[i].set((z[i] - jnp.where(idx > i, R[i, :], 0.0) @ x) / R[i, i])

    z = jax.lax.fori_loop(0, n, fwd, jnp.zeros_like(b))
    return jax.lax.fori_loop(0, n, back, jnp.zeros_like(b))
