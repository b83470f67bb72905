r"""High-order Hammerstein ARX by relaxation: the paper's (13)–(16).

Model (13): $A^n(q) y(t) = B^n(q)\,\Phi(t)\beta + e(t)$ with
$B^n = b_1 q^{-1} + \dots + b_n q^{-n}$ and $\hat x = \Phi\beta$ the spline layer.

The criterion (14) is bilinear in $(b, \beta)$. Both relaxation steps are linear
least-squares problems in the columns of one fixed matrix
$Z = [\,Y_{\rm lags},\ \Phi_{\rm lags}\,]$ (lagged outputs and lagged spline
regressors, $n + n p$ columns): step (15) uses $Z\,T_a(b)$, step (16) uses
$Z\,T_b(\beta)$ for small linear maps $T$. So the data are compressed **once** per
loop and no sweep touches them again, two ways (`relax_problem`):

- `"qr"`: $[Z\ y] = Q [R\ r]$ by a Householder QR, and each sweep solves
  $\min_\theta \lVert r - R\,T\,\theta\rVert$ by QR: conditioning of the original
  problem (the estimator's default);
- `"gram"`: the Gram matrix of $[Z\ y]$ from lagged cross-correlations (`lag_gram`),
  and each sweep solves its normal equations from the Gram blocks in whitened
  coordinates (`GramProblem`): faster, squares the condition number.

`relax` alternates the sweeps to a fixed point, plainly (the paper) or with Anderson
acceleration.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int

from .._filters import lagged
from .._linalg import lstsq as _lstsq, qr_r, spd_solve
from .._misc import first_min
from .gram import _DROP, GramProblem, lag_gram


class RelaxProblem(eqx.Module):
    """The compressed relaxation problem for one loop (built by
    [`jaxstiction.internal.relax_problem`][])."""

    R: Float[Array, "k k"]
    r: Float[Array, " k"]
    rho2: Float[Array, ""]
    cov: Float[Array, "p p"]
    count: Float[Array, ""]
    order: int = eqx.field(static=True)
    num_params: int = eqx.field(static=True)


def relax_problem(y, phi, order: int, weights=None, *, method: str = "qr"):
    r"""Build the compressed problem from output `y` (time,) and spline regressors
    `phi` (time, p), for ARX order `order` ($n$). Samples `t < n` only provide lags.

    `weights` (time,) in {0, 1} drops samples (padding of ragged batches).

    Pass well-conditioned regressors: with many knots the spline basis's own
    coordinates are so badly conditioned that the sweeps' rounding can keep the
    alternation from settling. The estimator passes `phi @ S` with `S` from
    `_gram.whitening` of their Gram matrix, and maps the coefficients back.

    `method`: how the data are compressed, once per loop:

    - `"qr"` (default): $[Z\ y]$ reduced to its triangular factor by a Householder QR
      (backward stable); each sweep then solves its two least-squares problems by QR
      on that factor. Returns a [`jaxstiction.internal.RelaxProblem`][].
    - `"gram"`: the Gram matrix of $[Z\ y]$, formed from the lagged cross-correlations
      of $y$ and the spline regressors (`lag_gram`, about $2n+1$ times fewer products
      than $Z^T Z$); each sweep solves its normal equations, two Cholesky
      factorisations of size $n + p$ and $2n$, so no sweep touches the data. Returns a
      [`jaxstiction.internal.GramProblem`][]. This squares the condition number: on noisy
      records it reaches the same minimum (criterion to 1e-9, valve output to 1e-6;
      `tests/test_relax.py`), but on exact, noise-free data with an ill-conditioned
      spline basis it loses about two digits in $a, b$ (seen in the same tests), so
      it is an opt-in (`SplineSettings(compression="gram")`) for screening noisy
      plant data, not the default.
    """
    if method not in ("gram", "qr"):
        raise ValueError(f"`method` must be 'gram' or 'qr', got {method!r}")
    n = order
    N, p = phi.shape
    w = jnp.ones((N,), y.dtype) if weights is None else weights
    w = w * (jnp.arange(N) >= n)
    phic = (phi - jnp.sum(w[:, None] * phi, 0) / jnp.sum(w)) * w[:, None]
    cov = phic.T @ phic / jnp.sum(w)
    if method == "gram":
        L = lag_gram(jnp.concatenate([y[:, None], phi], axis=1), n, w, window=weights is None)
        return GramProblem.of_lag_gram(L, cov, jnp.sum(w))
    ylag = lagged(y, n)
    philag = jnp.stack([lagged(phi[:, j], n) for j in range(p)], axis=2)  # (N, n, p)
    Z = jnp.concatenate([ylag, philag.reshape(N, n * p)], axis=1)
    A = jnp.concatenate([Z, y[:, None]], axis=1)
    Rfull = qr_r(A * w[:, None])
    k = Z.shape[1]
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
    coefficients (see [`jaxstiction.internal.hysteresis_regressors`][])."""

    a: Float[Array, " n"]
    b: Float[Array, " n"]
    beta: Float[Array, " p"]


def _coef(model: ARXHammerstein):
    return jnp.concatenate([-model.a, jnp.kron(model.b, model.beta)])


