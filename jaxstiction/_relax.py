r"""High-order Hammerstein ARX by relaxation: the paper's (13)–(16).

Model (13): $A^n(q) y(t) = B^n(q)\,\Phi(t)\beta + e(t)$ with
$B^n = b_1 q^{-1} + \dots + b_n q^{-n}$ and $\hat x = \Phi\beta$ the spline layer.

The criterion (14) is bilinear in $(b, \beta)$. Both relaxation steps are linear
least-squares problems in the columns of one fixed matrix
$Z = [\,Y_{\rm lags},\ \Phi_{\rm lags}\,]$ (lagged outputs and lagged spline
regressors, $n + n p$ columns): step (15) uses $Z\,T_a(b)$, step (16) uses
$Z\,T_b(\beta)$ for small linear maps $T$. So $Z$ is QR-factorised **once** per
loop, $[Z\ y] = Q [R\ r]$, and each sweep solves
$\min_\theta \lVert r - R\,T\,\theta\rVert$ — a problem whose size does not grow
with $N$. This is the Gram-tensor idea (compress once per loop), done with a QR factor instead
of normal matrices, so its conditioning is that of the original problem.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int

from ._filters import lagged
from ._linalg import gram_r, lstsq as _lstsq, qr_r, spd_solve


class RelaxProblem(eqx.Module):
    """The compressed relaxation problem for one loop (built by
    [`jaxstiction.relax_problem`][])."""

    R: Float[Array, "k k"]
    r: Float[Array, " k"]
    rho2: Float[Array, ""]
    cov: Float[Array, "p p"]
    count: Float[Array, ""]
    order: int = eqx.field(static=True)
    num_params: int = eqx.field(static=True)


def relax_problem(y, phi, order: int, weights=None, *, method: str = "qr") -> RelaxProblem:
    r"""Build the compressed problem from output `y` (time,) and spline regressors
    `phi` (time, p), for ARX order `order` ($n$). Samples `t < n` only provide lags.

    `weights` (time,) in {0, 1} drops samples (padding of ragged batches).

    `method`: how $[Z\ y]$ is reduced to its triangular factor: `"qr"` (default) by
    a Householder QR (backward stable), `"gram"` by one matrix product and a
    Cholesky factorisation of the column-scaled Gram matrix (`_linalg.gram_r`),
    about five times faster at N = 1500, n = 10, m = 6. The Gram route squares the
    condition number of $Z$: on noisy records it reaches the same minimum (criterion
    to 1e-9, valve output to 1e-6; `tests/test_relax.py`), but on exact, noise-free
    data with an ill-conditioned spline basis it loses about two digits in $a, b$
    (seen in the same tests), so it is an opt-in (`SplineSettings(compression=
    "gram")`) for screening noisy plant data, not the default.
    """
    if method not in ("gram", "qr"):
        raise ValueError(f"`method` must be 'gram' or 'qr', got {method!r}")
    n = order
    N, p = phi.shape
    ylag = lagged(y, n)
    philag = jnp.stack([lagged(phi[:, j], n) for j in range(p)], axis=2)  # (N, n, p)
    Z = jnp.concatenate([ylag, philag.reshape(N, n * p)], axis=1)
    w = jnp.ones((N,), y.dtype) if weights is None else weights
    w = w * (jnp.arange(N) >= n)
    A = jnp.concatenate([Z, y[:, None]], axis=1)
    Rfull = gram_r(A, w) if method == "gram" else qr_r(A * w[:, None])
    k = Z.shape[1]
    phic = (phi - jnp.sum(w[:, None] * phi, 0) / jnp.sum(w)) * w[:, None]
    cov = phic.T @ phic / jnp.sum(w)
    return RelaxProblem(
        R=Rfull[:k, :k],
        r=Rfull[:k, k],
        rho2=Rfull[k, k] ** 2,
        cov=cov,
        count=jnp.sum(w),
        order=n,
        num_params=p,
    )


class ARXHammerstein(eqx.Module):
    """High-order model: `a` = $[a_1..a_n]$, `b` = $[b_1..b_n]$, `beta` spline
    coefficients (see [`jaxstiction.hysteresis_regressors`][])."""

    a: Float[Array, " n"]
    b: Float[Array, " n"]
    beta: Float[Array, " p"]


def _coef(model: ARXHammerstein):
    return jnp.concatenate([-model.a, jnp.kron(model.b, model.beta)])


def relax_loss(model: ARXHammerstein, prob: RelaxProblem):
    """Criterion (14), mean square, from the compressed problem."""
    res = prob.r - prob.R @ _coef(model)
    return (jnp.sum(res**2) + prob.rho2) / prob.count


def _normalise(a, b, beta, cov):
    # Gain split between B and f is arbitrary: fix std(x_hat) = 1 and B(1) >= 0.
    s = jnp.sqrt(jnp.maximum(beta @ cov @ beta, 1e-300))
    sign = jnp.where(jnp.sum(b) < 0, -1.0, 1.0)
    return ARXHammerstein(a=a, b=b * s * sign, beta=beta / (s * sign))


def _linear_part(beta, prob: RelaxProblem, ridge=1e-14):
    r"""Step (16): unknowns `(a, b)` for fixed `beta`: $Z T_b(\beta) = [-Y, \Phi_k \beta]$."""
    n, p = prob.order, prob.num_params
    Ry = prob.R[:, :n]
    Rphi = prob.R[:, n:].reshape(-1, n, p)
    th = _lstsq(jnp.concatenate([-Ry, jnp.einsum("ikj,j->ik", Rphi, beta)], axis=1), prob.r, ridge)
    return th[:n], th[n:]


def relax_sweep(model: ARXHammerstein, prob: RelaxProblem, ridge=1e-14):
    """One relaxation sweep: step (15), then step (16), then gain normalisation."""
    n, p = prob.order, prob.num_params
    Ry = prob.R[:, :n]
    Rphi = prob.R[:, n:].reshape(-1, n, p)  # columns indexed by (lag k, basis j)
    # (15): unknowns [a, beta] for fixed b: Z T_a(b) = [-Y, sum_k b_k Phi_k].
    th = _lstsq(jnp.concatenate([-Ry, jnp.einsum("ikj,k->ij", Rphi, model.b)], axis=1), prob.r, ridge)
    beta = th[n:]
    a, b = _linear_part(beta, prob, ridge)  # (16)
    return _normalise(a, b, beta, prob.cov)


class RelaxSolution(eqx.Module):
    """Result of [`jaxstiction.relax`][]: the model, the criterion (14), the residual
    variance estimate `R` ($\\hat\\lambda$), steps taken, and an optimistix result code."""

    model: ARXHammerstein
    loss: Float[Array, ""]
    num_steps: Int[Array, ""]
    result: optx.RESULTS


def relax_init(prob: RelaxProblem) -> ARXHammerstein:
    """The paper's initialisation: $B^n = q^{-1}$, then $A^n$ and $f$ by least squares."""
    n, p = prob.order, prob.num_params
    dtype = prob.R.dtype
    b0 = jnp.zeros((n,), dtype).at[0].set(1.0)
    return ARXHammerstein(a=jnp.zeros((n,), dtype), b=b0, beta=jnp.zeros((p,), dtype))


