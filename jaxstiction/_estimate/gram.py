r"""The relaxation's Gram route: the Gram matrix of the lagged regressors read off
lagged cross-correlations (`lag_gram`), and the sweeps' normal equations from its
blocks in whitened coordinates (`GramProblem`). Built by
`relax.relax_problem(..., method="gram")`; see `relax` for the model and the
alternation."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._linalg import gram_cholesky, solve_upper, spd_solve


_DROP = 1e-10  # pivot (unit-diagonal scale) below which a column counts as dependent


def _lag_gram_window(x, n: int, lo, hi):
    r"""`lag_gram` for rows `t` in one window `[lo, hi)` with `lo >= n`, from
    correlations: for $k \ge l$, $\sum_{s=lo-k}^{hi-1-k} x_i(s) x_j(s+e)$, $e = k - l
    \ge 0$, is the window's correlation at lag $e$ plus the `k` samples before `lo`
    minus the `k` samples before `hi`; the entries with $k < l$ follow by symmetry."""
    N, q = x.shape
    xp = jnp.concatenate([x, jnp.zeros((2 * n, q), x.dtype)])
    inside = ((jnp.arange(N) >= lo) & (jnp.arange(N) < hi)).astype(x.dtype)
    xw = (x * inside[:, None]).T
    # one (q, N) x (N, q) product per lag e >= 0: x(s) against x(s + e)
    F = jnp.stack([xw @ xp[e : e + N] for e in range(n + 1)], axis=2)

    def edge(t0):
        # sum_{r=1}^{k} x_i(t0 - r) x_j(t0 - r + e), for e, k = 0..n
        seg = jax.lax.dynamic_slice_in_dim(xp, t0 - n, 2 * n)  # x(t0 - n .. t0 + n - 1)
        xi = seg[:n][::-1]  # x(t0 - r), r = 1..n
        xj = jnp.stack([seg[e : n + e][::-1] for e in range(n + 1)])  # (n+1, n, q): x(t0 - r + e)
        terms = jnp.einsum("ri,erj->ijer", xi, xj)
        return jnp.concatenate([jnp.zeros(terms.shape[:3] + (1,), x.dtype), jnp.cumsum(terms, axis=3)], axis=3)

    E = edge(lo) - edge(hi)  # (q, q, n+1, n+1)
    k = jnp.arange(n + 1)
    e = jnp.maximum(k[:, None] - k[None, :], 0)  # (k, l)
    Lh = F[:, :, e] + E[:, :, e, k[:, None]]  # (q, q, k, l), right for k >= l
    L = jnp.where(k[:, None] >= k[None, :], Lh, jnp.transpose(Lh, (1, 0, 3, 2)))
    return jnp.transpose(L, (0, 2, 1, 3))


def lag_gram(x, n: int, weights, *, window: bool = False):
    r"""The Gram matrix of the lagged signals, $L_{ikjl} = \sum_t w_t\, x_i(t-k)\,
    x_j(t-l)$ for signals `x` (time, q) and lags $k, l = 0..n$, shape (q, n+1, q, n+1);
    `weights` (time,) in {0, 1}, zero for `t < n`.

    When the weights are one run of ones (a record, its padding off; or an
    estimation window) it is read off lagged correlations with edge corrections,
    $O(N q^2 n)$ instead of the $O(N q^2 n^2)$ of forming the lagged matrix's Gram
    matrix; other weights (several runs) take that direct product. `window=True`
    says the weights are known to be one run, which skips the test (and, under
    `vmap`, the direct product that a data-dependent branch would also compute).
    """
    N, q = x.shape
    on = weights > 0
    idx = jnp.arange(N)
    lo = jnp.min(jnp.where(on, idx, N))
    hi = jnp.max(jnp.where(on, idx, -1)) + 1
    fast = lambda: _lag_gram_window(x, n, lo, jnp.maximum(hi, lo))
    if window:
        return fast()

    def direct():
        X = jnp.stack([jnp.concatenate([jnp.zeros((k, q), x.dtype), x[: N - k]]) for k in range(n + 1)], axis=2)
        Xw = X * weights[:, None, None]
        return jnp.einsum("tik,tjl->ikjl", Xw, X)

    one_run = jnp.sum(on) == hi - lo
    return jax.lax.cond(one_run, fast, direct)


class GramProblem(eqx.Module):
    r"""The relaxation problem as the blocks of the Gram matrix of $[Z\ y]$ (built by
    [`jaxstiction.internal.relax_problem`][] with `method="gram"`): $G_{yy} = Y^T Y$ (n, n),
    $C = Y^T \Phi$ (n, n, p), $T = \Phi^T \Phi$ (n, p, n, p), $Y^T y$, $\Phi^T y$ and
    $y^T y$, with $Y$ the lagged outputs and $\Phi$ the lagged spline regressors
    (columns indexed by lag, then basis). For a fixed $b$ or a fixed $\beta$ the
    normal equations of (15) and (16), and the criterion, are contractions of these
    tensors: no sweep touches the data.

    The tensors are held in whitened coordinates $\gamma = S^{-1}\beta$ and $\alpha =
    S_y^{-1} a$, with $S$ and $S_y$ from the Cholesky factors of the Gram matrices of
    the spline regressors and of the lagged outputs, so $Y^T Y = I$ and each sweep's
    solves are those of two Schur complements, $p \times p$ and $n \times n$.
    The spline basis is badly conditioned (coefficients of 1e4 that cancel to a valve
    output of 1): in its own coordinates the normal equations of (15) lose about five
    digits per sweep, enough that the alternation never settles at `rtol = 1e-7`; in
    whitened ones they keep the digits of the QR route."""

    C: Float[Array, "n n p"]  # (a, k, j), whitened in a and j
    T: Float[Array, "n p n p"]  # (k, j, l, m), whitened in j and m
    # The same tensors laid out so that each sweep's contractions are matrix-vector
    # products: C as (a, j, k); T as (k l, j m) and (j m, k l).
    Cb: Float[Array, "n p n"]
    Tb: Float[Array, "nn pp"]
    Tbeta: Float[Array, "pp nn"]
    ry: Float[Array, " n"]
    rphi: Float[Array, "n p"]
    rr: Float[Array, ""]
    S: Float[Array, "p p"]
    S_inv: Float[Array, "p p"]
    Sy: Float[Array, "n n"]
    Sy_inv: Float[Array, "n n"]
    cov: Float[Array, "p p"]
    count: Float[Array, ""]
    order: int = eqx.field(static=True)
    num_params: int = eqx.field(static=True)

    @staticmethod
    def of_lag_gram(L, cov, count) -> "GramProblem":
        """From `lag_gram` of the signals `[y, phi]` (signal 0 is y; lag 0 of y is the
        target, lags 1..n are the regressors)."""
        return GramProblem.of_blocks(
            Gyy=L[0, 1:, 0, 1:],
            C=jnp.transpose(L[0, 1:, 1:, 1:], (0, 2, 1)),
            T=jnp.transpose(L[1:, 1:, 1:, 1:], (1, 0, 3, 2)),
            ry=L[0, 1:, 0, 0],
            rphi=L[1:, 1:, 0, 0].T,
            rr=L[0, 0, 0, 0],
            cov=cov, count=count,
        )

    @staticmethod
    def of_qr(prob) -> "GramProblem":
        """The same tensors from the triangular factor of the QR compression."""
        n, p = prob.order, prob.num_params
        Ry = prob.R[:, :n]
        Rphi = prob.R[:, n:].reshape(-1, n, p)
        return GramProblem.of_blocks(Gyy=Ry.T @ Ry, C=jnp.einsum("ia,ikj->akj", Ry, Rphi),
                                     T=jnp.einsum("ikj,ilm->kjlm", Rphi, Rphi), ry=Ry.T @ prob.r,
                                     rphi=jnp.einsum("ikj,i->kj", Rphi, prob.r), rr=prob.r @ prob.r + prob.rho2,
                                     cov=prob.cov, count=prob.count)

    @staticmethod
    def of_blocks(Gyy, C, T, ry, rphi, rr, cov, count) -> "GramProblem":
        """From the Gram blocks in the model's own coordinates."""
        n, p = C.shape[1], C.shape[2]
        S, S_inv = whitening(T[0, :, 0, :], 1e-12)  # the lag-1 spline regressors
        Sy, Sy_inv = whitening(Gyy, 0.0)  # exact: the sweeps take Y^T Y = I
        C = jnp.einsum("akj,ab,jm->bkm", C, Sy, S)
        T = jnp.einsum("kjlm,ja,mb->kalb", T, S, S)
        return GramProblem(C=C, T=T, Cb=jnp.transpose(C, (0, 2, 1)),
                           Tb=jnp.transpose(T, (0, 2, 1, 3)).reshape(n * n, p * p),
                           Tbeta=jnp.transpose(T, (1, 3, 0, 2)).reshape(p * p, n * n),
                           ry=Sy.T @ ry, rphi=rphi @ S, rr=rr, S=S, S_inv=S_inv, Sy=Sy, Sy_inv=Sy_inv,
                           cov=cov, count=count, order=n, num_params=p)

    def _schur(self, cb, tbb, v2, ridge):
        r"""The system $[[I, -c], [-c^T, t]]\,[\alpha; x] = [-r_y; v_2]$ by its Schur
        complement: $(t - c^T c)\,x = v_2 - c^T r_y$, $\alpha = c\,x - r_y$."""
        x = self.solve(tbb - cb.T @ cb, v2 - cb.T @ self.ry, ridge)
        alpha = cb @ x - self.ry
        # the least-squares criterion at the solution: y'y - theta'X'y
        crit = self.rr + alpha @ self.ry - x @ v2
        return self.Sy @ alpha, x, crit

    def _blocks16(self, beta):
        r"""Step (16)'s blocks for fixed $\beta$ (whitened, $\gamma$): $Y^T M$ and $M^T M$
        with $M = \sum_j \gamma_j \Phi_{\cdot j}$, and $\gamma$."""
        n = self.order
        g = self.S_inv @ beta
        return self.C @ g, (jnp.outer(g, g).reshape(-1) @ self.Tbeta).reshape(n, n), g

    def solve_ab(self, beta, ridge):
        r"""Step (16), unknowns $(a, b)$ for fixed $\beta$: $X = [-Y,\ \sum_j \beta_j
        \Phi_{\cdot j}]$; also the criterion (sum of squares) at the solution."""
        cb, tbb, g = self._blocks16(beta)
        return self._schur(cb, tbb, self.rphi @ g, ridge)

    def solve_a_beta(self, b, ridge):
        r"""Step (15), unknowns $(a, \beta)$ for fixed $b$: $X = [-Y,\ \sum_k b_k \Phi_{k\cdot}]$."""
        p = self.num_params
        cb = self.Cb @ b
        tbb = (jnp.outer(b, b).reshape(-1) @ self.Tb).reshape(p, p)
        a, g, _ = self._schur(cb, tbb, b @ self.rphi, ridge)
        return a, self.S @ g

    @staticmethod
    def solve(G, v, ridge):
        """`G x = v` on the unit-diagonal scaling of `G` plus `ridge`: the
        normal-equation form of `_linalg.lstsq` (column scaling, Tikhonov rows)."""
        d = jnp.sqrt(jnp.maximum(jnp.diag(G), 1e-300))
        d = jnp.where(jnp.diag(G) > 0, d, 1.0)
        Gs = G / (d[:, None] * d[None, :]) + ridge * jnp.eye(G.shape[0], dtype=G.dtype)
        # A column whose part outside the span of the others is lost in rounding (or
        # all zero: a masked knot) is dropped, its coefficient ~0.
        return spd_solve(Gs, v / d, tol=_DROP) / d

    def loss_of(self, a, b, beta):
        r"""$\lVert y - Z c\rVert^2$ for $c = [-a,\ b \otimes \beta]$."""
        g = self.S_inv @ beta
        a = self.Sy_inv @ a
        Cbb = jnp.einsum("akj,k,j->a", self.C, b, g)
        quad = a @ a - 2.0 * a @ Cbb + jnp.outer(b, b).reshape(-1) @ self.Tb @ jnp.outer(g, g).reshape(-1)
        lin = -a @ self.ry + b @ self.rphi @ g
        return self.rr - 2.0 * lin + quad

    def _normal16(self, beta):
        n = self.order
        cb, tbb, g = self._blocks16(beta)
        G = jnp.block([[jnp.eye(n, dtype=cb.dtype), -cb], [-cb.T, tbb]])
        return G, jnp.concatenate([-self.ry, self.rphi @ g]), g

    def loss(self, beta, ridge=1e-12):
        """The projected criterion of variable projection: $(a, b)$ eliminated."""
        G, v, _ = self._normal16(beta)
        return self.rr - self.solve(G, v, ridge) @ v

    def gauss_newton(self, beta, ridge=1e-12):
        r"""Kaufman's Gauss–Newton system $(J^T J, J^T e)$ in $\beta$ with $J = -P^\perp
        M_b$, $M_b = \sum_k b_k \Phi_{k\cdot}$, from the same tensors."""
        n = self.order
        G, v, g = self._normal16(beta)
        th = self.solve(G, v, ridge)
        b = th[n:]
        MtM = jnp.einsum("kjlm,k,l->jm", self.T, b, b)
        XtM = jnp.concatenate([-jnp.einsum("akj,k->aj", self.C, b),
                               jnp.einsum("kmlj,m,l->kj", self.T, g, b)])
        Mte = b @ self.rphi - th @ XtM
        W = jax.vmap(lambda col: self.solve(G, col, ridge), in_axes=1, out_axes=1)(XtM)
        # whitened (gamma) system to beta coordinates: d gamma = S_inv d beta
        return self.S_inv.T @ (MtM - XtM.T @ W) @ self.S_inv, self.S_inv.T @ Mte


def whitening(G, ridge):
    """`(S, S_inv)` with $S^T G S \approx I$: `S_inv` the Cholesky factor of the
    unit-diagonal form of `G` plus `ridge`, scaled back (`_linalg.gram_cholesky`), `S`
    its inverse (all-zero columns, masked knots, stay 0)."""
    S_inv = gram_cholesky(G, ridge)
    S = jax.vmap(solve_upper, in_axes=(None, 1), out_axes=1)(S_inv, jnp.eye(G.shape[0], dtype=G.dtype))
    return S, S_inv
