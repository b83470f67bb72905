r"""Data-quality gating: can this record show stiction at all?

Before a loop is judged, its record is checked for what hides a sticky valve from
OP and PV. A loop that fails a check gets the verdict `inconclusive` with the
reason named, instead of a yes or a no the data cannot support. Each measure is a
pure function of one loop (vmappable); [`jaxstiction.verdict`][] applies the
thresholds of [`jaxstiction.VerdictSettings`][]:

- `frozen_sensor`: PV does not change over the record (a dead transmitter, or a
  historian tag that stopped updating). The screen meets it before any fit: such a
  record cannot be fitted.
- `saturated`: OP sits at its minimum or maximum for a large share of the record
  (the valve is against a stop and cannot cycle).
- `compressed`: PV repeats its previous value on most samples where OP moves, in
  many separate runs (a historian's compression or a coarse quantisation: flat
  runs, then jumps), or OP does while PV moves. One long flat run is not this: a
  PV that stays flat over much of the record while OP travels is what a stuck valve
  does, and is left to the evidence.
- `setpoint_moves`: setpoint moves carry most of PV's variance, so PV's movements
  are the loop's answers to them, not a cycle of its own.
- `few_periods`: no oscillation with at least `min_periods` periods in the record,
  so a limit cycle cannot be told from a slow wander.

The first three hide the valve whatever the evidence (`HARD`); the last two leave
the verdict to the evidence when it is strong, and make it `inconclusive` when it
is not. `GATES` lists the codes; 0 is `ok`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .settings import VerdictSettings


GATES = ("ok", "frozen_sensor", "saturated", "compressed", "setpoint_moves", "few_periods")
HARD = ("frozen_sensor", "saturated", "compressed")


class GateMeasures(eqx.Module):
    """What the gate measured on one loop (arrays; a leading axis when batched).

    - `saturated`: share of real samples with OP within 0.1 % of its range from its
      minimum or maximum.
    - `compressed`: the larger of the share of OP's moves on which PV repeats its
      previous value and the share of PV's moves on which OP does;
      `longest_flat`: the longest run of samples over which that signal does not
      change, as a share of the record.
    - `setpoint_share`: variance of the setpoint over that of PV (0 without a
      setpoint).
    - `frozen`: PV never changes.
    """

    saturated: Float[Array, ""]
    compressed: Float[Array, ""]
    longest_flat: Float[Array, ""]
    setpoint_share: Float[Array, ""]
    frozen: Bool[Array, ""]


def gate_measures(op, pv, sp, mask) -> GateMeasures:
    """The gate's measures of one loop (see `GateMeasures`); `sp` all NaN when no
    setpoint was recorded."""
    w = mask > 0
    n = jnp.maximum(jnp.sum(w), 1)
    big = jnp.finfo(op.dtype).max
    lo = jnp.min(jnp.where(w, op, big))
    hi = jnp.max(jnp.where(w, op, -big))
    tol = 1e-3 * jnp.maximum(hi - lo, 1e-12)
    saturated = jnp.sum(w & ((op <= lo + tol) | (op >= hi - tol))) / n
    pair = w[1:] & w[:-1]
    dpv, dop = jnp.diff(pv), jnp.diff(op)
    pv_holds = pair & (dpv == 0) & (dop != 0)
    op_holds = pair & (dop == 0) & (dpv != 0)
    share_pv = jnp.sum(pv_holds) / jnp.maximum(jnp.sum(pair & (dop != 0)), 1)
    share_op = jnp.sum(op_holds) / jnp.maximum(jnp.sum(pair & (dpv != 0)), 1)
    flat = pair & (jnp.where(share_pv >= share_op, dpv, dop) == 0)
    count = jnp.cumsum(flat)
    run = count - jax.lax.cummax(jnp.where(flat, 0, count))  # length of the flat run ending at each sample
    longest = jnp.max(run) / n
    has_sp = jnp.all(jnp.where(w, jnp.isfinite(sp), True))
    spz = jnp.where(w & has_sp, sp, 0.0)

    def var(x):
        m = jnp.sum(jnp.where(w, x, 0.0)) / n
        return jnp.sum(jnp.where(w, (x - m) ** 2, 0.0)) / n

    share = jnp.where(has_sp, var(spz) / jnp.maximum(var(pv), 1e-300), 0.0)
    pvmin = jnp.min(jnp.where(w, pv, big))
    pvmax = jnp.max(jnp.where(w, pv, -big))
    frozen = pvmax - pvmin <= 1e-12 * jnp.maximum(jnp.abs(pvmax), 1e-300)
    return GateMeasures(saturated=saturated, compressed=jnp.maximum(share_pv, share_op),
                        longest_flat=longest.astype(op.dtype), setpoint_share=share, frozen=frozen)


def hard_checks(g: GateMeasures, settings: VerdictSettings) -> tuple[Bool[Array, ""], ...]:
    """The checks of `HARD`, in its order, by `settings`' thresholds: True where the
    record fails it."""
    return (g.frozen, g.saturated > settings.max_saturated,
            (g.compressed > settings.max_compressed) & (g.longest_flat <= settings.max_flat_run))


def hard_gated(g: GateMeasures, settings: VerdictSettings = VerdictSettings()) -> Bool[Array, ""]:
    """True where a hard gate stops the record whatever the evidence (PV frozen, OP
    at a stop, or the record compressed or coarsely quantised by the historian)."""
    frozen, saturated, compressed = hard_checks(g, settings)
    return frozen | saturated | compressed


GATE_TEXT = {
    "frozen_sensor": "PV does not change over the record: a frozen sensor or a tag that stopped updating",
    "saturated": "OP sits at its minimum or maximum on {saturated:.0%} of the record: the valve is against a stop",
    "compressed": ("one signal repeats its previous value on {compressed:.0%} of the other's moves: compressed or "
                   "coarsely quantised by the historian"),
    "setpoint_moves": ("the setpoint's variance is {setpoint_share:.0%} of PV's: PV's movements answer setpoint "
                       "moves"),
    "few_periods": "no oscillation with {min_periods:g} or more periods in the record",
}


def gate_reason(code: int, **values) -> str:
    """The one-line reason of gate `code` (an index into `GATES`), "" for `ok`."""
    name = GATES[int(code)]
    return "" if name == "ok" else GATE_TEXT[name].format(**values)
