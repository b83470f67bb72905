r"""Models drawn around a fitted loop model, to carry the uncertainty of S, J and the
process into the what-if intervals.

- $S$ and $J$: uniform on their intervals ([`jaxstiction.LoopFit`][]'s
  `S_interval`, `J_interval`, profile likelihood), $J \le S$;
- the process coefficients $\theta$ (the free entries of $B$ and $A$): from their
  asymptotic distribution $N(\hat\theta, \hat\sigma^2 (\Psi^T \Psi)^{-1})$, with
  $\Psi = \frac{D}{C}\,\partial \hat y / \partial \theta$ the prediction-error
  gradient whitened by the noise model and $\hat\sigma^2$ the variance of the
  innovations (Ljung 1999, Sec. 9.3), computed at the fitted valve path. A draw whose
  $A$ is not stable is replaced by the fitted process.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr

from .._control.closedloop import with_valve
from .._filters import lfilter
from .._linalg import _norm, householder, is_stable, solve_upper
from .._models import InitialState, LinearProcess, LoopModel


def with_process(model: LoopModel, b, a) -> LoopModel:
    """`model` with the process polynomials `b`, `a` (delay folded into `b`)."""
    return eqx.tree_at(lambda m: m.process, model, LinearProcess(b=b, a=a))


def free_parameters(model: LoopModel):
    """Which process coefficients `[b, a[1:]]` are free (non-zero in the fit)."""
    b, a = model.process.polynomials()
    return jnp.concatenate([b, a[1:]]) != 0


def process_factor(model: LoopModel, op, v, initial: InitialState, mask):
    """`(theta, free, R, sigma, scale)`: the process coefficients `theta = [b, a[1:]]`,
    which are free (non-zero in the fit), and the triangular factor `R` of the
    column-scaled, whitened sensitivity matrix (fixed coefficients pinned by a
    large regularising row), so that $\\hat\\theta + \\hat\\sigma R^{-1} z / \\text{scale}$,
    $z \\sim N(0, I)$, is a draw. `v` is the model's disturbance on the record."""
    b, a = model.process.polynomials()
    nb = b.shape[0]
    theta = jnp.concatenate([b, a[1:]])
    free = theta != 0
    d, c = model.noise.d.astype(op.dtype), model.noise.c.astype(op.dtype)
    w = (mask > 0).astype(op.dtype)

    def sim(th):
        return with_process(model, th[:nb], jnp.concatenate([a[:1], th[nb:]])).simulate(op, initial)

    G = jax.jacfwd(sim)(theta)  # (time, params)
    Psi = jax.vmap(lambda g: lfilter(d, c, g), in_axes=1, out_axes=1)(G) * w[:, None] * free[None, :]
    eps = lfilter(d, c, v) * w
    count = jnp.maximum(jnp.sum(w), 1.0)
    sigma = jnp.sqrt(jnp.sum(eps**2) / count)
    norms = jax.vmap(_norm, in_axes=1)(Psi)
    scale = jnp.where(free & (norms > 0), norms, 1.0)
    pin = jnp.where(free & (norms > 0), 1e-8, 1e8)
    _, R = householder(jnp.concatenate([Psi / scale, jnp.diag(pin)], axis=0))
    return theta, free & (norms > 0), R, sigma, scale


def draw_models(model: LoopModel, S_interval, J_interval, op, v, initial: InitialState, mask, key,
                count: int) -> LoopModel:
    """`count` models (a leading axis) drawn around `model` (see the module notes)."""
    theta, free, R, sigma, scale = process_factor(model, op, v, initial, mask)
    b, a = model.process.polynomials()
    nb = b.shape[0]
    k_s, k_j, k_p = jr.split(key, 3)
    dtype = op.dtype
    S0, J0 = model.chain[0].S, model.chain[0].J

    def bounds(iv, fallback):
        ok = jnp.all(jnp.isfinite(iv)) & (iv[1] >= iv[0])
        return jnp.where(ok, iv[0], fallback), jnp.where(ok, iv[1], fallback)

    s_lo, s_hi = bounds(S_interval, S0)
    j_lo, j_hi = bounds(J_interval, J0)
    S = s_lo + (s_hi - s_lo) * jr.uniform(k_s, (count,), dtype)
    J = jnp.minimum(j_lo + (j_hi - j_lo) * jr.uniform(k_j, (count,), dtype), S)
    z = jr.normal(k_p, (count, theta.shape[0]), dtype)

    def one(s, j, zk):
        th = theta + jnp.where(free, sigma * solve_upper(R, zk) / scale, 0.0)
        bk, ak = th[:nb], jnp.concatenate([a[:1], th[nb:]])
        ok = is_stable(ak) & jnp.all(jnp.isfinite(th))
        m = with_process(model, jnp.where(ok, bk, b), jnp.where(ok, ak, a))
        return with_valve(m, s, j)

    return jax.vmap(one)(S, J, z)

