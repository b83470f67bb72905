"""Two-branch cubic-spline hysteresis layer: the paper's equations (5)–(9).

All functions are pure and work on one loop; `vmap` them to batch.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def scale_input(u: Float[Array, " time"], lo, hi) -> Float[Array, " time"]:
    """Map `u` from `[lo, hi]` to `[-1, 1]` (the spline basis is built there, for
    conditioning)."""
    return 2.0 * (u - lo) / (hi - lo) - 1.0


def direction(u: Float[Array, " time"], *, threshold=0.0) -> Float[Array, " time"]:
    r"""Direction signal $h(t)$: 1 while the input rises, 0 while it falls.

    With `threshold == 0` this is the paper's literal rule (5),
    $h(t) = 1$ if $u(t) \ge u(t-1)$ else 0 (and $h(0) = 1$).

    With `threshold > 0` it is the robust rule: the direction only changes once
    the input has moved more than `threshold` away from its running extreme since
    the last change, so noise smaller than `threshold` never flips it. Tie
    `threshold` to the OP noise level, e.g. [`jaxstiction.internal.noise_threshold`][].
    """
    u = jnp.asarray(u)
    threshold = jnp.asarray(threshold, u.dtype)
    literal = jnp.concatenate([jnp.ones((1,), u.dtype), (jnp.diff(u) >= 0).astype(u.dtype)])

    def step(carry, ut):
        h, ext = carry
        ext = jnp.where(h > 0, jnp.maximum(ext, ut), jnp.minimum(ext, ut))
        down = (h > 0) & (ut < ext - threshold)
        up = (h == 0) & (ut > ext + threshold)
        h = jnp.where(down, 0.0, jnp.where(up, 1.0, h)).astype(u.dtype)
        ext = jnp.where(down | up, ut, ext)
        return (h, ext), h

    _, robust = jax.lax.scan(step, (jnp.ones((), u.dtype), u[0]), u)
    return jnp.where(threshold > 0, robust, literal)


def noise_threshold(u: Float[Array, " time"], weights=None, *, factor=3.0):
    r"""A direction threshold tied to the OP noise level.

    Estimates the noise standard deviation $\sigma$ of `u` from its second
    differences, robustly (median absolute deviation; for white noise the second
    difference has standard deviation $\sqrt 6\,\sigma$), and returns
    `factor * sigma`. `weights` (time,) in {0, 1} restricts it to the samples marked
    1 (a second difference counts only when its three samples are all marked).
    """
    u = jnp.asarray(u)
    d2 = jnp.diff(u, n=2)
    if weights is not None:
        ok = (weights[2:] * weights[1:-1] * weights[:-2]) > 0
        d2 = jnp.where(ok, d2, jnp.nan)
    med = jnp.nanmedian(d2)
    mad = jnp.nanmedian(jnp.abs(d2 - med))
    return factor * 1.4826 * mad / jnp.sqrt(6.0)


def uniform_knots(num_knots: int, dtype=None) -> Float[Array, " knots"]:
    """`num_knots` equally spaced knots on the scaled input range `[-1, 1]` (6)."""
    return jnp.linspace(-1.0, 1.0, num_knots, dtype=dtype)


def spline_basis(
    u: Float[Array, " time"], knots: Float[Array, " knots"], mask=None
) -> Float[Array, "time basis"]:
    r"""Cubic-spline basis of (7): $|u - g_k|^3$ for the interior knots
    $g_2 \ldots g_{m-1}$, then $1, u, u^2, u^3$. Shape `(time, m + 2)`.

    `mask` (optional, shape `(m - 2,)`) zeroes unused interior knots, so that
    candidates with different knot counts share one padded shape under `vmap`.
    """
    interior = knots[1:-1]
    cubic = jnp.abs(u[:, None] - interior[None, :]) ** 3
    if mask is not None:
        cubic = cubic * mask[None, :]
    poly = jnp.stack([jnp.ones_like(u), u, u**2, u**3], axis=1)
    return jnp.concatenate([cubic, poly], axis=1)


def hysteresis_regressors(
    u: Float[Array, " time"], h: Float[Array, " time"], knots, mask=None
) -> Float[Array, "time params"]:
    r"""Regressors $\Phi(t)$ with $\hat x(t) = \Phi(t)\beta$ for the two-branch model
    $\hat x = h f_1(u) + (1-h) f_2(u)$: `[h * basis, (1 - h) * basis]`.

    The first half of $\beta$ is the ascent spline $f_1$ (7), the second the descent
    spline $f_2$ (9), sharing knots ($m_1 = m_2 = m$).
    """
    b = spline_basis(u, knots, mask)
    return jnp.concatenate([h[:, None] * b, (1.0 - h)[:, None] * b], axis=1)


def valve_curves(beta, u_grid, knots, mask=None):
    """Evaluate the ascent ($f_1$) and descent ($f_2$) curves on `u_grid` (scaled)."""
    b = spline_basis(u_grid, knots, mask)
    p = b.shape[1]
    return b @ beta[:p], b @ beta[p:]
