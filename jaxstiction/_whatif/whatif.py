r"""What fixing the valve would buy: [`jaxstiction.whatif`][] and
[`jaxstiction.compensate`][].

For a loop with a fitted Kano valve and process ([`jaxstiction.LoopFit`][]`.physical`):

1. the controller is identified from the record (or given);
2. the disturbance the loop met is reconstructed: the output disturbance $v$ that
   makes the fitted loop reproduce the recorded PV, the identified noise model's
   output for the innovations recovered from the record (`replay`);
3. the loop is closed again in simulation under that same disturbance and setpoint,
   three ways: **as is** (the fitted Kano valve), **repaired** (a linear valve: S =
   J = 0, the same process), and **compensated** (the fitted valve with a knocker or
   constant reinforcement designed on this loop, [`jaxstiction.compensate`][]);
4. the same is repeated for models drawn around the fit (S and J on their intervals,
   the process from its asymptotic distribution; `uncertainty`) for the intervals.

Everything is one pure function of arrays: `eqx.filter_vmap(whatif)(fits, loops)`
batches loops.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, Bool, Float

from .._blocks import Kano
from .._control.closedloop import closed_loop, closed_loop_stable, ClosedLoopRun, Knocker, with_valve
from .._control.controller import Controller, identify_controller
from .._estimate.result import LoopFit
from .._loop import Loop
from .._misc import stack_trees
from .._models import LoopModel
from .compensate import Compensation, design_knocker, METHODS, no_knock
from .refine import refit_for_replay
from .replay import Replay, replay, setpoints
from .settings import CompensateSettings, WhatIfSettings
from .stats import loop_stats, LoopStats, SETTLE_TOLERANCE, settled_after, settling_errors
from .uncertainty import draw_models, free_parameters


class WhatIf(eqx.Module):
    """Result of [`jaxstiction.whatif`][] (arrays; a leading axis when batched).

    - `controller`: the [`jaxstiction.Controller`][] used (identified or given);
      `knocker`: the designed compensator, a [`jaxstiction.Knocker`][] (period 1:
      constant reinforcement); `objective`: its design objective;
    - `as_is`, `repaired`, `compensated`: [`LoopStats`][jaxstiction.LoopStats] of the
      fitted loop replayed three ways (engineering units; travel in % of span per
      hour, reversals per hour); `recorded`: the record's own (its valve travel is
      the fitted valve's under the recorded OP);
    - `as_is_interval`, `repaired_interval`, `compensated_interval`: the same with a
      leading axis of 2, `[low, high]`, the `level` quantiles over the drawn models
      (NaN without draws); `benefit`, `benefit_interval`: the fall of the standard
      deviation of SP − PV a repair buys, $\\sigma_\\text{as is} - \\sigma_\\text{rep}$;
    - `pv_range`: the recorded PV's range (max − min), for the benefit in % of it;
    - `S`, `J`: the fitted valve's; `draws_used`: drawn models kept (their runs
      stayed finite and the record does not reject them: the variance of their
      innovations is within the chi-square bound, at `level`, of the fit's);
      `has_setpoint`; `stable`: the three fitted-loop runs stayed bounded and the
      repaired loop (the fitted process, a linear valve, the controller), linearised
      over the recorded OP range, is stable (`closed_loop_stable`, roots within
      radius 1 + 1/n);
    - `start`: the first sample the numbers are read from, `sync` (the valve's path
      no longer depends on its unknown initial state, see `replay`) plus `settle`
      (the repaired loop's settling time, `settled_after`, to `SETTLE_TOLERANCE`
      of its peak times the ratio of the repaired to the as-is error's standard
      deviation: the repaired run starts from the record's as-is state, and its
      transient must fall below the repaired error's size), or, when that leaves
      fewer than `min_samples`, the last `min_samples` samples (never before
      `sync`; `settled` is then false: the repaired run may still carry some of its
      start); `samples`: how many real samples that leaves; `enough`: stable, with
      at least `min_samples` of them;
    - `op_*`, `pv_*`, `valve_*` (`as_is`, `repaired`, `compensated`): the runs.
    """

    controller: Controller
    knocker: Knocker
    objective: Float[Array, ""]
    as_is: LoopStats
    repaired: LoopStats
    compensated: LoopStats
    recorded: LoopStats
    as_is_interval: LoopStats
    repaired_interval: LoopStats
    compensated_interval: LoopStats
    benefit: Float[Array, ""]
    benefit_interval: Float[Array, " 2"]
    pv_range: Float[Array, ""]
    S: Float[Array, ""]
    J: Float[Array, ""]
    draws_used: Array
    has_setpoint: Bool[Array, ""]
    stable: Bool[Array, ""]
    start: Array
    sync: Array
    settle: Array
    settled: Bool[Array, ""]
    samples: Array
    enough: Bool[Array, ""]
    op_as_is: Float[Array, " time"]
    op_repaired: Float[Array, " time"]
    op_compensated: Float[Array, " time"]
    pv_as_is: Float[Array, " time"]
    pv_repaired: Float[Array, " time"]
    pv_compensated: Float[Array, " time"]
    valve_as_is: Float[Array, " time"]
    valve_repaired: Float[Array, " time"]
    valve_compensated: Float[Array, " time"]


class _Prepared(eqx.Module):
    """What `whatif` and `compensate` share: the model, the controller, the replay,
    the as-is and repaired runs and their stats."""

    model: LoopModel
    controller: Controller
    replay: Replay
    mask: Array
    window: Array
    start: Array
    settle: Array
    ts: Array
    as_is: ClosedLoopRun
    repaired: ClosedLoopRun
    as_is_stats: LoopStats
    repaired_stats: LoopStats


def _runs3(models, controller: Controller, rp: Replay, knockers: Knocker) -> ClosedLoopRun:
    """Closed-loop runs of a batch of models, each with its own knocker."""
    return jax.vmap(lambda m, k: closed_loop(m, controller, rp.sp_sim, rp.disturbance, rp.initial, rp.op0, k))(
        models, knockers)


def _innovation_variance(rp: Replay, window):
    return jnp.sum(window * rp.innovations**2) / jnp.maximum(jnp.sum(window), 1.0)


def chi2_quantile(p: float, dof):
    """The `p` quantile of a chi-square distribution with `dof` degrees of freedom
    (Wilson and Hilferty's cube-root approximation, within 1 % for `dof` >= 2)."""
    z = jax.scipy.special.ndtri(p)
    dof = jnp.asarray(dof, float)
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * jnp.sqrt(2.0 / (9.0 * dof))) ** 3


def _prepare(model: LoopModel, loop: Loop, controller: Controller | None, init_count: int,
             threshold: float, min_samples: int = 0) -> _Prepared:
    dtype = jnp.result_type(loop.op.dtype, loop.pv.dtype, jnp.float32)
    op, pv = jnp.asarray(loop.op, dtype), jnp.asarray(loop.pv, dtype)
    mask = (jnp.asarray(loop.mask) > 0).astype(dtype)
    ts = jnp.asarray(loop.ts, dtype)
    if controller is None:
        controller = identify_controller(op, pv, loop.setpoint, mask)
    rp = replay(model, loop, controller, init_count)
    repaired_model = with_valve(model, jnp.zeros((), dtype), jnp.zeros((), dtype))
    # the numbers are read once the valve's unknown start no longer shows and the
    # repaired loop has forgotten how it started (see `replay`)
    n = op.shape[0]
    # a slow repaired loop (an integrating process, a detuned PI) may settle for
    # longer than the record leaves: then the last `min_samples` valid samples are
    # read (never before `sync`), and `settled` is false
    last = jnp.max(jnp.where(mask > 0, jnp.arange(n) + 1, 0))

    def window_after(settle):
        start = jnp.minimum(rp.sync + settle, jnp.maximum(rp.sync, last - min_samples))
        start = jnp.minimum(start, n)
        return start, mask * (jnp.arange(n) >= start)

    none = no_knock(dtype)
    runs = _runs3(stack_trees(model, repaired_model), controller, rp, stack_trees(none, none))

    def stats_in(window):
        return jax.vmap(lambda r: loop_stats(r.pv, rp.sp_stat, r.valve, window, ts, threshold))(runs)

    # the repaired loop's response to a start unlike the truth's, simulated once
    errors = settling_errors(repaired_model, controller, op[0], n)
    start, _ = window_after(settled_after(errors))
    # The repaired run starts from the record's (as-is) state, so its transient starts
    # at the size of the as-is error, and must fall to a share of the repaired error's
    # size, not of its own start: where a repair removes most of the variability, it
    # settles to `SETTLE_TOLERANCE` of its peak times the repaired-to-as-is ratio,
    # measured on the record's second half (which the first transient leaves alone).
    tail = stats_in(mask * (jnp.arange(n) >= jnp.maximum(start, (rp.sync + last) // 2)))
    ratio = tail.error_std[1] / tail.error_std[0]
    ratio = jnp.where(jnp.isfinite(ratio), jnp.clip(ratio, 0.0, 1.0), 1.0)
    settle = settled_after(errors, SETTLE_TOLERANCE * ratio)
    start, window = window_after(settle)
    stats = stats_in(window)
    first, second = (jax.tree.map(lambda t, i=i: t[i], (runs, stats)) for i in (0, 1))
    return _Prepared(model=model, controller=controller, replay=rp, mask=mask, window=window, start=start,
                     settle=settle, ts=ts, as_is=first[0], repaired=second[0], as_is_stats=first[1],
                     repaired_stats=second[1])


def _check(fit, loop):
    if not isinstance(fit, LoopFit):
        raise ValueError(f"`fit` must be a jaxstiction.LoopFit (from jaxstiction.estimate), got {type(fit).__name__}")
    _check_model(fit.physical, loop)


def _check_model(model, loop):
    if not isinstance(loop, Loop):
        raise ValueError(f"`loop` must be a jaxstiction.Loop, got {type(loop).__name__}")
    if loop.op.ndim != 1:
        raise ValueError(f"`loop` must be one unbatched loop (1-D OP), got OP of shape {loop.op.shape}; "
                         "batch with eqx.filter_vmap")
    if not isinstance(model, LoopModel) or not model.chain or not isinstance(model.chain[0], Kano):
        raise ValueError("the model must be a jaxstiction.LoopModel whose first block is a Kano valve "
                         "(a LoopFit's `physical` model)")


def _whatif(fit: LoopFit, loop: Loop, settings: WhatIfSettings = WhatIfSettings(), *,
            controller: Controller | None = None) -> WhatIf:
    r"""What fixing the valve of one loop would buy (see the module notes).

    **Arguments:**

    - `fit`: the loop's [`jaxstiction.LoopFit`][] (its `physical` model, the Kano
      valve and the process, is replayed whichever family `estimate` chose);
    - `loop`: the [`jaxstiction.Loop`][] it was fitted on, with its setpoint `sp`
      when one was recorded (else the setpoint is taken as constant);
    - `settings`: [`jaxstiction.WhatIfSettings`][];
    - `controller`: a [`jaxstiction.Controller`][] to use instead of identifying one
      (e.g. [`jaxstiction.Controller.pi`][] from the tuning in the DCS).

    **Returns:** a [`jaxstiction.WhatIf`][]. Pure and jitted;
    `eqx.filter_vmap(jaxstiction.whatif)(fits, loops)` batches loops.

    **Raises:** `ValueError` when `fit` is not a `LoopFit` with a Kano valve or `loop`
    is not one unbatched `Loop`.
    """
    _check(fit, loop)
    controller = _controller(loop, controller)
    if not settings.refine:
        return _whatif_model(fit.physical, loop, fit.S_interval, fit.J_interval, settings, controller=controller)
    model = _refined(fit.physical, loop, controller, settings.init_count, settings.polish)
    # the intervals of S and J move with the polished valve
    dS, dJ = model.chain[0].S - fit.physical.chain[0].S, model.chain[0].J - fit.physical.chain[0].J
    return _whatif_model(model, loop, fit.S_interval + dS, fit.J_interval + dJ, settings, controller=controller)


def _controller(loop: Loop, controller: Controller | None) -> Controller:
    """The given controller, else the one identified from the record."""
    if controller is not None:
        return controller
    dtype = jnp.result_type(loop.op.dtype, loop.pv.dtype, jnp.float32)
    mask = (jnp.asarray(loop.mask) > 0).astype(dtype)
    return identify_controller(jnp.asarray(loop.op, dtype), jnp.asarray(loop.pv, dtype), loop.setpoint, mask)


def _refined(model: LoopModel, loop: Loop, controller: Controller, init_count: int, polish: bool) -> LoopModel:
    """`model` made ready for the replay (`refit_for_replay`)."""
    dtype = jnp.result_type(loop.op.dtype, loop.pv.dtype, jnp.float32)
    op, pv = jnp.asarray(loop.op, dtype), jnp.asarray(loop.pv, dtype)
    w = (jnp.asarray(loop.mask) > 0).astype(dtype)
    sp_sim, sp_stat, _ = setpoints(loop, controller)
    return refit_for_replay(model, op, pv, w, controller, sp_sim, sp_stat, init_count, polish=polish)


def _whatif_model(model: LoopModel, loop: Loop, S_interval, J_interval, settings: WhatIfSettings = WhatIfSettings(),
                  *, controller: Controller | None = None) -> WhatIf:
    """[`jaxstiction.whatif`][] of a given model (its first block a Kano valve) with
    the intervals of its S and J (NaN: none): a plant model, a nominal model, or a
    fit's `physical` model."""
    _check_model(model, loop)
    threshold = settings.reversal_threshold
    p = _prepare(model, loop, controller, settings.init_count, threshold, settings.min_samples)
    rp, mask, window, ts, model, ctrl = p.replay, p.mask, p.window, p.ts, p.model, p.controller
    dtype = mask.dtype
    design = design_knocker(model, ctrl, rp, window, ts, p.as_is_stats, settings.compensate, threshold)
    comp_run = design.run

    # the record itself (its valve: the fitted valve under the recorded OP)
    pv = jnp.asarray(loop.pv, dtype)
    valve_rec = model.chain[0](jnp.asarray(loop.op, dtype), rp.initial.chain[0])
    recorded = loop_stats(pv, rp.sp_stat, valve_rec, window, ts, threshold)

    # draws: each model replays the record with its own disturbance
    K = settings.draws
    none = no_knock(dtype)
    if K > 0:
        op = jnp.asarray(loop.op, dtype)
        models = draw_models(model, jnp.asarray(S_interval, dtype), jnp.asarray(J_interval, dtype), op,
                             rp.disturbance, rp.initial, mask, jr.PRNGKey(settings.seed), K)

        def one(m):
            r = replay(m, loop, ctrl, initial=rp.initial, sync=rp.sync)
            rep = with_valve(m, jnp.zeros((), dtype), jnp.zeros((), dtype))
            runs = _runs3(stack_trees(m, rep, m), ctrl, r, stack_trees(none, none, design.knocker))
            st = jax.vmap(lambda run: loop_stats(run.pv, r.sp_stat, run.valve, window, ts, threshold))(runs)
            return st, _innovation_variance(r, window)

        st, v_k = jax.vmap(one)(models)  # (K, 3), (K,)
        # a draw is kept when the record does not reject it: its innovations' variance
        # within the chi-square bound of the fit's (the quadratic approximation that
        # drew it can be poor, and a model the data reject has a disturbance that
        # carries its own error)
        v_0 = _innovation_variance(rp, window)
        n_eff = jnp.maximum(jnp.sum(window), 1.0)
        dof = jnp.sum(free_parameters(model)) + 2
        ok = jnp.all(jnp.isfinite(st.error_std), axis=1) & (
            n_eff * jnp.log(v_k / v_0) <= chi2_quantile(settings.level, dof))
        q = jnp.asarray([(1 - settings.level) / 2, (1 + settings.level) / 2], dtype)

        def interval(x, x0):
            # the fit itself is one of the models the intervals span, and lies inside
            # them however the draws fall around it
            x = jnp.concatenate([jnp.where(ok, x, jnp.nan), x0[None]])
            lo, hi = jnp.nanquantile(x, q)
            return jnp.stack([jnp.minimum(lo, x0), jnp.maximum(hi, x0)])

        base = (p.as_is_stats, p.repaired_stats, design.compensated)
        ivs = [jax.tree.map(lambda t, t0, j=j: interval(t[:, j], t0), st, base[j]) for j in range(3)]
        benefit_iv = interval(st.error_std[:, 0] - st.error_std[:, 1],
                              p.as_is_stats.error_std - p.repaired_stats.error_std)
        used = jnp.sum(ok)
    else:
        nan2 = jnp.full((2,), jnp.nan, dtype)
        ivs = [jax.tree.map(lambda _: nan2, p.as_is_stats) for _ in range(3)]
        benefit_iv, used = nan2, jnp.zeros((), jnp.int32)

    _, _, has_sp = setpoints(loop, ctrl)
    big = jnp.finfo(dtype).max
    pv_range = jnp.max(jnp.where(mask > 0, pv, -big)) - jnp.min(jnp.where(mask > 0, pv, big))
    bound = 1e3 * jnp.maximum(pv_range, 1e-12)
    bounded = jnp.all(jnp.stack([jnp.all(jnp.where(mask > 0, jnp.abs(r.pv - rp.sp_stat) < bound, True))
                                 for r in (p.as_is, p.repaired, comp_run)]))
    # the repaired loop must also be stable as a linear loop: an unstable one may
    # stay bounded (OP banging between its limits) and read as a number, but that
    # number is the runaway's (concealed seed 26: a fitted gain 1.8 times the
    # plant's, a repaired error of 717 against a true 1.35). A root within radius
    # 1 + 1/n (growth by at most e over the record) is let pass, as the limit-cycle
    # check does
    op_rec = jnp.asarray(loop.op, dtype)
    op_lo, op_hi = jnp.min(jnp.where(mask > 0, op_rec, big)), jnp.max(jnp.where(mask > 0, op_rec, -big))
    stable = bounded & closed_loop_stable(model, ctrl, op_lo, op_hi, margin=-1.0 / jnp.maximum(jnp.sum(mask), 1.0))
    samples = jnp.sum(window)
    enough = stable & (samples >= settings.min_samples)
    return WhatIf(
        controller=ctrl, knocker=design.knocker, objective=design.objective,
        as_is=p.as_is_stats, repaired=p.repaired_stats, compensated=design.compensated, recorded=recorded,
        as_is_interval=ivs[0], repaired_interval=ivs[1], compensated_interval=ivs[2],
        benefit=p.as_is_stats.error_std - p.repaired_stats.error_std, benefit_interval=benefit_iv,
        pv_range=pv_range, S=model.chain[0].S, J=model.chain[0].J, draws_used=used, has_setpoint=has_sp,
        stable=stable, start=p.start, sync=rp.sync, settle=p.settle,
        settled=p.start >= rp.sync + p.settle, samples=samples.astype(jnp.int32),
        enough=enough,
        op_as_is=p.as_is.op, op_repaired=p.repaired.op, op_compensated=comp_run.op_valve,
        pv_as_is=p.as_is.pv, pv_repaired=p.repaired.pv, pv_compensated=comp_run.pv,
        valve_as_is=p.as_is.valve, valve_repaired=p.repaired.valve, valve_compensated=comp_run.valve,
    )


def _compensate(fit: LoopFit, loop: Loop, settings: CompensateSettings = CompensateSettings(), *,
                controller: Controller | None = None, init_count: int = 32,
                reversal_threshold: float = 0.1, min_samples: int = 200, refine: bool = True) -> Compensation:
    r"""Design a compensator (a knocker or constant reinforcement) for one loop on its
    identified closed loop (see
    `jaxstiction._whatif.compensate`).

    **Arguments:** `fit`, `loop`, `controller` as for [`jaxstiction.whatif`][];
    `settings`: [`jaxstiction.CompensateSettings`][] (the grid, the travel weight,
    `method="grid"` or `"gradient"`); `init_count`, `reversal_threshold`,
    `min_samples` and `refine` as in [`jaxstiction.WhatIfSettings`][].

    **Returns:** a [`jaxstiction.Compensation`][]: the compensator, the predicted
    variability with and without it (and with a repaired valve), and the extra
    travel it costs. Pure and jitted; vmappable over loops.

    **Raises:** `ValueError` as [`jaxstiction.whatif`][].
    """
    _check(fit, loop)
    controller = _controller(loop, controller)
    model = _refined(fit.physical, loop, controller, init_count, refine) if refine else fit.physical
    p = _prepare(model, loop, controller, init_count, reversal_threshold, min_samples)
    d = design_knocker(p.model, p.controller, p.replay, p.window, p.ts, p.as_is_stats, settings, reversal_threshold)
    a, r, c = p.as_is_stats, p.repaired_stats, d.compensated
    removable = a.error_std - r.error_std
    reduction = (a.error_std - c.error_std) / jnp.where(removable != 0, removable, jnp.nan)
    return Compensation(
        knocker=d.knocker, method=jnp.asarray(METHODS.index(settings.method)), controller=p.controller,
        error_std_as_is=a.error_std, error_std_compensated=c.error_std, error_std_repaired=r.error_std,
        reduction=reduction, reduction_percent=100.0 * (a.error_std - c.error_std) / a.error_std,
        travel_as_is=a.travel, travel_compensated=c.travel, travel_repaired=r.travel,
        reversals_as_is=a.reversals, reversals_compensated=c.reversals, reversals_repaired=r.reversals,
        objective=d.objective, grid_objective=d.grid_objective,
        pv_as_is=p.as_is.pv, pv_compensated=d.run.pv, pv_repaired=p.repaired.pv, op_compensated=d.run.op_valve,
    )


whatif = eqx.filter_jit(_whatif)
whatif_model = eqx.filter_jit(_whatif_model)
compensate = eqx.filter_jit(_compensate)
