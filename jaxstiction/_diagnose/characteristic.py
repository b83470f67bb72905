r"""Valve characteristic: does an equal-percentage valve explain where the loop operates?

A nominal model with a linear valve states its operating point: the process sees
$x - x_0$ (`op_offset`) and PV sits at `pv_offset` plus the process's response. An
equal-percentage valve of rangeability $R$ passes $100\,(R^{x/100} - 1)/(R - 1)$
instead, so in closed loop the controller holds OP where that characteristic
delivers what the process needs: for $R = 15$ near 77 % of OP instead of 50 %. The
diagnosis's grid statistic refits $B$ and the offset for every candidate, which
absorbs that shift and leaves only the characteristic's curvature over the OP range
visited; over a few percent of OP that curvature is small (P3 with $R = 15$: not
significant on two seeds of five, with the nominal's held-out fitness near −600 %).

This test keeps what the nominal states. Each candidate is the nominal with an
equal-percentage block added and nothing refitted, so its only parameter is $R$:

$$r_R = z - G(q)\,\big(f_R(x) - x\big),$$

with $z$ the nominal's simulation error and $G$ its process. The statistic is the
log-likelihood ratio of the best $R$ over the nominal itself, from the residuals
whitened by the diagnosis's noise model. Even the mildest characteristic searched
($R = 3$) moves a valve at 50 % by 13 % of its travel, so a nominal that is right
scores far below zero, and so does one whose error is of another kind (dynamics, a
band, a drift): the test fires only when a characteristic's shift of the operating
point is there. Its null comes from the diagnosis's bootstrap noise records
(the nominal plus noise).
"""

import jax
import jax.numpy as jnp
import numpy as np

from .._blocks import EqualPercentage
from .._filters import lfilter


# NumPy constants: importing the package must not create a JAX backend
RANGEABILITIES = np.geomspace(3.0, 100.0, 36)  # equal-percentage valves searched (typical R: 20-50)


def _through_process(b, a, x):
    """$G(q) x$ with the process at rest at $x(0)$ before the record."""
    gain = jnp.sum(b) / jnp.sum(a)
    return lfilter(b, a, x - x[0]) + gain * x[0]


@jax.jit
def characteristic_statistics(op_in, records, b, a, c, d, w):
    """The operating-point statistic of every record, and each candidate's loss.

    **Arguments:** `op_in`: the nominal chain's output (valve position, %), `(N,)`;
    `records`: nominal simulation errors, `(B, N)` (the observed one first, then the
    bootstrap's noise records); `b`, `a`: the nominal process with its delay folded
    into `b`; `c`, `d`: the noise model used to whiten; `w`: weights of the samples
    scored.

    **Returns:** `(T, losses)`: `T[i] = n log(loss_nominal / min_R loss_R)` on record
    `i` (`n` the weights' sum), and the mean whitened losses, `(B, len(R))`, per record
    and candidate, for the profile of $R$.
    """
    R = jnp.asarray(RANGEABILITIES, op_in.dtype)
    shift = jax.vmap(lambda r: EqualPercentage(r)(op_in) - op_in)(R)  # (R, N)
    white = jax.vmap(lambda x: lfilter(d, c, _through_process(b, a, x)))(shift)  # (R, N)
    wr = jax.vmap(lambda r: lfilter(d, c, r))(records)  # (B, N)
    n = jnp.sum(w)
    loss0 = jnp.sum(w * wr**2, axis=1)
    # |wr - white|^2 expanded: no (B, R, N) array
    losses = loss0[:, None] - 2.0 * (wr * w) @ white.T + jnp.sum(w * white**2, axis=1)[None, :]
    losses = jnp.maximum(losses, 1e-300)
    T = n * jnp.log(loss0 / jnp.min(losses, axis=1))
    return T, losses / n


def rangeability_profile(nll) -> tuple[float, tuple[float, float]]:
    """The best $R$ and its 95 % profile interval from `nll` (`n log loss` on the grid
    `RANGEABILITIES`): a parabola in $\\log R$ through the grid's best point and its
    neighbours (the likelihood is sharp, often narrower than the grid's step); the
    grid's own points when the best lies on its edge or the parabola is not convex."""
    nll = np.asarray(nll, float)
    lr = np.log(RANGEABILITIES)
    j = int(np.argmin(nll))
    inside = RANGEABILITIES[nll - nll[j] <= 3.84]
    grid = float(RANGEABILITIES[j]), (float(inside.min()), float(inside.max()))
    if j == 0 or j == len(nll) - 1:
        return grid
    x, y = lr[j - 1:j + 2], nll[j - 1:j + 2]
    c2, c1, _ = np.polyfit(x - x[1], y, 2)
    if not c2 > 0:
        return grid
    v = -c1 / (2 * c2)
    half = np.sqrt(3.84 / c2)  # nll rises by 3.84 (chi2(1), 95 %) at v +- half
    return float(np.exp(x[1] + v)), (float(np.exp(x[1] + v - half)), float(np.exp(x[1] + v + half)))
