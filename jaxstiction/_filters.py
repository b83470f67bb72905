"""Discrete-time transfer functions in the delay operator $q^{-1}$, as pure JAX.

Polynomials are coefficient arrays from $q^0$: `b = [b0, b1, ...]`, `a = [1, a1, ...]`.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._linalg import apply_qt, householder


def _pad(b, a):
    n = max(b.shape[0], a.shape[0])
    b = jnp.concatenate([b, jnp.zeros((n - b.shape[0],), b.dtype)])
    a = jnp.concatenate([a, jnp.zeros((n - a.shape[0],), a.dtype)])
    return b, a, n


@jax.jit
def lfilter(b, a, x: Float[Array, " time"], zi=None) -> Float[Array, " time"]:
    r"""$y = \frac{B(q)}{A(q)} x$ with $a_0 = 1$ (direct form II transposed).

    `zi` is the initial filter state (length `max(len(a), len(b)) - 1`), zero by
    default. Differentiable in `b`, `a`, `x` and `zi`.
    """
    b = jnp.asarray(b, x.dtype)
    a = jnp.asarray(a, x.dtype)
    b, a, n = _pad(b, a)
    if n == 1:
        return b[0] * x
    if zi is None:
        zi = jnp.zeros((n - 1,), x.dtype)

    def step(z, xt):
        yt = b[0] * xt + z[0]
        znew = jnp.concatenate([z[1:], jnp.zeros((1,), x.dtype)]) + b[1:] * xt - a[1:] * yt
        return znew, yt

    _, y = jax.lax.scan(step, zi, x)
    return y


def steady_state(b, a, x0, dtype=None):
    """Initial state of [`jaxstiction.lfilter`][] that holds the output at its
    steady value for a constant input `x0` (as `scipy.signal.lfilter_zi * x0`).

    An integrating filter ($A(1) = 0$) has no steady state for a constant input other
    than 0; it is then started from rest (output 0), from which it ramps."""
    dtype = dtype or jnp.result_type(x0)
    b = jnp.asarray(b, dtype)
    a = jnp.asarray(a, dtype)
    b, a, n = _pad(b, a)
    a1 = jnp.sum(a)
    integrating = a1 == 0
    y0 = jnp.where(integrating, 0.0, jnp.sum(b) / jnp.where(integrating, 1.0, a1) * x0)
    # z_k = sum_{j>k} (b_j x0 - a_j y0)
    terms = b[1:] * x0 - a[1:] * y0
    return jnp.cumsum(terms[::-1])[::-1]


def freq_response(b, a, w: Float[Array, " freq"]):
    r"""$B(e^{i\omega}) / A(e^{i\omega})$ on the angular frequencies `w` (rad/sample)."""
    z = jnp.exp(-1j * w)
    kb = jnp.arange(b.shape[0])
    ka = jnp.arange(a.shape[0])
    num = jnp.sum(b[None, :] * z[:, None] ** kb[None, :], axis=1)
    den = jnp.sum(a[None, :] * z[:, None] ** ka[None, :], axis=1)
    return num / den


def step_response(b, a, n: int):
    """Response of $B/A$ to a unit step over `n` samples."""
    return lfilter(b, a, jnp.ones((n,), jnp.result_type(b, a, float)))


def lagged(x: Float[Array, " time"], n: int) -> Float[Array, "time lags"]:
    """Matrix whose column `k - 1` is `x(t - k)`, `k = 1..n`, zero before the record."""
    cols = [jnp.concatenate([jnp.zeros((k,), x.dtype), x[:-k]]) for k in range(1, n + 1)]
    return jnp.stack(cols, axis=1)


def fitness(y, yhat, mask=None):
    r"""Simulation fitness (34), in percent:
    $100\,(1 - \lVert y - \hat y\rVert / \lVert y - \bar y\rVert)$. `mask` selects
    the samples scored."""
    y = jnp.asarray(y)
    yhat = jnp.asarray(yhat)
    if mask is None:
        mask = jnp.ones_like(y)
    mean = jnp.sum(mask * y) / jnp.sum(mask)
    num = jnp.sqrt(jnp.sum(mask * (y - yhat) ** 2))
    den = jnp.sqrt(jnp.sum(mask * (y - mean) ** 2))
    return 100.0 * (1.0 - num / den)


def fitness_trend_free(y, yhat, mask, degree: int):
    r"""Simulation fitness (34), in percent, after a polynomial trend of `degree`
    (static), fitted on the samples selected by `mask` (one contiguous run, weight 1),
    is removed from the error $y - \hat y$ and from $y$:
    $100\,(1 - \lVert P(y - \hat y)\rVert / \lVert P y\rVert)$, with $P$ the
    projection off the Legendre polynomials of degree 0 to `degree` over that run.

    A slow drift at the output that no model of the loop can simulate then neither
    swamps nor tilts a comparison of two models' simulations; what is left is how
    each follows the loop's faster moves (see [`jaxstiction.verdict`][])."""
    y = jnp.asarray(y)
    mask = jnp.asarray(mask, y.dtype)
    count = jnp.sum(mask)
    t = jnp.arange(y.shape[0], dtype=y.dtype)
    start = jnp.argmax(mask > 0).astype(y.dtype)
    x = jnp.clip(2.0 * (t - start) / jnp.maximum(count - 1.0, 1.0) - 1.0, -1.0, 1.0)
    basis = [jnp.ones_like(x), x]
    for k in range(2, degree + 1):  # Legendre's recurrence
        basis.append(((2 * k - 1) * x * basis[-1] - (k - 1) * basis[-2]) / k)
    # Householder QR in pure JAX (no batched LAPACK under vmap: see `_linalg`); the
    # part of v off the basis has the norm of Q^T v below its first degree + 1 rows.
    V, _ = householder(jnp.stack(basis[: degree + 1], 1) * mask[:, None])

    def detrended_norm(v):
        return jnp.linalg.norm(apply_qt(V, mask * v)[degree + 1:])

    return 100.0 * (1.0 - detrended_norm(y - jnp.asarray(yhat)) / detrended_norm(y))
