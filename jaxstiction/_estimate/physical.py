r"""Physical stiction model: Kano's $S$, $J$ fitted jointly with the linear part.

$S$ and $J$ enter non-smoothly, so (as Jelali 2008, but vectorised) a grid over
$(S, J)$ is evaluated in one `vmap`, with the linear part solved by least squares at
each point (separable least squares); the best region is then refined on a finer
grid with an output-error fit of the linear part at every point. The finer grid also
gives a profile-likelihood interval for $S$ and $J$.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from .._blocks import Kano
from .._filters import lagged, lfilter, steady_state
from .._linalg import gram_cholesky, HouseholderQR, is_stable, lstsq as _lstsq
from .._misc import chunked_vmap, coarse, first_min
from .._spline import scale_input
from .reduce import LowOrder
from .settings import PhysicalSettings


# Bytes per record sample that one output-error fit of the final stage holds while it
# runs (its Jacobian, simulations and solver state); measured with XLA's memory
# analysis of `estimate`, see `PhysicalSettings.memory_budget`.
FIT_BYTES_PER_SAMPLE = 400


def fits_at_once(length: int, memory_budget: int) -> int:
    """How many output-error fits of a `length`-sample record run side by side within
    `memory_budget` bytes (at least one)."""
    return int(max(1, memory_budget // (FIT_BYTES_PER_SAMPLE * length)))


def _arx_design(x, y, order: int, delay):
    """Regressors of $A y = q^{-d} B x + c$: `[-y lags, x lags (delayed), 1]`."""
    xd = _delay(x, delay)
    return jnp.concatenate([-lagged(y, order), lagged(xd, order), jnp.ones((y.shape[0], 1), y.dtype)], axis=1)


def arx_loss(x, y, weights, order: int, delays, max_delay: int, start=0):
    """Mean squared one-step error of the ARX model $A y = q^{-d}B x$ for each delay
    $d$ in `delays` (all at most `max_delay`), over the samples with `weights` (in
    {0, 1}) on and index at least `start` (and late enough for every lag).

    The grid search needs the criterion only, never the coefficients, so it is read
    off the triangular factor of the augmented matrix `[X, y]`: its last diagonal
    entry is the residual norm. The factor comes from the column-scaled Gram matrix
    (`_linalg.gram_cholesky`, a small Cholesky). With `x` and `y` scaled to unit range
    the Gram matrix is well enough conditioned that the criterion agrees with the QR
    least-squares residual to ~1e-9 relative (tested against a NumPy `lstsq`
    reference), far below the differences the search ranks.

    The delays share one Gram matrix: that of `[-y lags, x lags 1..order+max_delay-1,
    1, y]`, from which each delay's rows and columns are picked (the regressors of
    delay $d$ are the output lags and input lags $d..d+$`order`$-1$). Samples before
    every lag exists are not scored, so the pick is exact.

    Only the input's columns change from one grid point to the next (a valve path
    and its first move, `start`), so the block of the output columns `[-y lags, 1,
    y]` is read off suffix sums over the samples, which do not depend on `x` (under
    `vmap` over grid points they are computed once), and only the products with the
    input lags are formed per point: about a fifth of the memory traffic of forming
    the whole lagged matrix per point, which bounded the grid's speed."""
    N = y.shape[0]
    n_x = order + max_delay - 1
    w0 = weights * (jnp.arange(N) >= order + max(3, max_delay - 1))
    Y = jnp.concatenate([-lagged(y, order), jnp.ones((N, 1), y.dtype), y[:, None]], axis=1)
    YY = jnp.cumsum((w0[:, None, None] * Y[:, :, None] * Y[:, None, :])[::-1], axis=0)[::-1]
    YY = jnp.concatenate([YY, jnp.zeros((1,) + YY.shape[1:], YY.dtype)])  # suffix sums; row N: none
    lo = jnp.clip(jnp.asarray(start), 0, N)
    G_yy = YY[lo]
    w = w0 * (jnp.arange(N) >= lo)
    X = lagged(x, n_x)
    Xw = X * w[:, None]
    G_xy = Xw.T @ Y
    G_xx = Xw.T @ X
    k = order
    G = jnp.block([
        [G_yy[:k, :k], G_xy[:, :k].T, G_yy[:k, k:]],
        [G_xy[:, :k], G_xx, G_xy[:, k:]],
        [G_yy[k:, :k], G_xy[:, k:].T, G_yy[k:, k:]],
    ])
    ys = jnp.arange(order)
    tail = jnp.array([order + n_x, order + n_x + 1])
    count = jnp.sum(w)

    def one(d):
        idx = jnp.concatenate([ys, order + d - 1 + jnp.arange(order), tail])
        return gram_cholesky(G[idx][:, idx])[-1, -1] ** 2 / count

    return jax.vmap(one)(jnp.atleast_1d(delays))