class _Reduced(eqx.Module):
    r"""The relaxation problem reduced to the spline coefficients: the blocks of
    $X(\beta)^T X(\beta)$ and $X(\beta)^T r$ as fixed tensors, $X(\beta) =
    [-R_y,\ \sum_j \beta_j R_{\phi,j}]$, so the projected criterion
    $f(\beta) = r^T r - r^T X (X^T X)^{-1} X^T r$ costs a $2n \times 2n$ solve."""

    Gyy: Array
    C: Array
    T: Array
    ry: Array
    rphi: Array
    rr: Array

    @staticmethod
    def of(prob: RelaxProblem) -> "_Reduced":
        n, p = prob.order, prob.num_params
        Ry = prob.R[:, :n]
        Rphi = prob.R[:, n:].reshape(-1, n, p)
        return _Reduced(Gyy=Ry.T @ Ry, C=jnp.einsum("ia,ikj->akj", Ry, Rphi),
                        T=jnp.einsum("ikj,ilm->kjlm", Rphi, Rphi), ry=Ry.T @ prob.r,
                        rphi=jnp.einsum("ikj,i->kj", Rphi, prob.r), rr=prob.r @ prob.r)

    def _normal(self, beta):
        cb = jnp.einsum("akj,j->ak", self.C, beta)
        tbb = jnp.einsum("kjlm,j,m->kl", self.T, beta, beta)
        return jnp.block([[self.Gyy, -cb], [-cb.T, tbb]]), jnp.concatenate([-self.ry, self.rphi @ beta])

    def _solve(self, G, v, ridge):
        d = jnp.sqrt(jnp.maximum(jnp.diag(G), 1e-300))
        Gs = G / (d[:, None] * d[None, :]) + ridge * jnp.eye(G.shape[0], dtype=G.dtype)
        return spd_solve(Gs, v / d) / d

    def loss(self, beta, ridge=1e-12):
        G, v = self._normal(beta)
        return self.rr - self._solve(G, v, ridge) @ v

    def gauss_newton(self, beta, ridge=1e-12):
        r"""Kaufman's Gauss–Newton system $(J^T J, J^T e)$ with $J = -P^\perp M_b$,
        $M_b = \sum_k b_k R_{\phi,k}$, from the same tensors."""
        n = self.Gyy.shape[0]
        G, v = self._normal(beta)
        th = self._solve(G, v, ridge)
        b = th[n:]
        MtM = jnp.einsum("kjlm,k,l->jm", self.T, b, b)
        XtM = jnp.concatenate([-jnp.einsum("akj,k->aj", self.C, b),
                               jnp.einsum("kmlj,m,l->kj", self.T, beta, b)])
        Mtr = b @ self.rphi
        Mte = Mtr - th @ XtM
        W = jax.vmap(lambda col: self._solve(G, col, ridge), in_axes=1, out_axes=1)(XtM)
        return MtM - XtM.T @ W, Mte


