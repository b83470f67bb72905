r"""A compensator until the repair: a knocker or constant reinforcement, designed on
the identified closed loop.

The knocker (Hägglund 2002; [`jaxstiction.Knocker`][]) adds short pulses to OP in the
direction OP is moving, so a sticky valve is knocked through its stickband in small
steps instead of sticking until the controller's integral has wound up a slip.
Constant reinforcement (Ivan and Lakshminarayanan 2009) is the knocker whose pulse
never ends (width and period 1): a bias of amplitude $a$ in the direction of OP's
last move, so a reversal of OP crosses the band at once. The
three parameters (amplitude $a$, width $\tau$, period $h$) are chosen on the
fitted loop replayed under the disturbance it met (see `replay`), minimising

$$\frac{\sigma_e(a, \tau, h)}{\sigma_{e,\text{as is}}} + w\,\frac{T(a, \tau, h)}{T_\text{as is}},$$

$\sigma_e$ the standard deviation of SP − PV and $T$ the valve travel (wear is the
knocker's price; $w$ = `CompensateSettings.travel_weight`). A knocker's effect hangs
on the band to a few percent, so each candidate is scored by its worst objective over
the fitted valve and four neighbours (`valve_neighbours`), each against its own run
without a knocker, and none is chosen when no candidate beats doing nothing.
The candidates come two ways:

- `"grid"` (default): every point of a [`jaxstiction.KnockerGrid`][] (knocks and
  constant reinforcement) simulated with the fitted Kano valve, all at once in one
  vmapped closed-loop run;
- `"gradient"`: gradient descent (Adam) on $\log a$ and a continuous $\tau$ through
  a smoothed Kano valve (`SmoothKano`), from a few periods of the grid, each result
  then scored with the exact valve beside the grid's constant reinforcement.

`benchmarks/whatif.py` measures both (the method page *What fixing the valve would buy*).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._control.closedloop import closed_loop, ClosedLoopRun, Knocker, SmoothKano, with_valve
from .._control.controller import Controller
from .._misc import first_min, stack_trees
from .._models import LoopModel
from .replay import Replay
from .settings import CompensateSettings
from .stats import loop_stats, LoopStats


METHODS = ("grid", "gradient")


class Design(eqx.Module):
    """A knocker designed on one model (`design_knocker`).

    - `knocker`: the chosen [`jaxstiction.Knocker`][] (exact pulses);
    - `objective`: its design objective (see the module notes; 1 + w for no knocker);
    - `grid_objective`: the objective of every candidate, the worst over the fitted
      valve and its neighbours (`inf` where a run is not finite;
      `method="gradient"`: the gradient results' exact objectives); a candidate
      that does not lower the error by `min_gain` everywhere keeps its objective
      here but is not chosen;
    - `compensated`: [`LoopStats`] of the compensated run; `run`: the run itself.
    """

    knocker: Knocker
    objective: Float[Array, ""]
    grid_objective: Float[Array, " points"]
    compensated: LoopStats
    run: ClosedLoopRun


def _runs(model: LoopModel, controller: Controller, rp: Replay, knockers: Knocker) -> ClosedLoopRun:
    """Closed-loop runs of one model under a batch of knockers."""
    return jax.vmap(lambda k: closed_loop(model, controller, rp.sp_sim, rp.disturbance, rp.initial, rp.op0, k))(
        knockers)


def _objective(stats: LoopStats, base: LoopStats, weight: float):
    e = stats.error_std / jnp.maximum(base.error_std, 1e-300)
    t = stats.travel / jnp.maximum(base.travel, 1e-300)
    return jnp.where(jnp.isfinite(e) & jnp.isfinite(t), e + weight * t, jnp.inf)


def _knockers(points, S) -> Knocker | None:
    """`(amplitude factor, width, period)` points as a batch of exact knockers, the
    amplitudes multiples of `S`; `None` for no points."""
    if not points:
        return None
    dtype = jnp.result_type(S)
    fa = jnp.asarray([p[0] for p in points], dtype)
    width = jnp.asarray([p[1] for p in points], dtype)
    period = jnp.asarray([p[2] for p in points], jnp.int32)
    return Knocker(amplitude=fa * jnp.maximum(S, 1e-3), width=width, period=period)


def grid_knockers(S, J, settings: CompensateSettings) -> Knocker:
    """Every grid point as a batch of exact knockers; amplitudes are multiples of
    `S` (the fitted band: the OP step that moves a stuck valve either way is at most
    S)."""
    return _knockers(settings.grid.points(), S)


def reinforcement_knockers(S, settings: CompensateSettings) -> Knocker | None:
    """The grid's constant reinforcement (`KnockerGrid.reinforcement` times `S`) as
    knockers of width and period 1; `None` when the grid has none."""
    return _knockers(settings.grid.reinforcement_points(), S)


def no_knock(dtype) -> Knocker:
    """The knocker that does nothing (amplitude 0)."""
    return Knocker(amplitude=jnp.zeros((), dtype), width=jnp.ones((), dtype), period=jnp.asarray(2, jnp.int32))


def valve_neighbours(model: LoopModel, settings: CompensateSettings) -> LoopModel:
    """`model` with its Kano valve at S × (1 ∓ `robust_S`) and at J ∓ `robust_J` × S
    (J within [0, S]): four models stacked along a leading axis."""
    S, J = model.chain[0].S, model.chain[0].J
    dS, dJ = settings.robust_S * S, settings.robust_J * S
    pairs = [(S - dS, J), (S + dS, J), (S, J - dJ), (S, J + dJ)]
    return stack_trees(*[with_valve(model, s, jnp.clip(j, 0.0, s)) for s, j in pairs])


def design_knocker(model: LoopModel, controller: Controller, rp: Replay, mask, ts, base: LoopStats,
                   settings: CompensateSettings, threshold: float) -> Design:
    """The knocker for `model` (a Kano valve first) in closed loop with `controller`
    under the replay `rp`; `base`: the as-is run's stats (the objective's scale on
    the fitted valve). Each candidate is scored by its worst objective over the
    fitted valve and its neighbours (`valve_neighbours`), each against its own run
    without a knocker; a candidate that does not lower the error's standard
    deviation by `settings.min_gain` on every one of them is not chosen. No knocker
    (objective 1 + w) is chosen when no candidate qualifies and beats it."""
    S, J = model.chain[0].S, model.chain[0].J
    w = settings.travel_weight

    def stats(run):
        return loop_stats(run.pv, rp.sp_stat, run.valve, mask, ts, threshold)

    none = no_knock(jnp.result_type(S))
    if settings.method == "grid":
        parts = [grid_knockers(S, J, settings)]
    else:
        parts = [gradient_knockers(model, controller, rp, mask, ts, base, settings),
                 reinforcement_knockers(S, settings)]
    # no knocker first, so that a tie keeps it
    parts = [jax.tree.map(lambda n: jnp.broadcast_to(n, (1,) + n.shape), none)] + [p for p in parts if p is not None]
    ks = jax.tree.map(lambda *k: jnp.concatenate(k), *parts)
    runs = _runs(model, controller, rp, ks)
    st = jax.vmap(stats)(runs)

    def scored(s):  # the objective, and whether the error falls by `min_gain` at least
        none_s = jax.tree.map(lambda t: t[0], s)
        gains = s.error_std <= (1.0 - settings.min_gain) * none_s.error_std
        return _objective(s, none_s, w), gains

    def on_neighbour(m):
        return scored(jax.vmap(stats)(_runs(m, controller, rp, ks)))

    obj, gains = scored(st)
    n_obj, n_gains = jax.vmap(on_neighbour)(valve_neighbours(model, settings))
    robust = jnp.maximum(obj, jnp.max(n_obj, axis=0))
    # a knocker that does not buy `min_gain` everywhere is not a candidate (no knocker, first, stays)
    enough = (gains & jnp.all(n_gains, axis=0)).at[0].set(True)
    i = first_min(jnp.where(enough, robust, jnp.inf))
    pick = lambda t: t[i]  # noqa: E731
    knocker = jax.tree.map(pick, ks)
    return Design(knocker=knocker, objective=robust[i], grid_objective=robust[1:],
                  compensated=jax.tree.map(pick, st), run=jax.tree.map(pick, runs))


def gradient_knockers(model: LoopModel, controller: Controller, rp: Replay, mask, ts, base: LoopStats,
                      settings: CompensateSettings) -> Knocker:
    """Knockers found by gradient descent through a smoothed valve (see the module
    notes): one per start (periods spread over the grid's, width 1, the grid's
    median amplitude), each amplitude and width refined by `gradient_steps` Adam
    steps; returned with exact pulses (width rounded, at least 1)."""
    S, J = model.chain[0].S, model.chain[0].J
    dtype = jnp.result_type(S)
    grid = settings.grid
    periods = sorted(grid.periods)
    k = settings.gradient_starts
    idx = [round(i * (len(periods) - 1) / max(k - 1, 1)) for i in range(k)]
    period = jnp.asarray([max(periods[i], 2) for i in idx], jnp.int32)
    amps = sorted(grid.amplitudes)
    scale = jnp.maximum(S, 1e-3)
    x0 = jnp.stack([jnp.full((k,), jnp.log(amps[len(amps) // 2]), dtype), jnp.ones((k,), dtype)], axis=1)
    smooth = eqx.tree_at(lambda m: m.chain[0], model, SmoothKano(S, J, settings.smooth * jnp.maximum(S, 1.0)))
    loss = smooth_objective(smooth, controller, rp, mask, ts, base, settings.travel_weight)

    def fit_one(x, h):
        def f(x):
            return loss(Knocker(jnp.exp(x[0]) * scale, x[1], h, soft=0.5))

        g = jax.grad(f)
        b1, b2, lr = 0.9, 0.999, settings.gradient_rate

        def step(i, c):
            x, m, v = c
            gi = g(x)
            gi = jnp.where(jnp.isfinite(gi), gi, 0.0)
            m = b1 * m + (1 - b1) * gi
            v = b2 * v + (1 - b2) * gi**2
            t = i + 1.0
            x = x - lr * (m / (1 - b1**t)) / (jnp.sqrt(v / (1 - b2**t)) + 1e-8)
            x = x.at[1].set(jnp.clip(x[1], 0.6, h / 2))
            return x, m, v

        z = jnp.zeros_like(x)
        return jax.lax.fori_loop(0, settings.gradient_steps, step, (x, z, z))[0]

    xs = jax.vmap(fit_one)(x0, period)
    width = jnp.maximum(jnp.round(xs[:, 1]), 1.0)
    return Knocker(amplitude=jnp.exp(xs[:, 0]) * scale, width=width, period=period)


def smooth_objective(model: LoopModel, controller: Controller, rp: Replay, mask, ts, base: LoopStats,
                     weight: float):
    """The design objective of a knocker (see the module notes) on `model` with a
    smooth valve, differentiable in the knocker's amplitude and width: the travel's
    |Δ| is $\\sqrt{\\Delta^2 + \\delta^2}$ with δ = 1e-3 % of span."""
    w = (mask > 0).astype(rp.sp_sim.dtype)
    count = jnp.maximum(jnp.sum(w), 1.0)
    hours = count * ts / 3600.0

    def f(knocker: Knocker):
        run = closed_loop(model, controller, rp.sp_sim, rp.disturbance, rp.initial, rp.op0, knocker)
        e = (rp.sp_stat - run.pv) * w
        m = jnp.sum(e) / count
        std = jnp.sqrt(jnp.sum(w * (e - m) ** 2) / count)
        travel = jnp.sum(w[1:] * w[:-1] * jnp.sqrt(jnp.diff(run.valve) ** 2 + 1e-6)) / hours
        return std / base.error_std + weight * travel / base.travel

    return f


class Compensation(eqx.Module):
    """Result of [`jaxstiction.compensate`][] (arrays; a leading axis when batched).

    - `knocker`: the designed [`jaxstiction.Knocker`][] (period 1: constant
      reinforcement); `method`: 0 grid, 1 gradient;
    - `controller`: the controller it was designed with;
    - `error_std_as_is`, `error_std_compensated`, `error_std_repaired`: the standard
      deviation of SP − PV of the fitted loop replayed as is, with the knocker, and
      with a linear valve (engineering units);
    - `reduction`: the share of the variability a repair would remove that the
      knocker removes, $(\\sigma_\\text{as is} - \\sigma_\\text{comp}) /
      (\\sigma_\\text{as is} - \\sigma_\\text{rep})$; `reduction_percent`: its
      reduction as a percentage of the as-is variability;
    - `travel_as_is`, `travel_compensated`, `travel_repaired` (% of span per hour),
      `reversals_as_is`, `reversals_compensated`, `reversals_repaired` (per hour);
    - `objective`: the design objective reached (the worst over the fitted valve and
      its neighbours); `grid_objective`: every point's, also of the points not
      chosen for falling short of `CompensateSettings.min_gain`;
    - `pv_as_is`, `pv_compensated`, `pv_repaired`, `op_compensated`: the runs.
    """

    knocker: Knocker
    method: Int[Array, ""]
    controller: Controller
    error_std_as_is: Float[Array, ""]
    error_std_compensated: Float[Array, ""]
    error_std_repaired: Float[Array, ""]
    reduction: Float[Array, ""]
    reduction_percent: Float[Array, ""]
    travel_as_is: Float[Array, ""]
    travel_compensated: Float[Array, ""]
    travel_repaired: Float[Array, ""]
    reversals_as_is: Float[Array, ""]
    reversals_compensated: Float[Array, ""]
    reversals_repaired: Float[Array, ""]
    objective: Float[Array, ""]
    grid_objective: Float[Array, " points"]
    pv_as_is: Float[Array, " time"]
    pv_compensated: Float[Array, " time"]
    pv_repaired: Float[Array, " time"]
    op_compensated: Float[Array, " time"]
