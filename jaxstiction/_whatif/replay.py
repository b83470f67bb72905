r"""The record as a closed loop to replay: a model's initial state and the disturbance
it needs to reproduce the recorded PV.

For a model $M$ (valve and process) the disturbance is
$v = PV - M(\text{recorded OP})$, simulated from $M$'s initial state estimated on
the whole record. It is the identified noise model's output: its innovations are
$\varepsilon = \frac{D(q)}{C(q)} v$ and $v = \frac{C(q)}{D(q)}\varepsilon$, so
replaying the innovations through the noise model replays $v$ itself, sample for
sample. Under it, $M$ in closed loop with the identified controller reproduces the
record; a repaired or compensated valve in the same loop then meets the disturbance
the loop met.

A sticky valve's state at the start of a record is unknown (where it stopped, which
way it last travelled), and until the valve has slipped both ways its path under the
recorded OP depends on that state. Every candidate initial state that explains the
record about as well as the best one (`initial_candidates`; within $\chi^2_2$ at 99 %
of it) is run, and `sync` is the first sample from which all their valve paths
agree: before it the disturbance carries the unknown start, so the what-if numbers
are read after it (and after the repaired loop has settled, see `whatif`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._control.controller import Controller
from .._filters import lfilter
from .._loop import Loop
from .._misc import first_min
from .._models import InitialState, LoopModel


# chi-square(2) at 99 %: candidate initial states within this of the best are plausible
PLAUSIBLE = 9.21


class Replay(eqx.Module):
    """One model's replay of a record (see the module notes).

    - `initial`: the model's initial state, estimated on the record;
    - `disturbance`: $v$ (0 on padding); `innovations`: $\\frac{D}{C} v$;
    - `sp_sim`: the setpoint the controller sees (the recorded one, else the
      controller's constant level); `sp_stat`: the one errors are measured against
      (the recorded one, else the mean PV);
    - `op0`: the recorded first OP; `sync`: the first sample from which the valve's
      path no longer depends on its unknown initial state.
    """

    initial: InitialState
    disturbance: Float[Array, " time"]
    innovations: Float[Array, " time"]
    sp_sim: Float[Array, " time"]
    sp_stat: Float[Array, " time"]
    op0: Float[Array, ""]
    sync: Int[Array, ""]


def setpoints(loop: Loop, controller: Controller):
    """`(sp_sim, sp_stat, has_sp)` of a loop (see `Replay`); padding repeats the last
    real setpoint."""
    dtype = jnp.result_type(loop.op.dtype, jnp.float32)
    pv = jnp.asarray(loop.pv, dtype)
    w = (jnp.asarray(loop.mask) > 0).astype(dtype)
    sp = jnp.asarray(loop.setpoint, dtype)
    has_sp = jnp.all(jnp.where(w > 0, jnp.isfinite(sp), True))
    count = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(w * pv) / count
    last = jnp.max(jnp.where(w > 0, jnp.arange(w.shape[0]), 0))
    sp = jnp.where(w > 0, sp, sp[last])
    level = jnp.where(jnp.isfinite(controller.setpoint), controller.setpoint, mean)
    sp_sim = jnp.where(has_sp, sp, level)
    sp_stat = jnp.where(has_sp, sp, mean)
    return sp_sim, sp_stat, has_sp


def initial_and_sync(model: LoopModel, op, pv, w, count: int):
    """`(initial, sync)`: the best initial state on the whole record and the first
    sample from which every plausible candidate's valve path agrees (see the module
    notes)."""
    states, errs = model.initial_candidates(op, pv, w, count=count)
    best = first_min(errs)
    n_eff = jnp.maximum(jnp.sum(w), 1.0)
    plausible = n_eff * jnp.log(errs / jnp.maximum(errs[best], 1e-300)) <= PLAUSIBLE
    plausible = plausible.at[best].set(True)
    paths = jax.vmap(lambda c: model.valve(op, c))(states.chain)
    big = jnp.finfo(op.dtype).max
    hi = jnp.max(jnp.where(plausible[:, None], paths, -big), axis=0)
    lo = jnp.min(jnp.where(plausible[:, None], paths, big), axis=0)
    apart = (hi - lo) > 1e-9 * (1.0 + jnp.abs(hi))
    sync = jnp.max(jnp.where(apart & (w > 0), jnp.arange(op.shape[0]) + 1, 0))
    return jax.tree.map(lambda t: t[best], states), sync.astype(jnp.int32)


def replay(model: LoopModel, loop: Loop, controller: Controller, init_count: int = 8, *,
           initial: InitialState | None = None, sync=None) -> Replay:
    """The replay of `loop` by `model` (see the module notes); `init_count`
    candidate stopping points per direction of the valve for its initial state, or
    `initial` and `sync` when already known (a drawn model reuses its fit's)."""
    dtype = jnp.result_type(loop.op.dtype, jnp.float32)
    op, pv = jnp.asarray(loop.op, dtype), jnp.asarray(loop.pv, dtype)
    w = (jnp.asarray(loop.mask) > 0).astype(dtype)
    if initial is None:
        initial, sync = initial_and_sync(model, op, pv, w, init_count)
    sim = model.simulate(op, initial)
    v = jnp.where(w > 0, pv - sim, 0.0)
    eps = lfilter(model.noise.d.astype(dtype), model.noise.c.astype(dtype), v)
    sp_sim, sp_stat, _ = setpoints(loop, controller)
    return Replay(initial=initial, disturbance=v, innovations=eps, sp_sim=sp_sim, sp_stat=sp_stat, op0=op[0],
                  sync=jnp.asarray(sync, jnp.int32))
