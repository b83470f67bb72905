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

from ._blocks import kano, kano_init
from ._filters import fitness, is_stable, lagged, lfilter, steady_state
from ._reduce import LowOrder
from ._relax import _lstsq
from ._spline import scale_input


class PhysicalSettings(eqx.Module):
    """Static settings of the physical (Kano) fit.

    - `num_S`, `num_J`: stage-1 grid; `S` spans 0 to `max_band` × OP range,
      `J` spans 0 to `S`.
    - `starts`: best stage-1 points refined on a `refine` × `refine` local grid.
    - `final`: points per axis of the output-error grid (stage 3, profile likelihood).
    - `burn_in`: samples ignored after the model valve first moves (see `_burn_in`).
    - `arx_order`: order of the least-squares linear part on the coarse grid.
    - `order`: order of the output-error linear part.
    - `max_delay`: delays 1..`max_delay` are tried.
    """

    num_S: int = eqx.field(static=True, default=61)
    num_J: int = eqx.field(static=True, default=11)
    max_band: float = eqx.field(static=True, default=1.0)
    arx_order: int = eqx.field(static=True, default=4)
    order: int = eqx.field(static=True, default=2)
    max_delay: int = eqx.field(static=True, default=3)
    starts: int = eqx.field(static=True, default=8)
    refine: int = eqx.field(static=True, default=21)
    final: int = eqx.field(static=True, default=5)
    oe_steps: int = eqx.field(static=True, default=40)
    burn_in: int = eqx.field(static=True, default=10)


def _arx_design(x, y, order: int, delay):
    """Regressors of $A y = q^{-d} B x + c$: `[-y lags, x lags (delayed), 1]`."""
    xd = _delay(x, delay)
    return jnp.concatenate([-lagged(y, order), lagged(xd, order), jnp.ones((y.shape[0], 1), y.dtype)], axis=1)


def arx_loss(x, y, weights, order: int, delay):
    """Mean squared one-step error of the ARX model $A y = q^{-d}B x$ (LS by QR)."""
    X = _arx_design(x, y, order, delay)
    w = weights * (jnp.arange(y.shape[0]) >= order + 3)
    th = _lstsq(X * w[:, None], y * w, 1e-10)
    return jnp.sum((w * (y - X @ th)) ** 2) / jnp.sum(w)


