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
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int

from ._filters import lagged
from ._linalg import lstsq as _lstsq, qr_r


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


def relax_problem(y, phi, order: int, weights=None) -> RelaxProblem:
    r"""Build the compressed problem from output `y` (time,) and spline regressors
    `phi` (time, p), for ARX order `order` ($n$). Samples `t < n` only provide lags.

    `weights` (time,) in {0, 1} drops samples (padding of ragged batches).
    """
    n = order
    N, p = phi.shape
    ylag = lagged(y, n)
    philag = jnp.stack([lagged(phi[:, j], n) for j in range(p)], axis=2)  # (N, n, p)
    Z = jnp.concatenate([ylag, philag.reshape(N, n * p)], axis=1)
    w = jnp.ones((N,), y.dtype) if weights is None else weights
    w = w * (jnp.arange(N) >= n)
    A = jnp.concatenate([Z, y[:, None]], axis=1) * w[:, None]
    Rfull = qr_r(A)
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


def relax_sweep(model: ARXHammerstein, prob: RelaxProblem, ridge=1e-14):
    """One relaxation sweep: step (15), then step (16), then gain normalisation."""
    n, p = prob.order, prob.num_params
    Ry = prob.R[:, :n]
    Rphi = prob.R[:, n:].reshape(-1, n, p)  # columns indexed by (lag k, basis j)
    # (15): unknowns [a, beta] for fixed b: Z T_a(b) = [-Y, sum_k b_k Phi_k].
    th = _lstsq(jnp.concatenate([-Ry, jnp.einsum("ikj,k->ij", Rphi, model.b)], axis=1), prob.r, ridge)
    a, beta = th[:n], th[n:]
    # (16): unknowns [a, b] for fixed beta: Z T_b(beta) = [-Y, Phi_k beta].
    th = _lstsq(jnp.concatenate([-Ry, jnp.einsum("ikj,j->ik", Rphi, beta)], axis=1), prob.r, ridge)
    a, b = th[:n], th[n:]
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


def relax(
    prob: RelaxProblem,
    init: ARXHammerstein | None = None,
    *,
    rtol=1e-7,
    atol=1e-9,
    max_steps=200,
    adjoint=optx.ImplicitAdjoint(),
) -> RelaxSolution:
    r"""Alternate (15) and (16) to a fixed point with `optx.fixed_point`
    (a `lax.while_loop`; gradients by implicit differentiation at the fixed point).

    Never raises: a fit that has not converged within `max_steps` returns
    `result = RESULTS.max_steps_reached`, which is safe under `vmap`.
    """
    if init is None:
        init = relax_init(prob)
        # Paper's initialisation: first step (15) with B = q^-1.
        init = relax_sweep(init, prob)
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