def relax_loss(model: ARXHammerstein, prob) -> Float[Array, ""]:
    """Criterion (14), mean square, from the compressed problem."""
    if isinstance(prob, GramProblem):
        return prob.loss_of(model.a, model.b, model.beta) / prob.count
    res = prob.r - prob.R @ _coef(model)
    return (jnp.sum(res**2) + prob.rho2) / prob.count


def _normalise(a, b, beta, cov):
    # Gain split between B and f is arbitrary: fix std(x_hat) = 1 and B(1) >= 0.
    s = jnp.sqrt(jnp.maximum(beta @ cov @ beta, 1e-300))
    sign = jnp.where(jnp.sum(b) < 0, -1.0, 1.0)
    return ARXHammerstein(a=a, b=b * s * sign, beta=beta / (s * sign))


def _linear_part(beta, prob, ridge=1e-14):
    r"""Step (16): unknowns `(a, b)` for fixed `beta`: $Z T_b(\beta) = [-Y, \Phi_k \beta]$."""
    n, p = prob.order, prob.num_params
    if isinstance(prob, GramProblem):
        return prob.solve_ab(beta, ridge)[:2]
    Ry = prob.R[:, :n]
    Rphi = prob.R[:, n:].reshape(-1, n, p)
    th = _lstsq(jnp.concatenate([-Ry, jnp.einsum("ikj,j->ik", Rphi, beta)], axis=1), prob.r, ridge)
    return th[:n], th[n:]


def _sweep_and_loss(model: ARXHammerstein, prob, ridge=1e-14):
    """One relaxation sweep and the criterion (14) of its result (on the Gram route
    read off step (16)'s solve; where only the model is used, jit drops the rest)."""
    n, p = prob.order, prob.num_params
    # (15): unknowns [a, beta] for fixed b: Z T_a(b) = [-Y, sum_k b_k Phi_k].
    if isinstance(prob, GramProblem):
        _, beta = prob.solve_a_beta(model.b, ridge)
        a, b, crit = prob.solve_ab(beta, ridge)  # (16)
        return _normalise(a, b, beta, prob.cov), crit / prob.count
    Ry = prob.R[:, :n]
    Rphi = prob.R[:, n:].reshape(-1, n, p)  # columns indexed by (lag k, basis j)
    th = _lstsq(jnp.concatenate([-Ry, jnp.einsum("ikj,k->ij", Rphi, model.b)], axis=1), prob.r, ridge)
    beta = th[n:]
    a, b = _linear_part(beta, prob, ridge)  # (16)
    new = _normalise(a, b, beta, prob.cov)
    return new, relax_loss(new, prob)


def relax_sweep(model: ARXHammerstein, prob, ridge=1e-14) -> ARXHammerstein:
    """One relaxation sweep: step (15), then step (16), then gain normalisation."""
    return _sweep_and_loss(model, prob, ridge)[0]


class RelaxSolution(eqx.Module):
    """Result of [`jaxstiction.internal.relax`][]: the model, the criterion (14), the residual
    variance estimate `R` ($\\hat\\lambda$), steps taken, and an optimistix result code."""

    model: ARXHammerstein
    loss: Float[Array, ""]
    num_steps: Int[Array, ""]
    result: optx.RESULTS


def relax_init(prob) -> ARXHammerstein:
    """The paper's initialisation: $B^n = q^{-1}$, then $A^n$ and $f$ by least squares."""
    n, p = prob.order, prob.num_params
    dtype = prob.cov.dtype
    b0 = jnp.zeros((n,), dtype).at[0].set(1.0)
    return ARXHammerstein(a=jnp.zeros((n,), dtype), b=b0, beta=jnp.zeros((p,), dtype))


_DAMPING = (1e-10, 1e-6, 1e-3, 1e-1)


