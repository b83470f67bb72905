r"""What to read off one closed-loop run (or the record): `loop_stats`, the numbers a
plant engineer asks for, and `settling_time`, how long a fitted loop keeps the
memory of its start."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._control.closedloop import closed_loop
from .._control.controller import Controller
from .._models import LoopModel
from .._verdict.indicators import cycle
from .._verdict.settings import VerdictSettings


SETTLE_TOLERANCE = 0.05
"""A loop has settled once its control error stays within this share of its peak
(`settling_time`)."""

SEGMENT = VerdictSettings().segment
"""A run read over more than this many samples has its oscillation read in segments
(`cycle`), as the verdict's indicators read a long record (the default
`VerdictSettings.segment`): a slow swing of the disturbance does not pass for the
oscillation."""


class LoopStats(eqx.Module):
    """What one run (or the record) shows, over the real samples:

    - `error_std`, `error_ptp`: standard deviation and peak-to-peak of SP − PV
      (engineering units; SP at its mean when none is recorded, so the PV's);
    - `pv_std`, `pv_ptp`: the same of PV itself (setpoint moves included);
    - `amplitude`, `period`: the oscillation of SP − PV: the period (samples) of its
      strongest component (`dominant_period`) and the amplitude of the sine that
      carries the power within a factor 1.5 of that frequency,
      $\\sqrt{2\\,\\text{share}}\\;\\sigma_e$ (over more than `SEGMENT` samples
      read in segments, as `cycle` reads them);
    - `travel`: valve travel, the sum of |Δ valve|, in % of span per hour;
    - `reversals`: valve reversals per hour (moves of more than the threshold
      against the previous direction of travel).
    """

    error_std: Float[Array, ""]
    error_ptp: Float[Array, ""]
    pv_std: Float[Array, ""]
    pv_ptp: Float[Array, ""]
    amplitude: Float[Array, ""]
    period: Float[Array, ""]
    travel: Float[Array, ""]
    reversals: Float[Array, ""]


def count_reversals(x: Float[Array, " time"], w: Float[Array, " time"], threshold) -> Float[Array, ""]:
    """Reversals of `x` over the samples with `w > 0`: moves of more than
    `threshold` back from the furthest point reached in the current direction (the
    first such move sets a direction and is not counted)."""

    def step(carry, xw):
        d, ext, count = carry
        xt, wt = xw
        ext = jnp.where(d > 0, jnp.maximum(ext, xt), jnp.where(d < 0, jnp.minimum(ext, xt), ext))
        up, down = xt > ext + threshold, xt < ext - threshold
        new_d = jnp.where(d > 0, jnp.where(down, -1.0, d), jnp.where(d < 0, jnp.where(up, 1.0, d),
                                                                    jnp.where(up, 1.0, jnp.where(down, -1.0, d))))
        turned = (new_d != d) & (d != 0)
        ext = jnp.where(new_d != d, xt, ext)
        keep = wt > 0
        return (jnp.where(keep, new_d, d), jnp.where(keep, ext, carry[1]), count + keep * turned), None

    zero = jnp.zeros((), x.dtype)
    (_, _, count), _ = jax.lax.scan(step, (zero, x[0], zero), (x, w))
    return count


def loop_stats(pv, sp_stat, valve, mask, ts, threshold) -> LoopStats:
    """`LoopStats` of one run: `pv`, the setpoint the error is measured against
    `sp_stat`, the `valve` position, `mask` (real samples) and the sampling time
    `ts` (s). Pure and vmappable."""
    w = (mask > 0).astype(pv.dtype)
    count = jnp.maximum(jnp.sum(w), 1.0)
    hours = count * ts / 3600.0
    big = jnp.finfo(pv.dtype).max

    def std_ptp(x):
        m = jnp.sum(w * x) / count
        s = jnp.sqrt(jnp.sum(w * (x - m) ** 2) / count)
        return s, jnp.max(jnp.where(w > 0, x, -big)) - jnp.min(jnp.where(w > 0, x, big))

    e = (sp_stat - pv) * w
    e_std, e_ptp = std_ptp(e)
    pv_std, pv_ptp = std_ptp(pv)
    amplitude, period = cycle(e, w, segment=SEGMENT)
    pair = w[1:] * w[:-1]
    travel = jnp.sum(pair * jnp.abs(jnp.diff(valve))) / hours
    reversals = count_reversals(valve, w, threshold) / hours
    return LoopStats(error_std=e_std, error_ptp=e_ptp, pv_std=pv_std, pv_ptp=pv_ptp, amplitude=amplitude,
                     period=period, travel=travel, reversals=reversals)


def settling_errors(model: LoopModel, controller: Controller, op0, n: int) -> Array:
    """The control error's magnitude (2, `n`) of the loop after a step disturbance at
    its output and after an offset of its OP (a start whose controller output or
    process state differs from the truth's is both). The loop starts at rest at OP
    `op0` with the setpoint at its PV; the steps are small (1e-6), so OP limits stay
    out of play."""
    dtype = jnp.result_type(op0, jnp.float32)
    initial = model.rest_state(jnp.full((n,), op0, dtype))
    sp = jnp.full((n,), initial.filter[0] + model.pv_offset, dtype)
    step = jnp.where(jnp.arange(n) >= 1, 1e-6, 0.0).astype(dtype)
    output = closed_loop(model, controller, sp, step, initial, op0)
    offset = closed_loop(model, controller, sp, jnp.zeros((n,), dtype), initial, op0 + 1e-6)
    return jnp.abs(jnp.stack([output.pv, offset.pv]) - sp)


def settled_after(errors: Array, tolerance=SETTLE_TOLERANCE) -> Array:
    """The later, over the rows of `errors` (`settling_errors`), of the last sample at
    which the error is above `tolerance` of its peak, plus one (the record's length
    for a loop that does not settle within it)."""
    n = errors.shape[-1]
    late = ~(errors <= tolerance * jnp.max(errors, axis=-1, keepdims=True))  # NaN (a runaway) is late too
    return jnp.max(jnp.where(late, jnp.arange(n) + 1, 0)).astype(jnp.int32)


def settling_time(model: LoopModel, controller: Controller, op0, n: int, tolerance=SETTLE_TOLERANCE) -> Array:
    """Samples the loop takes to forget how it started: the later of its settling
    after a step disturbance at its output and after an offset of its OP
    (`settling_errors`), each the last sample (of `n`) at which the control error is
    above `tolerance` of its peak, plus one (`n` for a loop that does not settle
    within `n`)."""
    return settled_after(settling_errors(model, controller, op0, n), tolerance)
