r"""The loop's controller: a PI in velocity form, identified from the record or given.

$$u(t) = u(t-1) + k_p\,\big(e(t-\ell) - e(t-\ell-1)\big) + k_i\,e(t-\ell),\qquad e = SP - PV,$$

OP clipped to `op_limits`; $\ell \in \{0, 1\}$ is the sample the controller lags PV
by (0 when OP answers the PV of its own sample, as in most DCS records; 1 when the
historian stamps OP one sample early). [`jaxstiction.identify_controller`][] finds
$k_p$, $k_i$ by least squares on $\Delta u$ for both lags and keeps the better one:

- from `SP`, `OP` and `PV` when a setpoint is recorded;
- from `OP` and `PV` alone when it is not: the setpoint is then taken as constant, an
  unknown level $r$ that enters as an intercept $k_i r$, fitted with the gains.

A direct-acting loop (a process gain below zero) has negative gains.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._linalg import lstsq


# how the controller was obtained (`Controller.source`)
SOURCES = ("identified from SP, OP and PV", "identified from OP and PV (setpoint taken as constant)", "given")


class Controller(eqx.Module):
    """A PI controller in velocity form (see the module notes).

    - `kp`, `ki`: gains per sample (OP % per PV unit); `lag`: 0 or 1 (an integer
      array, so controllers of different lags batch together);
    - `setpoint`: the constant setpoint level used when the record has none (the
      fitted $r$, or the mean PV when $k_i$ is too small to tell);
    - `op_limits`: OP is clipped to these;
    - `fit`: the share of the variance of ΔOP its law explains (1 for a given one);
    - `source`: an index into `SOURCES` (identified with SP, without, or given).
    """

    kp: Float[Array, ""]
    ki: Float[Array, ""]
    lag: Int[Array, ""] = eqx.field(default_factory=lambda: jnp.array(0))
    setpoint: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.array(jnp.nan))
    op_limits: Float[Array, " 2"] = eqx.field(default_factory=lambda: jnp.array([0.0, 100.0]))
    fit: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.array(1.0))
    source: Int[Array, ""] = eqx.field(default_factory=lambda: jnp.array(2))

    @staticmethod
    def pi(gain, integral_time, ts, *, lag: int = 0, op_limits=(0.0, 100.0)) -> Controller:
        r"""A PI tuning given by the user, in the standard form
        $u = K_c\,(e + \frac{1}{T_i}\int e\,dt)$: `gain` $K_c$ in OP % per PV unit
        (negative for a direct-acting loop), `integral_time` $T_i$ and the sampling
        time `ts` in seconds. In velocity form $k_p = K_c$, $k_i = K_c T_s / T_i$.

        **Raises:** `ValueError` when `integral_time` or `ts` is not positive, or
        `gain` is zero or not finite."""
        gain, integral_time, ts = float(gain), float(integral_time), float(ts)
        if not (integral_time > 0 and ts > 0):
            raise ValueError(f"a PI needs `integral_time` > 0 and `ts` > 0 (seconds), got {integral_time:g} and {ts:g}")
        if not (gain != 0 and math.isfinite(gain)):
            raise ValueError(f"a PI needs a finite, non-zero `gain`, got {gain:g}")
        if lag not in (0, 1):
            raise ValueError(f"`lag` must be 0 or 1, got {lag!r}")
        dtype = jnp.result_type(float)
        return Controller(kp=jnp.asarray(gain, dtype), ki=jnp.asarray(gain * ts / integral_time, dtype),
                          lag=jnp.asarray(lag), op_limits=jnp.asarray(op_limits, dtype))


def _lagged(x, lag: int):
    """`x(t - lag)`, the first sample repeated before the record."""
    return x if lag == 0 else jnp.concatenate([x[:1], x[:-1]])


def _fit_lag(op, e, w, has_sp, lag: int):
    """Least-squares PI of one lag: `(theta, fit)`, `theta = (kp, ki, intercept)`."""
    el = _lagged(e, lag)
    # pairs of real samples, both lags real too
    pair = w[1:] * w[:-1] * (_lagged(w, lag)[1:] if lag else 1.0) * (_lagged(w, lag)[:-1] if lag else 1.0)
    # OP held at a limit is not the controller's law (anti-windup clips it): left out
    lo, hi = jnp.min(jnp.where(w > 0, op, jnp.inf)), jnp.max(jnp.where(w > 0, op, -jnp.inf))
    held = (op[1:] == op[:-1]) & ((op[1:] == lo) | (op[1:] == hi))
    pair = pair * (~held)
    du = jnp.diff(op)
    M = jnp.stack([jnp.diff(el), el[1:], jnp.where(has_sp, 0.0, 1.0) * jnp.ones_like(du)], axis=1)
    theta = lstsq(M * pair[:, None], du * pair)
    res = (du - M @ theta) * pair
    count = jnp.maximum(jnp.sum(pair), 1.0)
    mean = jnp.sum(du * pair) / count
    var = jnp.sum(pair * (du - mean) ** 2) / count
    return theta, 1.0 - jnp.sum(res**2) / count / jnp.maximum(var, 1e-300)


def identify_controller(op: Float[Array, " time"], pv: Float[Array, " time"], sp: Float[Array, " time"],
                        mask: Float[Array, " time"]) -> Controller:
    """The PI controller of one loop from its record (see the module notes).

    **Arguments:** `op`, `pv`, `sp` (all NaN: no setpoint recorded, so it is taken as
    a constant level, fitted with the gains), `mask` (1 on real samples).

    **Returns:** a [`jaxstiction.Controller`][] with `fit`, the share of ΔOP's variance
    its law explains, and `source` 0 (with SP) or 1 (constant SP). Pure and
    vmappable; least squares by Householder QR. OP limits are those of the record,
    widened to [0, 100] when it stays inside."""
    dtype = jnp.result_type(op.dtype, pv.dtype, jnp.float32)
    op, pv, sp = (jnp.asarray(x, dtype) for x in (op, pv, sp))
    w = (jnp.asarray(mask) > 0).astype(dtype)
    has_sp = jnp.all(jnp.where(w > 0, jnp.isfinite(sp), True))
    e = jnp.where(has_sp, jnp.where(w > 0, sp, 0.0) - pv, -pv) * w
    op = op * w
    fits = [_fit_lag(op, e, w, has_sp, lag) for lag in (0, 1)]
    better = fits[1][1] > fits[0][1] + 1e-3  # lag 0 unless lag 1 explains clearly more
    theta = jnp.where(better, fits[1][0], fits[0][0])
    fit = jnp.where(better, fits[1][1], fits[0][1])
    count = jnp.maximum(jnp.sum(w), 1.0)
    pv_mean = jnp.sum(w * pv) / count
    big = jnp.finfo(dtype).max
    pv_lo, pv_hi = jnp.min(jnp.where(w > 0, pv, big)), jnp.max(jnp.where(w > 0, pv, -big))
    # the constant setpoint: the intercept over k_i, when that is a level near the record's
    r = theta[2] / jnp.where(theta[1] != 0, theta[1], 1.0)
    span = pv_hi - pv_lo
    r_ok = (jnp.abs(theta[1]) > 0) & (r >= pv_lo - span) & (r <= pv_hi + span)
    setpoint = jnp.where(has_sp, jnp.nan, jnp.where(r_ok, r, pv_mean))
    lo, hi = jnp.min(jnp.where(w > 0, op, big)), jnp.max(jnp.where(w > 0, op, -big))
    limits = jnp.stack([jnp.minimum(lo, 0.0), jnp.maximum(hi, 100.0)])
    return Controller(kp=theta[0], ki=theta[1], lag=better.astype(jnp.int32), setpoint=setpoint, op_limits=limits,
                      fit=jnp.clip(fit, -1.0, 1.0), source=jnp.where(has_sp, 0, 1).astype(jnp.int32))