def valve_from(op, S, J, weights, burn: int, start, count: int):
    """Kano valve position for `op` from candidate initial state number `start` of
    `Kano.initial_states(op[:8 * count], count)` (`start = -1`, the last, is the
    default start: at rest at `op[0]`, last travel up), the weights of the samples from its first
    move on (plus `burn` samples of linear transient), and the index they start at.

    Before its first move the valve rests at an unknown position; those samples are
    not scored. The mean loss over the scored samples is the criterion, so the
    unknown start does not decide the search.
    """
    blk = Kano(S, J)
    cands = blk.initial_states(op[: 8 * count], count)
    rest = blk.init(op[0])
    cands = jax.tree.map(lambda c, r: jnp.concatenate([c, jnp.asarray(r)[None]]), cands, rest)
    state = jax.tree.map(lambda t: t[start], cands)
    x = blk(op, state)
    moved = x != x[0]
    first = jnp.where(jnp.any(moved), jnp.argmax(moved), op.shape[0])
    return x, weights * (jnp.arange(op.shape[0]) >= first + burn), first + burn


def _delay(x, d):
    # x delayed by d - 1 extra samples (lagged() supplies one), padded with x[0].
    idx = jnp.arange(x.shape[0]) - (d - 1)
    return jnp.where(idx >= 0, x[jnp.clip(idx, 0)], x[0])


class OEModel(eqx.Module):
    linear: LowOrder
    offset: Float[Array, ""]
    state: Float[Array, " s"]

    def simulate(self, x, max_delay: int, *, initial_state=True):
        b, a = self.linear.polynomials(max_delay)
        zi = steady_state(b, a, x[0])
        if initial_state:
            zi = zi + self.state
        return lfilter(b, a, x, zi) + self.offset


def fit_oe(x, y, weights, order: int, delay, max_delay: int, max_steps=40) -> tuple[OEModel, Array]:
    r"""Box–Jenkins fit of $y = q^{-d} B/A\, x + c + \frac{C}{D} e$ (first-order $C/D$) by
    Levenberg–Marquardt on the prediction error $\varepsilon = \frac{D}{C}(y - q^{-d}\frac{B}{A}x - c)$,
    from an ARX start; the initial filter state is estimated too.

    The noise model matters: in closed loop the input is correlated with the noise
    through the controller, and a pure output-error fit ($C/D = 1$) is biased.
    Returns the deterministic part (`OEModel`), the noise polynomials `(C, D)` and the
    solver result."""
    L = order
    X = _arx_design(x, y, L, delay)
    w = weights * (jnp.arange(y.shape[0]) >= L + max_delay)
    th = _lstsq(X * w[:, None], y * w, 1e-10)
    a0, b0 = th[:L], th[L : 2 * L]
    ok0 = is_stable(jnp.concatenate([jnp.ones((1,), y.dtype), a0]), margin=1e-3)
    a0 = jnp.where(ok0, a0, jnp.zeros_like(a0).at[0].set(-0.5))
    mask = jnp.ones((L,), y.dtype)
    nstate = max_delay + L - 1
    one = jnp.ones((1,), y.dtype)

    def model(theta):
        a, b, c, s, _, _ = theta
        return OEModel(LowOrder(a, b, delay, mask), c, s)

    def resid(theta, _):
        cn, dn = theta[4], theta[5]
        v = y - model(theta).simulate(x, max_delay)
        # keep C/D invertible and stable inside the search
        cn = jnp.tanh(cn)
        dn = jnp.tanh(dn)
        eps = lfilter(jnp.concatenate([one, dn]), jnp.concatenate([one, cn]), v)
        return weights * eps

    z1 = jnp.zeros((1,), y.dtype)
    theta0 = (a0, b0, jnp.zeros((), y.dtype), jnp.zeros((nstate,), y.dtype), z1, z1)
    m0 = model(theta0)
    c0 = jnp.sum(weights * (y - m0.simulate(x, max_delay))) / jnp.sum(weights)
    theta0 = (a0, b0, c0, theta0[3], z1, z1)
    sol = optx.least_squares(
        resid, optx.LevenbergMarquardt(rtol=1e-7, atol=1e-9, linear_solver=HouseholderQR()), theta0,
        max_steps=max_steps, throw=False,
    )
    m = model(sol.value)
    ok = is_stable(m.linear.polynomials(max_delay)[1])
    m = jax.tree.map(lambda n, s: jnp.where(ok, n, s), m, model(theta0))
    c = jnp.concatenate([one, jnp.where(ok, jnp.tanh(sol.value[4]), 0.0)])
    d = jnp.concatenate([one, jnp.where(ok, jnp.tanh(sol.value[5]), 0.0)])
    return m, (c, d), sol.result

