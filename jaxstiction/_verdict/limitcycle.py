r"""Does the fitted valve, closed again around the loop's own controller, reproduce
the limit cycle the record shows?

A sticky valve under a controller with integral action cycles by itself: the error
winds the controller up until the valve slips past the setpoint, and again the other
way. A valve model fitted to a sticky loop should therefore reproduce, with no noise
at all, the recorded oscillation's amplitude and period; a band fitted to an
oscillation that comes from elsewhere (a disturbance, a tight tuning) does not,
because the cycle it makes is set by the loop's own dynamics, not by the
disturbance's.

`limit_cycle` identifies the PI controller from the record
([`jaxstiction.identify_controller`][]: with `SP` when recorded, else with a constant
setpoint) and closes the fitted Kano model around it, and the same model with its valve
repaired (S = J = 0, `closed_loop`), under the recorded setpoint (or the
identified constant one), without disturbance. The process starts at rest half a
band (at least 1 % of the OP range) above the record's mean OP, so that the
controller has an error to act on. After the runs' first quarter, each run's
control error and the recorded one are read as `loop_stats` reads an oscillation:
the period of its strongest component and the amplitude of the sine carrying the
power within a factor 1.5 of it. A run's match to the record is the product of the
amplitude match $\min(a/a_r,\,a_r/a)$ and the period match $\min(p/p_r,\,p_r/p)$, in
[0, 1]. The **reproduction** is the Kano run's match less the repaired run's, in
[−1, 1]: near 1 when the fitted valve makes the recorded cycle and a repaired one
would not; near 0 when both runs match alike (setpoint moves answered the same
way) or neither does.

It is NaN when the controller cannot be
identified (its law explains less than `min_controller_fit` of the variance of ΔOP:
a cascade's slave, a manual stretch), when the repaired loop under that PI,
linearised over the recorded OP range (`closed_loop_stable`: the fitted spline after
the valve scales OP, and its gain counts), has a
closed-loop root outside the circle of radius $1 + 1/n$ ($n$ samples: it grows by
more than a factor $e$ over the record, so the fitted process and the identified PI
disagree with a record that stayed bounded), or when a run is not finite. A root
just outside the unit circle (`stable` false) grows too slowly to matter over the
record: it is judged.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._control.closedloop import closed_loop, closed_loop_stable, with_valve
from .._control.controller import identify_controller
from .indicators import cycle


MIN_CONTROLLER_FIT = 0.2  # share of ΔOP's variance the identified PI must explain


class LimitCycle(eqx.Module):
    """Result of `limit_cycle` (arrays; a leading axis when batched): the
    oscillation of the control error, `amplitude_*` (engineering units) and
    `period_*` (samples), of the record (`recorded`) and, after their first quarter,
    of the noise-free closed-loop runs of the fitted Kano model (`kano`) and of the
    same model with its valve repaired (`repaired`); `controller_fit`: the share of
    ΔOP's variance the identified PI explains; `stable`: the repaired loop is stable
    under that PI (its closed-loop roots, `closed_loop_stable`); `reproduction`:
    see the module notes (NaN where it cannot be judged)."""

    amplitude_recorded: Float[Array, ""]
    period_recorded: Float[Array, ""]
    amplitude_kano: Float[Array, ""]
    period_kano: Float[Array, ""]
    amplitude_repaired: Float[Array, ""]
    period_repaired: Float[Array, ""]
    controller_fit: Float[Array, ""]
    stable: Bool[Array, ""]
    reproduction: Float[Array, ""]


def _match(a, b):
    """`min(a / b, b / a)` for positive `a`, `b`; 0 where either is not."""
    ok = (a > 0) & (b > 0) & jnp.isfinite(a) & jnp.isfinite(b)
    a, b = jnp.where(ok, a, 1.0), jnp.where(ok, b, 1.0)
    return jnp.where(ok, jnp.minimum(a / b, b / a), 0.0)


def limit_cycle(fit, op: Float[Array, " time"], pv: Float[Array, " time"], sp: Float[Array, " time"],
                mask: Float[Array, " time"], min_controller_fit: float = MIN_CONTROLLER_FIT,
                segment: int | None = None) -> LimitCycle:
    """The limit-cycle check of one loop (see the module notes) from its
    [`jaxstiction.LoopFit`][] `fit` (its `physical` model and its `S`, `J`) and record:
    `op`, `pv`, `sp` (all NaN when no setpoint is recorded) and `mask` (1 on real
    samples, which come first); over more than `segment` samples the oscillations
    are read in segments (`cycle`). Pure; vmaps over loops."""
    w = (mask > 0).astype(pv.dtype)
    n = jnp.sum(w)
    controller = identify_controller(op, pv, sp, mask)
    has_sp = jnp.all(jnp.where(w > 0, jnp.isfinite(sp), True))
    count = jnp.maximum(n, 1.0)
    level = jnp.where(jnp.isfinite(controller.setpoint), controller.setpoint, jnp.sum(w * pv) / count)
    r = jnp.where(has_sp & (w > 0), jnp.where(jnp.isfinite(sp), sp, level), level)
    u0 = jnp.sum(w * op) / count
    op_lo, op_hi = jnp.min(jnp.where(w > 0, op, jnp.inf)), jnp.max(jnp.where(w > 0, op, -jnp.inf))
    span = op_hi - op_lo
    start = u0 + jnp.maximum(0.5 * jnp.abs(fit.S), 0.01 * span)
    late = w * (jnp.arange(op.shape[0]) >= n / 4)
    zero = jnp.zeros_like(pv)

    def error(model):
        return r - closed_loop(model, controller, r, zero, model.rest_state(jnp.full_like(op, start)), u0).pv

    repaired = with_valve(fit.physical, jnp.zeros_like(fit.S), jnp.zeros_like(fit.J))
    e_k, e_l, e_r = error(fit.physical), error(repaired), jnp.where(w > 0, r - pv, 0.0)
    # periods up to half the samples read: a slow cycle holds few in a short record
    (a_k, p_k), (a_l, p_l), (a_r, p_r) = (cycle(e, weights, min_periods=2.0, segment=segment)
                                          for e, weights in ((e_k, late), (e_l, late), (e_r, w)))
    stable = closed_loop_stable(repaired, controller, op_lo, op_hi)
    # a root within 1 + 1/n of the unit circle grows by at most e over the record
    slow = closed_loop_stable(repaired, controller, op_lo, op_hi, margin=-1.0 / count)
    score = _match(a_k, a_r) * _match(p_k, p_r) - _match(a_l, a_r) * _match(p_l, p_r)
    judged = (controller.fit >= min_controller_fit) & slow & jnp.isfinite(a_k) & jnp.isfinite(a_l) & (a_r > 0)
    return LimitCycle(amplitude_recorded=a_r, period_recorded=p_r, amplitude_kano=a_k, period_kano=p_k,
                      amplitude_repaired=a_l, period_repaired=p_l, controller_fit=controller.fit, stable=stable,
                      reproduction=jnp.where(judged, score, jnp.nan))
