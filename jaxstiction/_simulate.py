"""Closed-loop simulation of a plant [`jaxstiction.LoopModel`][] under PI(D) control.

The whole loop runs in one `lax.scan`: setpoint → controller → input chain of
blocks → process → (+ noise, output-side blocks) → PV, which the controller sees.
The noise gain that reaches a requested noise-to-signal ratio is found by a few
closed-loop passes inside the same jitted call, so [`jaxstiction.simulate_loop`][]
can be `vmap`ped over keys and over plant parameters.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jax.tree_util as jtu
from jaxtyping import Array, Float, PRNGKeyArray

from ._blocks import _f, Quantiser
from ._filters import lfilter, steady_state
from ._loop import Loop
from ._models import LoopModel


class Experiment(eqx.Module):
    """How the loop is operated: controller, setpoint and noise level.

    - `kc`: velocity-form PID $u(t) = u(t-1) + k_0 e(t) + k_1 e(t-1) + k_2 e(t-2)$,
      $e = r - PV$; OP starts at the plant's `op_offset` and is clipped to `op_limits`.
    - `sp_amplitude`, `sp_switch_prob`: setpoint GBN $r = \\pm$amplitude (around the
      plant's `pv_offset`), its sign switching with that probability each sample.
    - `nsr`: requested var(noise)/var(noise-free PV); the plant's noise model $C/D$
      shapes the noise.
    """

    kc: Float[Array, 3] = eqx.field(converter=_f, default=(0.31, -0.3, 0.0))
    op_limits: Float[Array, 2] = eqx.field(converter=_f, default=(0.0, 100.0))
    sp_amplitude: Float[Array, ""] = eqx.field(converter=_f, default=20.0)
    sp_switch_prob: Float[Array, ""] = eqx.field(converter=_f, default=0.05)
    nsr: Float[Array, ""] = eqx.field(converter=_f, default=0.05)
    nsr_iterations: int = eqx.field(static=True, default=24)


class LoopRecord(eqx.Module):
    """A simulated record: `op`, `pv` (measured), `pv_clean` (noise-free, before
    quantisation), `sp`, `valve` (process input, i.e. the chain's output), `t`, the
    noise gain used and the noise-to-signal ratio achieved."""

    op: Float[Array, "*batch time"]
    pv: Float[Array, "*batch time"]
    pv_clean: Float[Array, "*batch time"]
    sp: Float[Array, "*batch time"]
    valve: Float[Array, "*batch time"]
    t: Float[Array, "*batch time"]
    noise_gain: Float[Array, "*batch"]
    nsr: Float[Array, "*batch"]

    def window(self, start: int, stop: int) -> LoopRecord:
        """Samples `start:stop` of every series, keeping their times."""
        sl = slice(start, stop)
        return LoopRecord(self.op[..., sl], self.pv[..., sl], self.pv_clean[..., sl], self.sp[..., sl],
                          self.valve[..., sl], self.t[..., sl], self.noise_gain, self.nsr)

    @property
    def loop(self) -> Loop:
        """The record as a [`jaxstiction.Loop`][] (OP and measured PV, Ts = 1 s)."""
        return Loop(op=self.op, pv=self.pv, mask=jnp.ones_like(self.op), ts=jnp.ones(self.op.shape[:-1], self.op.dtype))

    def __len__(self) -> int:
        return self.op.shape[-1]


def _run(plant: LoopModel, exp: Experiment, r, v_unit, alpha):
    """One closed-loop pass for noise gain `alpha`: `(op, pv, pv_clean, valve)`."""
    dtype = r.dtype
    b, a = plant.process.polynomials()
    off = plant.op_offset.astype(dtype)
    kc = exp.kc.astype(dtype)
    lo, hi = exp.op_limits.astype(dtype)[0], exp.op_limits.astype(dtype)[1]
    chain = tuple(plant.chain)
    outs = tuple(plant.output)
    clean_outs = tuple(o for o in outs if not isinstance(o, Quantiser))

    def chain_step(states, u):
        new, v = [], u
        for blk, s in zip(chain, states):
            s, v = blk.step(s, v)
            new.append(s)
        return tuple(new), v

    def out_step(blocks, states, y):
        new, v = [], y
        for blk, s in zip(blocks, states):
            s, v = blk.step(s, v)
            new.append(s)
        return tuple(new), v

    def body(carry, inp):
        u_prev, e1, e2, cs, z, os, ocs = carry
        r_t, v_t = inp
        y = z[0] + plant.pv_offset  # b[0] = 0: the output depends on past inputs only
        ocs, pv_clean = out_step(clean_outs, ocs, y)
        os, pv = out_step(outs, os, y + alpha * v_t)
        err = r_t - pv
        u = jnp.clip(u_prev + kc[0] * err + kc[1] * e1 + kc[2] * e2, lo, hi)
        cs, x = chain_step(cs, u)
        xd = x - off
        z = jnp.concatenate([z[1:], jnp.zeros((1,), dtype)]) + b[1:] * xd - a[1:] * (y - plant.pv_offset)
        return (u, err, e1, cs, z, os, ocs), (u, pv, pv_clean, x)

    zero = jnp.zeros((), dtype)
    states, v = [], off
    for blk in chain:
        s = blk.init(v)
        states.append(s)
        _, v = blk.step(s, v)
    z0 = steady_state(b, a, v - off, dtype)
    os0 = tuple(o.init(zero) for o in outs)
    ocs0 = tuple(o.init(zero) for o in clean_outs)
    carry0 = (off, zero, zero, tuple(states), z0, os0, ocs0)
    _, out = jax.lax.scan(body, carry0, (r, v_unit))
    return out


def _check_causal(plant: LoopModel):
    b, _ = plant.process.polynomials()
    if not isinstance(b, jax.core.Tracer) and b.ndim == 1 and float(b[0]) != 0.0:
        raise ValueError(
            f"the plant's process has b[0] = {float(b[0])} with no delay: the closed loop would be algebraic; "
            "set b[0] = 0 or a delay >= 1"
        )


def simulate_loop(plant: LoopModel, experiment: Experiment, key: PRNGKeyArray, n: int) -> LoopRecord:
    """Simulate `n` samples of `plant` in closed loop under `experiment`.

    Before $t = 0$ the loop is at rest: OP at the plant's `op_offset`, every block at
    rest there, the process at steady state. The setpoint GBN and the white noise
    are drawn from `key`; the noise gain $\\alpha$ is found with
    `experiment.nsr_iterations` closed-loop passes (fixed-point steps
    $\\alpha \\leftarrow \\sqrt{\\text{nsr}\\,\\mathrm{var}(\\text{pv\\_clean})/
    \\mathrm{var}(C/D\\,e)}$, then bisection in $\\log\\alpha$ once the target is
    bracketed: with stiction var(pv_clean) jumps with $\\alpha$); the best pass is
    returned and the ratio achieved is in `LoopRecord.nsr`. `vmap` over `key` (and
    over numeric plant or experiment fields) works.

    **Raises:** `ValueError` if `n` is not a Python int >= 2, or if the process is not
    strictly proper (b[0] ≠ 0 with no delay).
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 2:
        raise ValueError(f"`n` must be a Python int >= 2, got {n!r}.")
    _check_causal(plant)
    return _simulate_loop(plant, experiment, key, n)


@eqx.filter_jit
def _simulate_loop(plant: LoopModel, experiment: Experiment, key: PRNGKeyArray, n: int) -> LoopRecord:
    dtype = jnp.result_type(plant.op_offset, experiment.kc)
    k_sign, k_switch, k_e, _ = jr.split(key, 4)
    sign0 = jnp.where(jr.bernoulli(k_sign), 1.0, -1.0).astype(dtype)
    switch = (jr.uniform(k_switch, (n,), dtype) < experiment.sp_switch_prob).at[0].set(False)
    parity = jnp.cumsum(switch.astype(jnp.int32)) % 2
    r = experiment.sp_amplitude.astype(dtype) * sign0 * (1 - 2 * parity).astype(dtype) + plant.pv_offset
    e = jr.normal(k_e, (n,), dtype)
    v_unit = lfilter(plant.noise.c.astype(dtype), plant.noise.d.astype(dtype), e)
    var_v = jnp.var(v_unit)
    nsr = experiment.nsr.astype(dtype)
    nsr_safe = jnp.where(nsr > 0, nsr, 1.0)
    inf = jnp.asarray(jnp.inf, dtype)

    def search(_, carry):
        alpha, lo, hi, best_err, best = carry
        out = _run(plant, experiment, r, v_unit, alpha)
        var_c = jnp.var(out[2])
        ratio = alpha**2 * var_v / var_c
        err = jnp.where(alpha > 0, jnp.abs(jnp.log(ratio / nsr_safe)), inf)
        err = jnp.where(nsr > 0, err, 0.0)
        better = err < best_err
        best_err = jnp.where(better, err, best_err)
        best = jtu.tree_map(lambda new, old: jnp.where(better, new, old), (alpha, ratio, out), best)
        below = ratio < nsr
        lo, hi = jnp.where(below, alpha, lo), jnp.where(below, hi, alpha)
        proposal = jnp.sqrt(nsr * var_c / var_v)
        mid = jnp.where(lo > 0, jnp.sqrt(lo * hi), hi / 2)
        alpha = jnp.where(jnp.isfinite(hi), mid, proposal)
        return alpha, lo, hi, best_err, best

    zero = jnp.zeros((), dtype)
    empty = (zero, zero, (jnp.zeros((n,), dtype),) * 4)
    carry = (zero, zero, inf, inf, empty)
    *_, (alpha, achieved, (op, pv, pv_clean, valve)) = jax.lax.fori_loop(0, experiment.nsr_iterations, search, carry)
    return LoopRecord(op=op, pv=pv, pv_clean=pv_clean, sp=r, valve=valve, t=jnp.arange(n, dtype=dtype),
                      noise_gain=alpha, nsr=achieved)
