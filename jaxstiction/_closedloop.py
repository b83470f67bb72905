r"""The loop closed again in simulation: the controller identified from the record,
and a fitted loop model run under it.

A sticky valve shows itself in closed loop as a limit cycle. With the controller
known, a fitted valve and process can be put back into the loop and asked whether
they cycle as the record does: a Kano valve that reproduces the recorded cycle's
period and amplitude, where a linear valve in the same loop does not, is evidence
that the cycle is the valve's. The same closed loop answers what a repair would buy
(the valve made linear) under the disturbance the loop saw.

The controller is a PI(D) in velocity form,
$u(t) = u(t-1) + k_p (e(t) - e(t-1)) + k_i e(t)$, $e = SP - PV$, identified by least
squares from the record (`identify_controller`): from `SP`, `OP` and `PV` when a
setpoint is recorded; from `OP` and `PV` alone when it is not, with the setpoint
taken as constant (an unknown level, fitted).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._filters import steady_state
from ._linalg import lstsq
from ._models import LoopModel


class Controller(eqx.Module):
    """A PI controller in velocity form (see the module notes): gains `kp`, `ki`
    (per sample), OP clipped to `op_limits`. `fit` is the share of the variance of
    ΔOP its law explains (1 for a controller given by the user). A direct-acting
    loop has negative gains."""

    kp: Float[Array, ""]
    ki: Float[Array, ""]
    op_limits: Float[Array, " 2"] = eqx.field(default_factory=lambda: jnp.array([0.0, 100.0]))
    fit: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.array(1.0))


def identify_controller(op, pv, sp, mask) -> Controller:
    """The PI controller of one loop from its record (see the module notes). `sp`
    all NaN: no setpoint recorded, so it is taken as a constant level, fitted with
    the gains. Pure and vmappable; least squares by Householder QR."""
    w = (mask > 0).astype(op.dtype)
    pair = w[1:] * w[:-1]
    has_sp = jnp.all(jnp.where(w > 0, jnp.isfinite(sp), True))
    e = jnp.where(has_sp, jnp.where(w > 0, sp, 0.0) - pv, -pv)
    du = jnp.diff(op)
    de = jnp.diff(e)
    # with no setpoint, e = r - PV with r unknown: k_i r enters as an intercept
    M = jnp.stack([de, e[1:], jnp.where(has_sp, 0.0, 1.0) * jnp.ones_like(de)], axis=1) * pair[:, None]
    theta = lstsq(M, du * pair)
    res = du * pair - M @ theta
    count = jnp.maximum(jnp.sum(pair), 1.0)
    mean = jnp.sum(du * pair) / count
    var = jnp.sum(pair * (du - mean) ** 2) / count
    fit = 1.0 - jnp.sum(res**2) / count / jnp.maximum(var, 1e-300)
    big = jnp.finfo(op.dtype).max
    lo, hi = jnp.min(jnp.where(w > 0, op, big)), jnp.max(jnp.where(w > 0, op, -big))
    limits = jnp.stack([jnp.minimum(lo, 0.0), jnp.maximum(hi, 100.0)])
    return Controller(kp=theta[0], ki=theta[1], op_limits=limits, fit=jnp.clip(fit, -1.0, 1.0))


def closed_loop(model: LoopModel, controller: Controller, sp: Float[Array, " time"],
                disturbance: Float[Array, " time"], op0):
    """`(op, pv, valve)`: `model` run in closed loop under `controller` with setpoint
    `sp` and `disturbance` added to PV, from rest at OP = `op0` (every block at rest
    there, the process at steady state). Pure; vmappable over models and signals."""
    dtype = sp.dtype
    op0 = jnp.asarray(op0, dtype)
    b, a = model.process.polynomials()
    b, a = b.astype(dtype), a.astype(dtype)
    off = model.op_offset.astype(dtype)
    chain = tuple(model.chain)
    states, v0 = model._chain_init(op0)
    z0 = steady_state(b, a, v0 - off, dtype)
    y0 = z0[0]
    lo, hi = controller.op_limits[0], controller.op_limits[1]

    def body(carry, inputs):
        u1, e1, cs, z = carry
        r_t, d_t = inputs
        y = z[0]
        pv = y + model.pv_offset + d_t
        e = r_t - pv
        u = jnp.clip(u1 + controller.kp * (e - e1) + controller.ki * e, lo, hi)
        new = []
        x = u
        for blk, s in zip(chain, cs):
            s, x = blk.step(s, x)
            new.append(s)
        xd = x - off
        z = jnp.concatenate([z[1:], jnp.zeros((1,), dtype)]) + b[1:] * xd - a[1:] * y
        return (u, e, tuple(new), z), (u, pv, x)

    e0 = sp[0] - (y0 + model.pv_offset + disturbance[0])
    _, (u, pv, x) = jax.lax.scan(body, (op0, e0, tuple(states), z0), (sp, disturbance))
    return u, pv, x
