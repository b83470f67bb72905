r"""The loop closed again in simulation, and what to measure on it.

`closed_loop` runs a fitted [`jaxstiction.LoopModel`][] under a
[`jaxstiction.Controller`][] in one `lax.scan`: setpoint → controller (→ knocker)
→ input chain (the valve) → process → + disturbance → PV, which the controller sees:

$$PV(t) = \text{pv\_offset} + \frac{B(q)}{A(q)}\big(x(t) - \text{op\_offset}\big) + v(t),
\qquad x = \text{chain}\big(u + k\big),$$

with $u$ the controller's output and $k$ the knocker's pulses (0 without one).
Started from a model's [`jaxstiction.InitialState`][] and with $u(0)$ the recorded
OP, a model run under the disturbance $v = PV - \text{simulation of the recorded OP}$
reproduces the record exactly when the controller is exact: the as-is loop *is* the
record, and changing the valve changes only what the valve changes.

A [`jaxstiction.Knocker`][] (Hägglund 2002) adds to OP pulses of amplitude $a$ and
width $\tau$ samples every $h$ samples, each in the direction OP moved since the last
pulse started. `SmoothKano` is Kano's valve with its thresholds made sigmoids, for
gradients with respect to a compensator's parameters.

What to read off a run is the what-if's (`jaxstiction._whatif.stats`); the verdict
closes the fitted loop too, to see whether it reproduces the recorded limit cycle.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._blocks import _f, AbstractBlock, Kano
from .._linalg import is_stable
from .._models import InitialState, LoopModel
from .controller import Controller


def with_valve(model: LoopModel, S, J) -> LoopModel:
    """`model` with its first block (a Kano valve) set to `S`, `J` (`S = J = 0`: the
    valve repaired, the same process)."""
    return eqx.tree_at(lambda m: m.chain[0], model, Kano(S, J))


class Knocker(eqx.Module):
    """Hägglund's (2002) knocker: pulses of `amplitude` (% of span) and `width`
    samples every `period` samples, added to OP in the direction OP moved since the
    previous pulse started (no pulse while it has not moved).

    `soft` (static, samples): 0 for the exact pulse ($k \\ne 0$ while the phase is
    below `width`); above 0 the pulse's edges are sigmoids of that width, so a
    simulation is differentiable in `width` too (for `method="gradient"`)."""

    amplitude: Float[Array, ""] = eqx.field(converter=_f)
    width: Float[Array, ""] = eqx.field(converter=_f)
    period: Array = eqx.field(converter=jnp.asarray)
    soft: float = eqx.field(static=True, default=0.0)

    def init(self, u0):
        """`(sign, OP at the last pulse start)`."""
        u0 = jnp.asarray(u0)
        return jnp.zeros_like(u0), u0

    def step(self, state, t, u):
        """`(state, pulse)` at sample `t` for controller output `u`."""
        sign, u_last = state
        phase = jnp.mod(t, self.period)
        start = phase == 0
        moved = jnp.sign(u - u_last)
        sign = jnp.where(start & (moved != 0), moved, sign)
        u_last = jnp.where(start, u, u_last)
        edge = self.width - phase.astype(u.dtype) - 0.5
        on = jax.nn.sigmoid(edge / self.soft) if self.soft > 0 else (edge > 0).astype(u.dtype)
        return (sign, u_last), self.amplitude * sign * on


class SmoothKano(AbstractBlock):
    """[`jaxstiction.Kano`][] with its decisions made smooth: each threshold test
    (stop, reverse past `S`, slip past `J`) is a sigmoid of width `eps` (% of span)
    and the state (stuck share, direction) is continuous. As `eps` → 0 it is Kano's
    valve; for `eps` > 0 a closed-loop simulation through it has gradients with
    respect to what drives it (a compensator's amplitude), where Kano's valve has
    none across its slip events."""

    S: Float[Array, ""] = eqx.field(converter=_f)
    J: Float[Array, ""] = eqx.field(converter=_f)
    eps: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        return Kano.init(self, u0)  # the same state, made continuous by `step`

    def step(self, state, u):
        S, J, eps = self.S, self.J, self.eps
        y, us, stp, d, u_prev, du_prev = state
        du = u - u_prev
        sig = jax.nn.sigmoid
        stops = sig(-du * du_prev / eps**2) * (1.0 - stp)
        us = us + stops * (u_prev - us)
        stp = stp + stops
        reverse = stp * sig((-d * (u - us) - S) / eps)
        same = (stp - reverse) * sig((d * (u - us) - J) / eps)
        d = d * (1.0 - 2.0 * reverse)
        go = (1.0 - stp) + reverse + same
        y = go * (u - d * (S - J) / 2) + (1.0 - go) * y
        stp = stp - reverse - same
        return (y, us, stp, d, u, du), y

    def initial_states(self, u_open, count: int):
        return jax.tree.map(lambda t: jnp.asarray(t)[None], self.init(jnp.asarray(u_open)[0]))


class ClosedLoopRun(eqx.Module):
    """One closed-loop simulation: the controller output `op`, what reached the valve
    `op_valve` (OP plus the knocker's pulses, clipped), the `valve` position (the
    output of the model's first block, the stem, in % of span) and `pv`."""

    op: Float[Array, " time"]
    op_valve: Float[Array, " time"]
    valve: Float[Array, " time"]
    pv: Float[Array, " time"]


def closed_loop(model: LoopModel, controller: Controller, sp: Float[Array, " time"],
                disturbance: Float[Array, " time"], initial: InitialState, op0,
                knocker: Knocker | None = None) -> ClosedLoopRun:
    """`model` run in closed loop under `controller` (and `knocker`) with setpoint
    `sp` and `disturbance` added to PV (see the module notes).

    The model starts from `initial` (its chain's states, the held valve position, the
    process filter's state); the controller's output at the first sample is `op0`
    (the recorded OP), with the error before the record taken as the first one.
    Pure; vmappable over models, controllers, knockers and signals; differentiable
    where the valve is (`SmoothKano`). The process must be strictly proper (b[0] =
    0), as every fitted model is."""
    dtype = jnp.result_type(sp.dtype, jnp.float32)
    sp, disturbance = jnp.asarray(sp, dtype), jnp.asarray(disturbance, dtype)
    b, a = model.process.polynomials()
    b, a = b.astype(dtype), a.astype(dtype)
    off = jnp.asarray(model.op_offset, dtype)
    pv_off = jnp.asarray(model.pv_offset, dtype)
    chain = tuple(model.chain)
    lo, hi = controller.op_limits[0], controller.op_limits[1]
    kp, ki, lag = controller.kp, controller.ki, controller.lag
    z0 = jnp.asarray(initial.filter, dtype)
    op0 = jnp.asarray(op0, dtype)
    e0 = sp[0] - (z0[0] + pv_off + disturbance[0])
    kstate0 = knocker.init(op0) if knocker is not None else ()

    def body(carry, inputs):
        u1, e1, e2, cs, z, holding, first, ks = carry
        t, r, v = inputs
        y = z[0]
        pv = y + pv_off + v
        e = r - pv
        el, el1 = jnp.where(lag == 1, e1, e), jnp.where(lag == 1, e2, e1)
        u = jnp.clip(u1 + kp * (el - el1) + ki * el, lo, hi)
        if knocker is not None:
            ks, k = knocker.step(ks, t, u)
            uv = jnp.clip(u + k, lo, hi)
        else:
            uv = u
        new, x, stem = [], uv, uv
        for i, (blk, s) in enumerate(zip(chain, cs)):
            s, x = blk.step(s, x)
            new.append(s)
            if i == 0:
                stem = x
        # a valve held at an unknown position at the start stays there until the
        # chain's output first changes (as `LoopModel.simulate`)
        first = jnp.where(t == 0, x, first)
        holding = holding & (x == first)
        x = jnp.where(holding, initial.hold, x)
        z = jnp.concatenate([z[1:], jnp.zeros((1,), dtype)]) + b[1:] * (x - off) - a[1:] * y
        return (u, e, e1, tuple(new), z, holding, first, ks), (u, uv, stem, pv)

    n = sp.shape[0]
    carry = (op0 - ki * e0, e0, e0, tuple(initial.chain), z0, jnp.asarray(initial.held, bool),
             jnp.zeros((), dtype), kstate0)
    _, (u, uv, stem, pv) = jax.lax.scan(body, carry, (jnp.arange(n), sp, disturbance))
    return ClosedLoopRun(op=u, op_valve=uv, valve=stem, pv=pv)


def chain_gain(model: LoopModel, op_lo, op_hi) -> Float[Array, ""]:
    """The static gain of `model`'s chain with its valve (the first block) repaired:
    the secant of the blocks that follow it (a fitted valve characteristic, the
    estimator's spline, which also scales OP) over the OP range `[op_lo, op_hi]`,
    each block at rest at its input."""
    def static(u):
        x = u
        for blk in tuple(model.chain)[1:]:
            _, x = blk.step(blk.init(x), x)
        return x

    lo, hi = jnp.asarray(op_lo), jnp.asarray(op_hi)
    width = jnp.maximum(hi - lo, 1e-6 * jnp.maximum(jnp.abs(hi), 1.0))
    return (static(lo + width) - static(lo)) / width


def closed_loop_stable(model: LoopModel, controller: Controller, op_lo, op_hi, margin=0.0) -> Bool[Array, ""]:
    r"""Whether `model`'s loop with its valve repaired, closed under `controller`'s PI
    (in velocity form, lag 0 or 1), is stable, linearised over the OP range
    `[op_lo, op_hi]`: the roots of
    $A(q^{-1})(1 - q^{-1}) + q^{-\ell} g B(q^{-1}) \big(k_p + k_i - k_p q^{-1}\big)$,
    with $g$ the static gain of the blocks after the valve (`chain_gain`), inside
    the circle of radius `1 - margin` (`is_stable`)."""
    b, a = model.process.polynomials()
    b = b * chain_gain(model, op_lo, op_hi).astype(b.dtype)
    c = jnp.stack([controller.kp + controller.ki, -controller.kp]).astype(a.dtype)
    left = jnp.convolve(a, jnp.asarray([1.0, -1.0], a.dtype))
    right = jnp.convolve(b, c)
    n = max(left.shape[0], right.shape[0]) + 1

    def padded(x, shift):
        return jnp.zeros((n,), a.dtype).at[shift:shift + x.shape[0]].set(x)

    char = jnp.where(controller.lag == 1, padded(left, 0) + padded(right, 1), padded(left, 0) + padded(right, 0))
    return is_stable(char, margin)