def _burn_in(x, weights, burn: int):
    """Drop the samples before the model valve first moves (plus `burn` samples of
    transient): until then the valve sits at an unknown initial position that the
    model cannot know, and those samples would otherwise dominate the (S, J) search."""
    moved = jnp.abs(x - x[0]) > 0
    first = jnp.where(jnp.any(moved), jnp.argmax(moved), x.shape[0])
    return weights * (jnp.arange(x.shape[0]) >= first + burn)


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
    Returns the deterministic part (`OEModel`) and the solver result."""
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
        resid, optx.LevenbergMarquardt(rtol=1e-7, atol=1e-9), theta0, max_steps=max_steps, throw=False
    )
    m = model(sol.value)
    ok = is_stable(m.linear.polynomials(max_delay)[1])
    m = jax.tree.map(lambda n, s: jnp.where(ok, n, s), m, model(theta0))
    return m, sol.result

def physical_valve(op, S, J, model: OEModel, y0, lo, hi, max_delay: int):
    """Scaled valve position for OP `op` through Kano(S, J), starting at rest at the
    position that puts the model's steady-state output at the first PV sample `y0`
    (the valve's initial position is otherwise unknown)."""
    b, a = model.linear.polynomials(max_delay)
    gain = jnp.sum(b) / jnp.sum(a)
    x0 = (y0 - model.offset) / jnp.where(jnp.abs(gain) > 1e-12, gain, 1e-12)
    x0 = jnp.clip(lo + (x0 + 1.0) * (hi - lo) / 2.0, jnp.min(op) - (hi - lo), jnp.max(op) + (hi - lo))
    state = (x0,) + tuple(kano_init(op[0])[1:])
    return scale_input(kano(op, S, J, state=state), lo, hi)


def models_at(models, i):
    """Member `i` of a batch of models."""
    return jax.tree.map(lambda t: t[i], models)


class PhysicalFit(eqx.Module):
    """Result of [`jaxstiction.fit_physical`][] (S, J in % of OP span)."""

    S: Float[Array, ""]
    J: Float[Array, ""]
    S_interval: Float[Array, " 2"]
    J_interval: Float[Array, " 2"]
    delay: Array
    model: OEModel
    v_oe: Float[Array, ""]
    fitness: Float[Array, ""]
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

    # Samples before the model valve first moves are charged the output variance
    # (unexplained), so a late first move is not a way to skip data.
    var_y = jnp.sum(weights * (y - jnp.sum(weights * y) / count) ** 2) / count

    def charged(v, wb):
        skipped = jnp.sum(weights - wb)
        return (v * jnp.sum(wb) + skipped * var_y) / count

    def arx_at(s, j):
        x = scale_input(kano(op, s, j), lo, hi)
        wb = _burn_in(x, weights, settings.burn_in)
        return jax.vmap(lambda d: charged(arx_loss(x, y, wb, settings.arx_order, d), wb))(delays)

    def search(S, J):
        # Plain vmap: `lax.map(..., batch_size=...)` stalled XLA's CPU runtime here
        # (jaxlib 0.10.2, reproducible, all threads idle); the grid fits in memory.
        loss = jax.vmap(arx_at)(S, J)
        return jnp.min(loss, axis=1), jnp.argmin(loss, axis=1)

    # Stage 1: S in [0, max_band * span], J = S * fraction.
    Sg = jnp.linspace(0.0, settings.max_band, settings.num_S, dtype=dtype) * span
    fr = jnp.linspace(0.0, 1.0, settings.num_J, dtype=dtype)
    S1 = jnp.repeat(Sg, settings.num_J)
    J1 = S1 * jnp.tile(fr, settings.num_S)
    l1, _ = search(S1, J1)
    top = jnp.argsort(l1)[: settings.starts]
    # Stage 2: a fine local grid around each of the best stage-1 points.
    dS = span * settings.max_band / (settings.num_S - 1)
    r = jnp.linspace(-1.0, 1.0, settings.refine, dtype=dtype)
    dJ = jnp.maximum(S1[top] / (settings.num_J - 1), dS)
    S2 = jnp.clip(S1[top][:, None] + dS * jnp.repeat(r, settings.refine)[None, :], 0.0, None).ravel()
    J2 = jnp.clip(J1[top][:, None] + dJ[:, None] * jnp.tile(r, settings.refine)[None, :], 0.0, None).ravel()
    J2 = jnp.minimum(J2, S2)
    l2, d2 = search(S2, J2)
    k = jnp.argmin(l2)
    delay = delays[d2[k]]
    # Stage 3: output-error fits on a small grid around the best point, which also
    # gives the profile likelihood of (S, J).
    hs = dS / (settings.refine - 1)
    hj = dJ[k // (settings.refine**2)] / (settings.refine - 1)
    rr = jnp.linspace(-1.0, 1.0, settings.final, dtype=dtype)
    Sf = jnp.clip(S2[k] + hs * jnp.repeat(rr, settings.final), 0.0, None)
    Jf = jnp.minimum(jnp.clip(J2[k] + hj * jnp.tile(rr, settings.final), 0.0, None), Sf)

    def fine(s, j):
        x = scale_input(kano(op, s, j), lo, hi)
        wb = _burn_in(x, weights, settings.burn_in)
        m, res = fit_oe(x, y, wb, settings.order, delay, settings.max_delay, settings.oe_steps)
        v = charged(jnp.sum((wb * (y - m.simulate(x, settings.max_delay))) ** 2) / jnp.sum(wb), wb)
        return m, jnp.where(jnp.isfinite(v), v, jnp.inf), res

    models, v, res = jax.vmap(fine)(Sf, Jf)
    b = jnp.argmin(v)
    step = 2.0 / (settings.final - 1)
    # Profile likelihood: N_eff log(V / Vmin) <= chi2(2, 95%) = 5.99, with N_eff
    # corrected for residual autocorrelation (output-error residuals are coloured).
    x = scale_input(kano(op, Sf[b], Jf[b]), lo, hi)
    e = _burn_in(x, weights, settings.burn_in) * (y - models_at(models, b).simulate(x, settings.max_delay))
    rho = jnp.clip(jnp.sum(e[1:] * e[:-1]) / jnp.sum(e**2), 0.0, 0.99)
    neff = count * (1 - rho) / (1 + rho)
    inside = neff * jnp.log(v / v[b]) <= 5.99

    def interval(g, h):
        lo_ = jnp.min(jnp.where(inside, g, jnp.inf)) - h * step / 2
        hi_ = jnp.max(jnp.where(inside, g, -jnp.inf)) + h * step / 2
        return jnp.clip(jnp.stack([lo_, hi_]), 0.0, None)

    S_int = interval(Sf, hs)
    J_int = interval(Jf, hj)
    # The loss is piecewise constant in (S, J) (slip events move at thresholds), so the
    # arg-min sits anywhere on a flat cell, often at its edge. The point estimate is the
    # member of the 95 % region nearest to the region's centroid: the most margin to
    # the thresholds, hence the best chance of the same events on new data.
    cS = jnp.sum(jnp.where(inside, Sf, 0.0)) / jnp.sum(inside)
    cJ = jnp.sum(jnp.where(inside, Jf, 0.0)) / jnp.sum(inside)
    dist = ((Sf - cS) / hs) ** 2 + ((Jf - cJ) / jnp.maximum(hj, 1e-12)) ** 2
    b = jnp.argmin(jnp.where(inside, dist, jnp.inf))
    best = models_at(models, b)
    x = physical_valve(op, Sf[b], Jf[b], best, y[0], lo, hi, settings.max_delay)
    ysim = best.simulate(x, settings.max_delay)
    return PhysicalFit(
        S=Sf[b],
        J=Jf[b],
        S_interval=S_int,
        J_interval=J_int,
        delay=delay,
        model=best,
        v_oe=v[b],
        fitness=fitness(y, ysim, weights),
        grid_S=Sf,
        grid_J=Jf,
        grid_loss=v,
        result=jax.tree.map(lambda t: t[b], res),
    )