def models_at(models, i):
    """Member `i` of a batch of models."""
    return jax.tree.map(lambda t: t[i], models)


class PhysicalFit(eqx.Module):
    """Result of [`jaxstiction.internal.fit_physical`][] (S, J in % of OP span)."""

    S: Float[Array, ""]
    J: Float[Array, ""]
    S_interval: Float[Array, " 2"]
    J_interval: Float[Array, " 2"]
    delay: Array
    model: OEModel
    v_oe: Float[Array, ""]
    noise: tuple
    grid_S: Float[Array, " g"]
    grid_J: Float[Array, " g"]
    grid_loss: Float[Array, " g"]
    result: optx.RESULTS


@eqx.filter_jit
def fit_physical(op, y, weights, lo, hi, settings: PhysicalSettings = PhysicalSettings()) -> PhysicalFit:
    r"""Fit Kano's stiction model ($S$, $J$ in % of span) and a low-order output-error
    linear part to OP `op` (raw %) and scaled output `y`.

    `lo`, `hi`: the OP range used to scale the valve position to [-1, 1] (as for the
    spline model). `weights` marks estimation samples.
    """
    dtype = y.dtype
    span = hi - lo
    count = jnp.sum(weights)
    delays = jnp.arange(1, settings.max_delay + 1)
    # The loss is very rugged in (S, J): a slowly ramping controller output crosses
    # the slip thresholds at sample-exact times, so a 0.25 % change in S can move a
    # slip event. Hence a dense separable-LS search (cheap ARX least squares at each
    # point, evaluated in batches) before any output-error fit.

    # The valve's state at the start of the record is unknown, so each (S, J) is
    # scored on the samples after its model valve first moves (plus a transient),
    # as a mean. Charging the skipped samples instead lets the unknown start decide
    # the search: the true (S, J) from the default start often moves late. A model
    # valve that stays put for most of the record is not a fit: it needs at least
    # half of the estimation samples.
    def charged(v, wb):
        return jnp.where(jnp.sum(wb) >= 0.5 * count, v, jnp.inf)

    starts_all = jnp.arange(4 * settings.init_count + 3)
    default = starts_all[-1]

    def arx_at(s, j, ds, cands):
        def one(c):
            x, wb, first = valve_from(op, s, j, weights, settings.burn_in, c, settings.init_count)
            x = scale_input(x, lo, hi)
            return charged(arx_loss(x, y, weights, settings.arx_order, ds, settings.max_delay, first), wb)

        loss = jax.vmap(one)(cands)  # (cands, delays)
        flat = first_min(loss.ravel())
        return jnp.min(loss), ds[flat % ds.shape[0]], cands[flat // ds.shape[0]]

    def search(S, J, ds=delays, cands=jnp.array([default])):
        # Chunk size from a memory budget: each grid point holds one regressor matrix
        # of the record's length per start.
        per_point = op.shape[0] * cands.shape[0] * (2 * settings.arx_order + settings.max_delay + 2)
        chunk = int(max(1, min(settings.chunk, settings.memory_budget // (8 * per_point))))
        return chunked_vmap(lambda s, j: arx_at(s, j, ds, cands), (S, J), chunk)

    # Stage 1: S in [0, max_band * span], J = S * fraction, every delay.
    Sg = jnp.linspace(0.0, settings.max_band, settings.num_S, dtype=dtype) * span
    fr = jnp.linspace(0.0, 1.0, settings.num_J, dtype=dtype)
    S1 = jnp.repeat(Sg, settings.num_J)
    J1 = S1 * jnp.tile(fr, settings.num_S)
    l1, d1, _ = search(S1, J1)
    top = jnp.argsort(coarse(l1))[: settings.starts]
    # The delay barely interacts with S and J: the best stage-1 point's is kept.
    delay = d1[top[0]][None]
    # Stage 2: around each of the best stage-1 points, S on a fine grid (the loss is
    # a narrow ridge in S: cells ~0.05 % wide on a 1500-sample record) and J on a
    # coarser one.
    dS = span * settings.max_band / (settings.num_S - 1)
    rs = jnp.linspace(-1.0, 1.0, settings.refine_S, dtype=dtype)
    rj = jnp.linspace(-1.0, 1.0, settings.refine, dtype=dtype)
    dJ = jnp.maximum(S1[top] / (settings.num_J - 1), dS)
    S2 = jnp.clip(S1[top][:, None] + dS * jnp.repeat(rs, settings.refine)[None, :], 0.0, None).ravel()
    J2 = jnp.clip(J1[top][:, None] + dJ[:, None] * jnp.tile(rj, settings.refine_S)[None, :], 0.0, None).ravel()
    J2 = jnp.minimum(J2, S2)
    l2, _, _ = search(S2, J2, delay)
    # The loss is a narrow ridge (cells of width ~0.05 % in S on a 1500-sample
    # record), finer than any affordable grid: refine the best point of each of the
    # `polish_starts` best stage-2 blocks by alternating fine line searches in S and J.
    R2 = settings.refine * settings.refine_S
    blk_best = first_min(l2.reshape(settings.starts, R2), axis=1) + jnp.arange(settings.starts) * R2
    lb = l2[blk_best]
    # overlapping blocks often share their best point: keep distinct points only
    same = (jnp.abs(S2[blk_best][:, None] - S2[blk_best][None, :]) < 1e-9) & (
        jnp.abs(J2[blk_best][:, None] - J2[blk_best][None, :]) < 1e-9)
    lc = coarse(lb)
    earlier = (lc[None, :] < lc[:, None]) | ((lc[None, :] == lc[:, None]) & (
        jnp.arange(settings.starts)[None, :] < jnp.arange(settings.starts)[:, None]))
    lb = jnp.where(jnp.any(same & earlier, axis=1), jnp.inf, lb)
    order = jnp.argsort(coarse(lb))[: settings.polish_starts]
    pick = blk_best[order]
    s0, j0, dJk = S2[pick], J2[pick], dJ[order]
    rl = jnp.linspace(-1.0, 1.0, settings.line, dtype=dtype)
    c0 = jnp.full((settings.polish_starts,), default)

    def line_search(i, carry):
        # even i: a line in S (J clipped to S); odd i: a line in J. One traced body
        # for all `2 * rounds` searches.
        s0, j0, c0 = carry
        along_S = i % 2 == 0
        Sl = jnp.where(along_S, jnp.clip(s0[:, None] + dS * rl[None, :], 0.0, None),
                       jnp.broadcast_to(s0[:, None], (s0.shape[0], rl.shape[0])))
        Jl = jnp.where(along_S, jnp.broadcast_to(j0[:, None], Sl.shape),
                       jnp.clip(j0[:, None] + dJk[:, None] * rl[None, :], 0.0, None))
        Jl = jnp.minimum(Jl, Sl)
        ll, _, cl = search(Sl.ravel(), Jl.ravel(), delay, starts_all)
        a = first_min(ll.reshape(Sl.shape), axis=1)[:, None]
        pick = lambda g: jnp.take_along_axis(g, a, axis=1)[:, 0]  # noqa: E731
        return pick(Sl), pick(Jl), pick(cl.reshape(Sl.shape))

    s0, j0, c0 = jax.lax.fori_loop(0, 2 * settings.rounds, line_search, (s0, j0, c0))
    # Stage 3: output-error (Box-Jenkins) fits on a small grid around each refined
    # point; the best decides, and its grid gives the profile likelihood of (S, J).
    hs = dS / (settings.refine - 1)
    hjk = dJk / (settings.refine - 1)
    rr = jnp.linspace(-1.0, 1.0, settings.final, dtype=dtype)
    Sf = jnp.clip(s0[:, None] + hs * jnp.repeat(rr, settings.final)[None, :], 0.0, None)
    Jf = jnp.minimum(jnp.clip(j0[:, None] + hjk[:, None] * jnp.tile(rr, settings.final)[None, :], 0.0, None), Sf)
    delay_k = jnp.repeat(delay, settings.polish_starts)

    def fine(s, j, delay, c, steps=settings.oe_steps):
        x, wb, _ = valve_from(op, s, j, weights, settings.burn_in, c, settings.init_count)
        x = scale_input(x, lo, hi)
        m, cd, res = fit_oe(x, y, wb, settings.order, delay, settings.max_delay, steps)
        v = charged(jnp.sum((wb * (y - m.simulate(x, settings.max_delay))) ** 2) / jnp.sum(wb), wb)
        return (m, cd), jnp.where(jnp.isfinite(v), v, jnp.inf), res

    K, F = Sf.shape
    # As many fits at once as the memory budget allows (all of them on records of a
    # few thousand samples): each holds Jacobians and simulations of the record's
    # length, ~FIT_BYTES_PER_SAMPLE bytes per sample.
    fits = fits_at_once(op.shape[0], settings.memory_budget)
    (models, noises), v, res = chunked_vmap(
        fine, (Sf.ravel(), Jf.ravel(), jnp.repeat(delay_k, F), jnp.repeat(c0, F)), fits)
    kbest = first_min(jnp.min(v.reshape(K, F), axis=1))
    sel = kbest * F + jnp.arange(F)
    models, noises, res = jax.tree.map(lambda t: t[sel], (models, noises, res))
    v, Sf, Jf = v[sel], Sf[kbest], Jf[kbest]
    delay = delay_k[kbest]
    start = c0[kbest]
    hj = hjk[kbest]
    b = first_min(v)
    step = 2.0 / (settings.final - 1)
    # Profile likelihood: N_eff log(V / Vmin) <= chi2(2, 95%) = 5.99, with N_eff
    # corrected for residual autocorrelation (output-error residuals are coloured).
    x, wb, _ = valve_from(op, Sf[b], Jf[b], weights, settings.burn_in, start, settings.init_count)
    x = scale_input(x, lo, hi)
    e = wb * (y - models_at(models, b).simulate(x, settings.max_delay))
    rho = jnp.clip(jnp.sum(e[1:] * e[:-1]) / jnp.sum(e**2), 0.0, 0.99)
    neff = count * (1 - rho) / (1 + rho)
    inside = neff * jnp.log(v / v[b]) <= 5.99

    # The intervals: the region on this grid and, when asked, on a wider one around
    # the same centre (the point estimate below stays on the first grid).
    gS, gJ, gv, ghs, ghj = Sf, Jf, v, jnp.full_like(Sf, hs), jnp.full_like(Jf, hj)
    if settings.interval_span > 0:
        span = settings.interval_span
        Sw = jnp.clip(s0[kbest] + span * hs * jnp.repeat(rr, settings.final), 0.0, None)
        Jw = jnp.minimum(jnp.clip(j0[kbest] + span * hj * jnp.tile(rr, settings.final), 0.0, None), Sw)
        # 15 Levenberg-Marquardt steps: the losses, not the models, are needed here
        # (within 7e-5 of a 100-step fit on 1500-sample loops, see `SCREEN_ESTIMATE`)
        _, vw, _ = chunked_vmap(lambda *a: fine(*a, steps=min(15, settings.oe_steps)),
                                (Sw, Jw, jnp.full((F,), delay), jnp.full((F,), start)), fits)
        gS, gJ, gv = jnp.concatenate([Sf, Sw]), jnp.concatenate([Jf, Jw]), jnp.concatenate([v, vw])
        ghs = jnp.concatenate([ghs, jnp.full_like(Sw, span * hs)])
        ghj = jnp.concatenate([ghj, jnp.full_like(Jw, span * hj)])
    region = neff * jnp.log(gv / jnp.min(gv)) <= 5.99

    def interval(g, h):
        lo_ = jnp.min(jnp.where(region, g - h * step / 2, jnp.inf))
        hi_ = jnp.max(jnp.where(region, g + h * step / 2, -jnp.inf))
        return jnp.clip(jnp.stack([lo_, hi_]), 0.0, None)

    S_int = interval(gS, ghs)
    J_int = interval(gJ, ghj)
    # The loss is piecewise constant in (S, J) (slip events move at thresholds), so any
    # member of the 95 % region fits the data as well as the arg-min. Their errors on
    # new data are not symmetric: a model valve with S a little too large stays stuck
    # through an excursion that moved the real valve, and the simulation then loses
    # the real limit cycle altogether, while S a little too small only moves a slip
    # by a sample. The point estimate is therefore the region's smallest S, and at
    # that S the J nearest the region's centroid.
    cJ = jnp.sum(jnp.where(inside, Jf, 0.0)) / jnp.sum(inside)
    minS = jnp.min(jnp.where(inside, Sf, jnp.inf))
    lowest = inside & (Sf <= minS + 1e-12 * (1 + jnp.abs(minS)))
    b = jnp.argmin(jnp.where(lowest, jnp.abs(Jf - cJ), jnp.inf))
    best = models_at(models, b)
    noise = models_at(noises, b)
    return PhysicalFit(
        S=Sf[b],
        J=Jf[b],
        S_interval=S_int,
        J_interval=J_int,
        delay=delay,
        model=best,
        v_oe=v[b],
        noise=noise,
        grid_S=Sf,
        grid_J=Jf,
        grid_loss=v,
        result=jax.tree.map(lambda t: t[b], res),
    )