_DAMPING = (1e-10, 1e-6, 1e-3, 1e-1)


def _varpro_step(beta, red: _Reduced):
    r"""One step of variable projection (Golub–Pereyra) on the spline coefficients:
    $(a, b)$ are eliminated by least squares for each $\beta$, leaving the projected
    criterion $f(\beta)$ in $p$ unknowns (`_Reduced.loss`). Candidate moves: Newton
    steps on $f$ (exact Hessian by autodiff) damped by $\mu I$ for several $\mu$ (so
    an indefinite Hessian away from the minimum still offers a descent direction),
    and the Gauss–Newton step with Kaufman's Jacobian (`_Reduced.gauss_newton`).
    The best of them, or no move, is taken: a fixed cost per step, never a rise of
    the criterion, and quadratic convergence near the minimum, where
    the alternation is linear."""
    p = beta.shape[0]
    g = jax.grad(red.loss)(beta)
    H = jax.hessian(red.loss)(beta)
    H = 0.5 * (H + H.T)
    scale = jnp.trace(jnp.abs(H)) / p
    eye = jnp.eye(p, dtype=H.dtype)
    d_n = jax.vmap(lambda mu: spd_solve(H + mu * scale * eye, -g))(jnp.asarray(_DAMPING, H.dtype))
    JtJ, Jte = red.gauss_newton(beta)
    d_gn = spd_solve(JtJ + 1e-12 * jnp.trace(JtJ) / p * eye, Jte)
    lengths = jnp.asarray([1.0, 0.5], H.dtype)
    cand = jnp.concatenate([d_n, 0.5 * d_n, lengths[:, None] * d_gn[None, :], jnp.zeros((1, p), H.dtype)])
    losses = jax.vmap(lambda d: red.loss(beta + d))(cand)
    losses = jnp.where(jnp.isfinite(losses), losses, jnp.inf)
    return beta + cand[jnp.argmin(losses)]


def relax(
    prob: RelaxProblem,
    init: ARXHammerstein | None = None,
    *,
    method: str = "alternation",
    projection_steps: int = 12,
    rtol=1e-7,
    atol=1e-9,
    max_steps=200,
    adjoint=optx.ImplicitAdjoint(),
) -> RelaxSolution:
    r"""Minimise the bilinear criterion (14) from the paper's start.

    - `method="alternation"` (default): the paper's relaxation, (15) and (16)
      alternated to a fixed point with `optx.fixed_point`. It converges linearly
      (tens to hundreds of sweeps), and under `vmap` every member runs as many sweeps
      as the slowest.
    - `method="variable_projection"`: first `projection_steps` steps of variable
      projection on the separable problem (`_varpro_step`: the linear part
      eliminated; damped Newton or Gauss–Newton on the spline coefficients; a fixed
      number of steps, so no member waits for another), then the alternation from
      there. The alternation's fixed point is the minimum both methods stop at (and
      what gradients are taken at, by implicit differentiation); started next to it,
      it needs a few sweeps (tested to reach the same minimum as the alternation and
      the NumPy reference). On this CPU each projection step (a Hessian through a
      small Cholesky solve, ~1.5–2 ms) costs more than the sweeps it saves at N =
      1500, n = 10, m = 6, so it is not the default; see `benchmarks/bench_relax.py`.

    Never raises: a fit that has not converged within `max_steps` returns
    `result = RESULTS.max_steps_reached`, which is safe under `vmap`.
    """
    if method not in ("alternation", "variable_projection"):
        raise ValueError(f"`method` must be 'alternation' or 'variable_projection', got {method!r}")
    if init is None:
        init = relax_init(prob)
        # Paper's initialisation: first step (15) with B = q^-1.
        init = relax_sweep(init, prob)
    if method == "variable_projection":
        beta = jax.lax.stop_gradient(init.beta)
        pr = jax.lax.stop_gradient(prob)
        red = _Reduced.of(pr)
        beta = jax.lax.fori_loop(0, projection_steps, lambda _, bt: _varpro_step(bt, red), beta)
        a, b = _linear_part(beta, pr)
        start = _normalise(a, b, beta, pr.cov)
        better = relax_loss(start, pr) <= relax_loss(jax.lax.stop_gradient(init), pr)
        init = jax.tree.map(lambda s_, i: jnp.where(better, s_, i), start, init)
    sol = optx.fixed_point(
        lambda m, pr: relax_sweep(m, pr),
        optx.FixedPointIteration(rtol=rtol, atol=atol),
        init,
        prob,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    return RelaxSolution(
        model=sol.value,
        loss=relax_loss(sol.value, prob),
        num_steps=sol.stats["num_steps"],
        result=sol.result,
    )
