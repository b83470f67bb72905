r"""The spline Hammerstein estimator end to end, for one loop, all candidates at once.

Pipeline for each candidate (knot count $m$, direction rule):
relaxation (15)–(16) → asymptotic weight (18) → reduction (19) over orders and
delays, ASYC (21) → output-error polish (ours) → FOE (22). Candidates share one
padded shape and run in one `vmap`.

The **polish** is this tool's addition: starting from the paper's estimate, a
Gauss–Newton minimisation of the simulation error over the spline coefficients, the
low-order linear part, an output offset and the initial filter state (standard
practice in system identification; it removes the start-up transient from the
criterion). The paper's own estimate is kept as `paper` so both can be reported.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from .._filters import fitness, lfilter, steady_state
from .._linalg import HouseholderQR, is_stable
from .._spline import hysteresis_regressors
from .gram import whitening
from .reduce import asymptotic_weight, LowOrder, reduce_model, ReductionSolution
from .relax import relax, relax_problem, RelaxSolution
from .settings import SplineSettings


class HammersteinModel(eqx.Module):
    """Spline valve + low-order linear part, in the estimator's scaled units."""

    beta: Float[Array, " p"]
    linear: LowOrder
    offset: Float[Array, ""]
    state: Float[Array, " s"]

    def simulate(self, phi, max_delay: int, *, initial_state: bool = True):
        """Simulated output for regressors `phi`; the filter starts at steady state
        for the first input (plus the estimated deviation if `initial_state`)."""
        x = phi @ self.beta
        b, a = self.linear.polynomials(max_delay)
        zi = steady_state(b, a, x[0])
        if initial_state:
            zi = zi + self.state
        return lfilter(b, a, x, zi) + self.offset


def _from_reduction(beta, low: LowOrder, phi, y, weights, max_delay):
    b, a = low.polynomials(max_delay)
    x = phi @ beta
    ys = lfilter(b, a, x, steady_state(b, a, x[0]))
    offset = jnp.sum(weights * (y - ys)) / jnp.sum(weights)
    nstate = max(b.shape[0], a.shape[0]) - 1
    return HammersteinModel(beta, low, offset, jnp.zeros((nstate,), y.dtype))


def polish(model: HammersteinModel, phi, y, weights, beta_mask, *, max_delay: int, max_steps=60):
    """Gauss–Newton on the simulation error (output error) from `model`."""
    count = jnp.sum(weights)
    phimean = jnp.sum(weights[:, None] * phi, 0) / count
    phic = (phi - phimean) * weights[:, None]
    lin_mask = model.linear.mask

    def resid(theta, _):
        beta, a, b, offset, state = theta
        m = HammersteinModel(beta, LowOrder(a, b, model.linear.delay, lin_mask), offset, state)
        err = weights * (y - m.simulate(phi, max_delay))
        xs = phic @ beta
        # Gain and level of x_hat are not identifiable apart from the linear part:
        # fix mean(x_hat) = 0 and var(x_hat) = 1 (soft rows, weight sqrt(count)).
        norm = jnp.sqrt(count) * jnp.stack([phimean @ beta, jnp.sum(xs**2) / count - 1.0])
        pins = jnp.concatenate([beta * (1 - beta_mask), a * (1 - lin_mask), b * (1 - lin_mask)])
        return jnp.concatenate([err, norm, pins])

    # Start from the normalised point.
    x = phi @ model.beta
    mu = jnp.sum(weights * x) / count
    sd = jnp.sqrt(jnp.sum(weights * (x - mu) ** 2) / count)
    beta0 = model.beta / sd
    const = jnp.zeros_like(beta0)
    p = beta0.shape[0] // 2
    # Spline constants sit at index p-4 (ascent) and 2p-4 (descent); shifting both by
    # the same amount shifts x_hat by a constant.
    const = const.at[p - 4].set(1.0).at[2 * p - 4].set(1.0)
    beta0 = beta0 - (mu / sd) * const
    b0, a0 = model.linear.polynomials(max_delay)
    gain = jnp.sum(b0) / jnp.sum(a0)
    offset0 = model.offset + gain * mu
    theta0 = (beta0, model.linear.a, model.linear.b * sd, offset0, model.state)
    sol = optx.least_squares(
        resid,
        optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10, linear_solver=HouseholderQR()),
        theta0,
        max_steps=max_steps,
        throw=False,
    )
    beta, a, b, offset, state = sol.value
    new = HammersteinModel(beta, LowOrder(a, b, model.linear.delay, lin_mask), offset, state)
    ok = is_stable(new.linear.polynomials(max_delay)[1]) & jnp.all(jnp.isfinite(beta))
    # Keep the polished model only when it is stable and no worse than the start.
    def loss(m):
        return jnp.sum((weights * (y - m.simulate(phi, max_delay))) ** 2)

    start_linear = LowOrder(model.linear.a, model.linear.b * sd, model.linear.delay, lin_mask)
    start = HammersteinModel(beta0, start_linear, offset0, model.state)
    better = ok & (loss(new) <= loss(start))
    chosen = jax.tree.map(lambda n, s: jnp.where(better, n, s), new, start)
    result = optx.RESULTS.where(ok, sol.result, optx.RESULTS.nonlinear_divergence)
    return chosen, result


class CandidateFit(eqx.Module):
    """Everything one candidate produced (a leading axis when batched)."""

    relaxation: RelaxSolution
    reduction: ReductionSolution
    paper: HammersteinModel
    model: HammersteinModel
    polish_result: optx.RESULTS
    v_oe: Float[Array, ""]
    v_oe_paper: Float[Array, ""]
    foe: Float[Array, ""]
    fitness: Float[Array, ""]
    fitness_paper: Float[Array, ""]