def _varpro_step(beta, red: GramProblem):
    r"""One step of variable projection (Golub–Pereyra) on the spline coefficients:
    $(a, b)$ are eliminated by least squares for each $\beta$, leaving the projected
    criterion $f(\beta)$ in $p$ unknowns (`GramProblem.loss`). Candidate moves: Newton
    steps on $f$ (exact Hessian by autodiff) damped by $\mu I$ for several $\mu$ (so
    an indefinite Hessian away from the minimum still offers a descent direction),
    and the Gauss–Newton step with Kaufman's Jacobian (`GramProblem.gauss_newton`).
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
    return beta + cand[first_min(losses)]


def _anderson(prob, model: ARXHammerstein, steps: int, memory: int, rtol, atol):
    r"""Anderson acceleration (type II, memory `memory`) of the alternation, run on
    $b$: a sweep reads only $b$ (step (15) solves for $a$ and $\beta$ from it), so the
    relaxation is a fixed-point map $b \mapsto h(b)$ in $n$ unknowns. Each step takes
    one sweep and an `memory`-column least-squares problem; a step whose sweep raises
    the criterion above the best so far restarts from the best model with the history
    cleared, so the criterion the steps return never exceeds the plain
    alternation's from the same start. Stops when $h$ moves $b$ by less than the
    fixed-point tolerance, or after `steps` steps. Returns `(model, steps taken)`."""
    pr = jax.lax.stop_gradient(prob)
    model = jax.lax.stop_gradient(model)
    n = model.b.shape[0]
    dtype = model.b.dtype
    zeros_hist = jnp.zeros((memory, n), dtype)

    def body(st):
        k, b, g_prev, f_prev, dF, dG, _, best, best_loss = st
        m, loss = _sweep_and_loss(ARXHammerstein(a=model.a, b=b, beta=model.beta), pr)
        g = m.b
        f = g - b
        done = jnp.all(jnp.abs(f) <= atol + rtol * jnp.abs(g))
        worse = loss > best_loss * (1.0 + 1e-9)
        slot = (k - 1) % memory
        dF = jnp.where(k > 0, dF.at[slot].set(f - f_prev), dF)
        dG = jnp.where(k > 0, dG.at[slot].set(g - g_prev), dG)
        A = dF @ dF.T
        scale = jnp.maximum(jnp.trace(A), jnp.finfo(dtype).tiny)
        gam = spd_solve(A / scale + 1e-12 * jnp.eye(memory, dtype=dtype), dF @ f / scale, tol=_DROP)
        b_next = g - gam @ dG
        better = loss <= best_loss
        best = jax.tree.map(lambda new, old: jnp.where(better, new, old), m, best)
        best_loss = jnp.where(better, loss, best_loss)
        # a rise: back to the best model, a plain sweep from it, history cleared
        b_next = jnp.where(worse, best.b, b_next)
        dF = jnp.where(worse, zeros_hist, dF)
        dG = jnp.where(worse, zeros_hist, dG)
        k_next = jnp.where(worse, 0, k + 1)
        return (k_next, b_next, g, f, dF, dG, done, best, best_loss), 1

    def cond(c):
        st, count = c
        return (count < steps) & ~st[6]

    def step(c):
        st, count = c
        new, inc = body(st)
        return new, count + inc

    inf = jnp.asarray(jnp.inf, dtype)
    st0 = (jnp.asarray(0), model.b, model.b, jnp.zeros_like(model.b), zeros_hist, zeros_hist,
           jnp.asarray(False), model, inf)
    (st, count) = jax.lax.while_loop(cond, step, (st0, jnp.asarray(0)))
    return st[7], count


def relax(
    prob: "RelaxProblem | GramProblem",
    init: ARXHammerstein | None = None,
    *,
    method: str = "alternation",
    projection_steps: int = 12,
    anderson_steps: int = 100,
    anderson_memory: int = 5,
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
    - `method="anderson"`: Anderson-accelerated sweeps (`_anderson`: a fixed-point
      map in $b$, memory `anderson_memory`, at most `anderson_steps`, restarted from
      the best model whenever the criterion rises), then the alternation to the same
      stopping rule. Fewer sweeps (a median of ~10 against ~30 on paper_sim loops),
      the same minimum (tested), gradients by implicit differentiation at it.
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

    `num_steps` counts every step, accelerated or projection steps and sweeps, and
    never exceeds `max_steps` (the accelerator takes at most half of them).

    Never raises: a fit that has not converged within `max_steps` returns
    `result = RESULTS.max_steps_reached`, which is safe under `vmap`.
    """
    if method not in ("alternation", "anderson", "variable_projection"):
        raise ValueError(f"`method` must be 'alternation', 'anderson' or 'variable_projection', got {method!r}")
    if init is None:
        init = relax_init(prob)
        # Paper's initialisation: first step (15) with B = q^-1.
        init = relax_sweep(init, prob)
    # Every method gets `max_steps` steps in all: the accelerator's share (at most
    # half) is taken off the finishing alternation's.
    if method == "variable_projection":
        pre = min(projection_steps, max_steps // 2)
        beta = jax.lax.stop_gradient(init.beta)
        pr = jax.lax.stop_gradient(prob)
        red = pr if isinstance(pr, GramProblem) else GramProblem.of_qr(pr)
        beta = jax.lax.fori_loop(0, pre, lambda _, bt: _varpro_step(bt, red), beta)
        a, b = _linear_part(beta, pr)
        start = _normalise(a, b, beta, pr.cov)
        better = relax_loss(start, pr) <= relax_loss(jax.lax.stop_gradient(init), pr)
        init = jax.tree.map(lambda s_, i: jnp.where(better, s_, i), start, init)
        extra = jnp.asarray(pre)
    elif method == "anderson":
        pre = min(anderson_steps, max_steps // 2)
        init, extra = _anderson(prob, init, pre, anderson_memory, rtol, atol)
    else:
        pre, extra = 0, jnp.asarray(0)
    sol = optx.fixed_point(
        lambda m, pr: relax_sweep(m, pr),
        optx.FixedPointIteration(rtol=rtol, atol=atol),
        init,
        prob,
        max_steps=max_steps - pre,
        adjoint=adjoint,
        throw=False,
    )
    return RelaxSolution(
        model=sol.value,
        loss=relax_loss(sol.value, prob),
        num_steps=sol.stats["num_steps"] + extra,
        result=sol.result,
    )
