r"""Drift: a likelihood-ratio test for a random walk hidden in coloured noise.

The residual is modelled as a random walk (the drift) plus AR(1) noise,

$$z(t) = w(t) + v(t),\quad w(t) = w(t-1) + \sigma_v \sqrt{q}\,\eta(t),\quad
v(t) = a\,v(t-1) + \sigma_v\,e(t),$$

with $\eta, e$ white and unit-variance, and an unknown level (diffuse $w(0)$). The
exact Gaussian likelihood comes from a two-state Kalman filter, with $\sigma_v$
concentrated out; $a$ and the drift-to-noise ratio $q$ are searched on a grid. The
statistic is the log-likelihood gained over the best stationary model ($q = 0$: AR(1)
noise about a constant level). $q = 0$ lies on the boundary, so the $\chi^2(1)$
threshold does not hold: the diagnosis judges twice the statistic by the
chi-bar-squared mixture $\tfrac12\chi^2(0) + \tfrac12\chi^2(1)$, which it measured to
be conservative here (the statistic is 0 more often than half the time).

The fitted model is also the drift's noise model: $(1 - a q^{-1})(1 - q^{-1})\,z$ is
the sum of two MA(1) processes, one MA(1) $1 + \theta q^{-1}$, so
$C/D = (1 + \theta q^{-1}) / ((1 - a q^{-1})(1 - q^{-1}))$, the predictor the k-step
figures use.
"""

import jax
import jax.numpy as jnp
import numpy as np


# NumPy constants: importing the package must not create a JAX backend
_Q = np.logspace(-5.0, 0.0, 21)  # drift-to-noise variance ratios searched (q = 0 is the null)
_DA0 = np.linspace(-0.03, 0.03, 13)  # the stationary fit's pole, around its least-squares value
_DA1 = np.linspace(-0.09, 0.03, 13)  # the drift fit's pole, around the stationary one (a drift pulls it up)


def _neg_loglik(y, a, q):
    """Concentrated negative log-likelihood (constants dropped) of `y` under the
    random walk + AR(1) model with pole `a` and ratio `q`, and $\\hat\\sigma_v^2$.
    The first sample only sets the diffuse level and is not scored."""
    dt = y.dtype
    F = jnp.array([[1.0, 0.0], [0.0, a]], dtype=dt)
    Qm = jnp.diag(jnp.stack([q, jnp.ones((), dt)]))
    P0 = jnp.diag(jnp.stack([jnp.asarray(1e7, dt), 1.0 / (1.0 - a * a)]))

    def step(c, yt):
        x, P = c
        nu = yt - x[0] - x[1]
        Ph = P[:, 0] + P[:, 1]
        S = Ph[0] + Ph[1]
        K = Ph / S
        x = F @ (x + K * nu)
        P = F @ (P - jnp.outer(K, Ph)) @ F.T + Qm
        return (x, P), (nu, S)

    _, (nu, S) = jax.lax.scan(step, (jnp.zeros(2, dt), P0), y)
    nu, S = nu[1:], S[1:]
    s2 = jnp.mean(nu**2 / S)
    return 0.5 * jnp.sum(jnp.log(S)) + 0.5 * nu.shape[0] * jnp.log(s2), s2


@jax.jit
def drift_test(z):
    """The drift statistic of residual `z` (1-D, unpadded) and the drift fit.

    **Returns:** `(statistic, a, q, sigma_v, a_stationary)`: the log-likelihood
    gained by the random walk over the best stationary AR(1) model (≥ 0); the drift
    model's pole, drift-to-noise variance ratio and noise innovation standard
    deviation (in the units of `z`; the drift's step standard deviation is
    `sigma_v * sqrt(q)`); and the best stationary model's pole.
    """
    sd = jnp.maximum(jnp.std(z), 1e-300)
    y = (z - jnp.mean(z)) / sd
    a_ls = jnp.sum(y[1:] * y[:-1]) / jnp.maximum(jnp.sum(y[:-1] ** 2), 1e-300)
    a0 = jnp.clip(a_ls + _DA0, -0.99, 0.999)
    nll0 = jax.vmap(lambda a: _neg_loglik(y, a, jnp.zeros((), y.dtype))[0])(a0)
    a_s = a0[jnp.argmin(nll0)]
    a1 = jnp.clip(a_s + _DA1, -0.99, 0.999)
    qs = jnp.asarray(_Q, y.dtype)
    nll1, s2 = jax.vmap(lambda a: jax.vmap(lambda q: _neg_loglik(y, a, q))(qs))(a1)
    k = jnp.argmin(nll1)
    i, j = k // nll1.shape[1], k % nll1.shape[1]
    stat = jnp.maximum(jnp.min(nll0) - nll1[i, j], 0.0)
    return stat, a1[i], qs[j], jnp.sqrt(s2[i, j]) * sd, a_s


def drift_noise_model(a, q):
    """$(C, D)$ of the drift model with pole `a` and ratio `q` (see the module
    docstring): the MA(1) root $\\theta$ solves $\\theta / (1 + \\theta^2) = \\gamma_1 / \\gamma_0$
    with $\\gamma_0 = q (1 + a^2) + 2$, $\\gamma_1 = -(a q + 1)$."""
    rho = -(a * q + 1.0) / (q * (1.0 + a * a) + 2.0)
    theta = jnp.clip((1.0 - jnp.sqrt(jnp.maximum(1.0 - 4.0 * rho * rho, 0.0))) / (2.0 * rho), -0.999, 0.999)
    c = jnp.stack([jnp.ones_like(theta), theta])
    d = jnp.convolve(jnp.stack([jnp.ones_like(a), -a]), jnp.array([1.0, -1.0], dtype=jnp.result_type(a)))
    return c, d