def fit_candidate(y, u, h, knots, knot_mask, weights, mask, settings: SplineSettings, num_knots):
    """Run the whole spline pipeline for one candidate (knots may be padded).

    `weights` marks the estimation samples, `mask` every real sample (the range
    check simulates over the whole record's OP but never looks at its PV outside
    the estimation samples)."""
    n, D = settings.arx_order, settings.max_delay
    phi = hysteresis_regressors(u, h, knots, knot_mask)
    # The relaxation runs on whitened spline regressors (phi S has an identity Gram
    # matrix on the estimation samples; masked knots stay zero columns). The basis's
    # own coordinates are so badly conditioned (coefficients of 1e4 that cancel) that
    # the sweeps' rounding kept the alternation from settling with many knots (CHEM23's
    # 10-knot candidate ran to the step cap). The valve output phi beta is unchanged.
    S, _ = whitening((phi * weights[:, None]).T @ phi, 1e-12)
    prob = relax_problem(y, phi @ S, n, weights, method=settings.compression)
    rsol = relax(prob, max_steps=settings.relax_steps)
    rsol = eqx.tree_at(lambda r: r.model.beta, rsol, S @ rsol.model.beta)
    hi = rsol.model
    x = phi @ hi.beta
    count = jnp.sum(weights)
    w, Gn, weight, variance, _, _ = asymptotic_weight(
        hi.a, hi.b, x * weights, y * weights, order=n, count=count, seg=settings.welch_segment, weights=weights
    )
    red = reduce_model(Gn, weight, w, variance, max_order=settings.max_order, max_delay=D)
    low = jax.tree.map(lambda t: t[red.best], red.models)
    paper = _from_reduction(hi.beta, low, phi, y, weights, D)
    p = phi.shape[1] // 2
    bm = jnp.concatenate([knot_mask, jnp.ones((4,), y.dtype)])
    beta_mask = jnp.concatenate([bm, bm])
    assert beta_mask.shape[0] == 2 * p
    if settings.polish:
        model, pres = polish(paper, phi, y, weights, beta_mask, max_delay=D, max_steps=settings.polish_steps)
    else:
        model, pres = paper, optx.RESULTS.successful

    def v_oe(m, initial_state):
        return jnp.sum((weights * (y - m.simulate(phi, D, initial_state=initial_state))) ** 2) / count

    voe = v_oe(model, True)
    voe_paper = v_oe(paper, False)
    dof = 2 * n + num_knots
    foe = (count + dof) / (count - dof) * voe
    ysim = model.simulate(phi, D)
    fit = fitness(y, ysim, weights)
    fit_paper = fitness(y, paper.simulate(phi, D, initial_state=False), weights)
    # A model whose simulation (driven by the whole record's OP) leaves the range of
    # the estimation PV by more than that range is never chosen: it runs away.
    big = jnp.finfo(y.dtype).max
    ymin = jnp.min(jnp.where(weights > 0, y, big))
    ymax = jnp.max(jnp.where(weights > 0, y, -big))
    span = ymax - ymin
    inside = (ysim >= ymin - settings.range_factor * span) & (ysim <= ymax + settings.range_factor * span)
    sane = jnp.all(inside | (mask == 0))
    foe = jnp.where(sane, foe, jnp.inf)
    return CandidateFit(rsol, red, paper, model, pres, voe, voe_paper, foe, fit, fit_paper)


def candidate_knots(settings: SplineSettings, dtype):
    """Padded knots and masks for all `settings.knot_counts` (uniform on [-1, 1])."""
    M = max(settings.knot_counts)
    knots, masks = [], []
    for m in settings.knot_counts:
        g = jnp.linspace(-1.0, 1.0, m, dtype=dtype)
        # pad interior knots at 0 (masked out), keep the end knots.
        inner = jnp.concatenate([g[1:-1], jnp.zeros((M - m,), dtype)])
        knots.append(jnp.concatenate([g[:1], inner, g[-1:]]))
        masks.append(jnp.concatenate([jnp.ones((m - 2,), dtype), jnp.zeros((M - m,), dtype)]))
    return jnp.stack(knots), jnp.stack(masks), jnp.asarray(settings.knot_counts)


def fit_spline_candidates(y, u, directions, weights, mask, settings: SplineSettings) -> CandidateFit:
    r"""Fit every (direction rule × knot count) candidate in one vmapped call.

    **Arguments:**

    - `y`: scaled output (time,); `u`: input scaled to [-1, 1] (time,).
    - `directions`: (rules, time) direction signals, e.g. literal and robust.
    - `weights`: (time,) 1 on estimation samples, 0 elsewhere; `mask`: (time,) 1 on
      real samples, 0 on padding.
    - `settings`: [`jaxstiction.SplineSettings`][].

    **Returns:** a [`jaxstiction.internal.CandidateFit`][] with leading axes (rules, knots).
    """
    knots, masks, counts = candidate_knots(settings, y.dtype)
    R, K = directions.shape[0], knots.shape[0]
    ri = jnp.repeat(jnp.arange(R), K)
    ki = jnp.tile(jnp.arange(K), R)
    # One candidate at a time (lax.map): memory stays that of one candidate's
    # regressors, which matters for long records.
    out = jax.lax.map(
        lambda ik: fit_candidate(y, u, directions[ik[0]], knots[ik[1]], masks[ik[1]], weights, mask, settings,
                                 counts[ik[1]]),
        (ri, ki),
    )
    return jax.tree.map(lambda t: t.reshape((R, K) + t.shape[1:]), out)
