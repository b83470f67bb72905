"""Closed-loop simulator of a control loop with the valve physics of DESIGN §3.

The whole loop runs in one `lax.scan`; the noise gain that reaches a requested
noise-to-signal ratio is found by a few fixed-point iterations inside the same jitted
call, so [`jaxstiction.simulate_loop`][] can be `vmap`ped over keys (and over the
numeric fields of [`jaxstiction.LoopConfig`][]).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jax.tree_util as jtu
from jaxtyping import Array, Float, PRNGKeyArray

from ._blocks import (
    actuator_lag_step,
    choudhury_init,
    choudhury_step,
    deadband_init,
    deadband_step,
    equal_percentage,
    he_init,
    he_step,
    kano_init,
    kano_step,
    quantize,
    random_walk,
    rate_limit_step,
    sinusoid,
)


STICTION_KINDS = ("none", "kano", "choudhury", "he", "deadband")


def _as_poly(x) -> tuple[float, ...]:
    return tuple(float(v) for v in x)


def _as_float(x) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return x


def _as_opt_float(x) -> Array | None:
    return None if x is None else _as_float(x)


class LoopConfig(eqx.Module):
    """Settings of one simulated control loop (defaults: the `paper_sim` loop, no valve
    fault).

    Signal chain (DESIGN §3): OP → actuator lag → rate limit → stiction / deadband →
    travel limits → equal-percentage characteristic → dead time → $G(q) = B/A$ →
    + noise $v = \\alpha\\,C/D\\,e$, sinusoid, drift → quantisation → PV. The
    controller sees the measured (quantised) PV.

    **Process and noise** (static tuples, polynomials in $q^{-1}$ from $q^0$):

    - `b`, `a`: process $B/A$; input is valve position minus `op_offset`. `b[0]` must be
      0 unless `dead_time >= 1` (a closed loop needs one sample of delay).
    - `noise_c`, `noise_d`: noise colouring $C/D$ driven by white $N(0, 1)$ noise.
    - `nsr`: requested $\\mathrm{var}(v)/\\mathrm{var}(\\text{noise-free PV})$; the gain
      $\\alpha$ is found with `nsr_iterations` closed-loop passes (fixed-point steps,
      then bisection once bracketed; see [`jaxstiction.simulate_loop`][]).

    **Controller and setpoint:**

    - `kc`: velocity-form PID, $u(t) = u(t-1) + k_0 e(t) + k_1 e(t-1) + k_2 e(t-2)$,
      $e = r - PV$; OP is clipped to `op_limits` and starts at `op_offset`.
    - `sp_amplitude`, `sp_switch_prob`: setpoint GBN $r = \\pm$amplitude, its sign
      switching with that probability each sample (initial sign random).

    **Valve and plant faults** ("off" by default):

    - `stiction`: `'none' | 'kano' | 'choudhury' | 'he' | 'deadband'` (static) with `S`
      (deadband + stickband) and `J` (slip jump), % of span. `'he'` uses
      $f_s = (S+J)/2$, $f_d = (S-J)/2$; `'deadband'` uses width `S` (J ignored).
    - `actuator_lag`: pole `a` of $x_a(t) = a x_a(t-1) + (1-a) u(t)$ (0 = off).
    - `rate_limit`: max stem move per sample (`None` = off).
    - `travel_lo`, `travel_hi`: stem travel limits (`None` = off).
    - `equal_percentage_R`: rangeability of the inherent characteristic
      (`None` = linear).
    - `dead_time`: extra whole samples of delay (static int).
    - `sin_amplitude`, `sin_period`, `sin_phase`: output sinusoid (period in samples).
    - `drift_std`: step std of a random-walk drift added at the output.
    - `quant_step`: sensor quantisation step (`None` = off).

    Before $t = 0$ the plant is at rest: OP, actuator and valve at `op_offset`, process
    input deviation and output zero, noise filter at rest.
    """

    b: tuple[float, ...] = eqx.field(
        static=True, converter=_as_poly, default=(0.0, 1.0, 0.5)
    )
    a: tuple[float, ...] = eqx.field(
        static=True, converter=_as_poly, default=(1.0, -1.5, 0.7)
    )
    noise_c: tuple[float, ...] = eqx.field(
        static=True, converter=_as_poly, default=(1.0,)
    )
    noise_d: tuple[float, ...] = eqx.field(
        static=True, converter=_as_poly, default=(1.0, -0.9)
    )
    kc: Float[Array, "3"] = eqx.field(converter=_as_float, default=(0.31, -0.3, 0.0))
    op_offset: Float[Array, ""] = eqx.field(converter=_as_float, default=50.0)
    op_limits: Float[Array, "2"] = eqx.field(converter=_as_float, default=(0.0, 100.0))
    sp_amplitude: Float[Array, ""] = eqx.field(converter=_as_float, default=20.0)
    sp_switch_prob: Float[Array, ""] = eqx.field(converter=_as_float, default=0.05)
    nsr: Float[Array, ""] = eqx.field(converter=_as_float, default=0.05)
    stiction: str = eqx.field(static=True, default="none")
    S: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    J: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    actuator_lag: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    rate_limit: Float[Array, ""] | None = eqx.field(
        converter=_as_opt_float, default=None
    )
    travel_lo: Float[Array, ""] | None = eqx.field(
        converter=_as_opt_float, default=None
    )
    travel_hi: Float[Array, ""] | None = eqx.field(
        converter=_as_opt_float, default=None
    )
    equal_percentage_R: Float[Array, ""] | None = eqx.field(
        converter=_as_opt_float, default=None
    )
    dead_time: int = eqx.field(static=True, default=0)
    sin_amplitude: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    sin_period: Float[Array, ""] = eqx.field(converter=_as_float, default=50.0)
    sin_phase: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    drift_std: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    quant_step: Float[Array, ""] | None = eqx.field(
        converter=_as_opt_float, default=None
    )
    nsr_iterations: int = eqx.field(static=True, default=24)

    def __check_init__(self):
        if self.stiction not in STICTION_KINDS:
            raise ValueError(
                f"`stiction` must be one of {', '.join(STICTION_KINDS)}; "
                f"got {self.stiction!r}."
            )
        if (
            isinstance(self.dead_time, bool)
            or not isinstance(self.dead_time, int)
            or self.dead_time < 0
        ):
            raise ValueError(
                "`dead_time` must be a non-negative Python int, got "
                f"{self.dead_time!r}."
            )
        if len(self.a) == 0 or self.a[0] == 0 or len(self.b) == 0:
            raise ValueError(
                "`a` must start with a non-zero coefficient and `b` must be "
                "non-empty; "
                f"got a={self.a}, b={self.b}."
            )
        if len(self.noise_d) == 0 or self.noise_d[0] == 0 or len(self.noise_c) == 0:
            raise ValueError(
                f"`noise_d` must start with a non-zero coefficient; got {self.noise_d}."
            )
        if self.b[0] != 0 and self.dead_time == 0:
            raise ValueError(
                f"`b[0]` is {self.b[0]} with `dead_time=0`: the closed loop would be "
                "algebraic; set b[0] = 0 (e.g. b=(0., 1., 0.5)) or dead_time >= 1."
            )
        if self.nsr_iterations < 2:
            raise ValueError(
                f"`nsr_iterations` must be >= 2, got {self.nsr_iterations}."
            )


class LoopRecord(eqx.Module):
    """One simulated (or sliced) loop record; all series in engineering units / % span.

    - `op`: controller output (after clipping).
    - `pv`: measured process variable (with noise, quantised).
    - `pv_clean`: `pv` without the stochastic noise $v$ and before quantisation
      (sinusoid and drift stay in).
    - `sp`: setpoint.
    - `valve`: valve position after stiction, travel limits and characteristic (before
      dead time).
    - `t`: sample times, `index * ts` (a slice keeps its place on the time axis).
    - `noise_gain`: the $\\alpha$ used; `nsr`: the achieved
      $\\mathrm{var}(v)/\\mathrm{var}(\\text{pv\\_clean})$ over the simulated run.
    - `ts`: sample time (static, 1.0).
    """

    op: Float[Array, "*batch time"]
    pv: Float[Array, "*batch time"]
    pv_clean: Float[Array, "*batch time"]
    sp: Float[Array, "*batch time"]
    valve: Float[Array, "*batch time"]
    t: Float[Array, "*batch time"]
    noise_gain: Float[Array, "*batch"]
    nsr: Float[Array, "*batch"]
    ts: float = eqx.field(static=True, default=1.0)

    def window(self, start: int, stop: int) -> "LoopRecord":
        """Samples `start:stop` of every series (last axis), keeping their times."""
        sl = slice(start, stop)
        return LoopRecord(
            op=self.op[..., sl],
            pv=self.pv[..., sl],
            pv_clean=self.pv_clean[..., sl],
            sp=self.sp[..., sl],
            valve=self.valve[..., sl],
            t=self.t[..., sl],
            noise_gain=self.noise_gain,
            nsr=self.nsr,
            ts=self.ts,
        )

    def __len__(self) -> int:
        return self.op.shape[-1]


def _push(hist, value):
    """Shift a most-recent-first history by one sample, inserting `value`."""
    return jnp.concatenate([value[None], hist])[: hist.shape[0]]


def _lfilter(b: tuple[float, ...], a: tuple[float, ...], x):
    """`scipy.signal.lfilter(b, a, x)` with zero initial conditions, as a `lax.scan`."""
    b = tuple(v / a[0] for v in b)
    a = tuple(v / a[0] for v in a)
    xh0 = jnp.zeros((max(len(b) - 1, 0),), x.dtype)
    yh0 = jnp.zeros((max(len(a) - 1, 0),), x.dtype)

    def step(carry, xt):
        xh, yh = carry
        yt = b[0] * xt
        for i in range(1, len(b)):
            yt = yt + b[i] * xh[i - 1]
        for j in range(1, len(a)):
            yt = yt - a[j] * yh[j - 1]
        return (_push(xh, xt), _push(yh, yt)), yt

    _, y = jax.lax.scan(step, (xh0, yh0), x)
    return y


def _stiction_fns(cfg: LoopConfig, dtype):
    S = cfg.S.astype(dtype)
    J = cfg.J.astype(dtype)
    kind = cfg.stiction
    if kind == "none":
        return (lambda u0: ()), (lambda s, x: (s, x))
    if kind == "kano":
        return kano_init, (lambda s, x: kano_step(s, x, S, J))
    if kind == "choudhury":
        return choudhury_init, (lambda s, x: choudhury_step(s, x, S, J))
    if kind == "he":
        fs, fd = (S + J) / 2, (S - J) / 2
        return he_init, (lambda s, x: he_step(s, x, fs, fd))
    return deadband_init, (lambda s, x: deadband_step(s, x, S))


def _run_loop(cfg: LoopConfig, r, dist, v_unit, alpha):
    """One closed-loop pass for a given noise gain: `(op, pv, pv_clean, valve)`."""
    dtype = r.dtype
    f = lambda x: None if x is None else jnp.asarray(x, dtype)
    off = f(cfg.op_offset)
    kc = f(cfg.kc)
    op_lo, op_hi = f(cfg.op_limits)[0], f(cfg.op_limits)[1]
    lag = f(cfg.actuator_lag)
    rmax, t_lo, t_hi = f(cfg.rate_limit), f(cfg.travel_lo), f(cfg.travel_hi)
    R, q = f(cfg.equal_percentage_R), f(cfg.quant_step)
    b, a, k = cfg.b, cfg.a, cfg.dead_time
    stic_init, stic_step = _stiction_fns(cfg, dtype)
    n_hist = max(k + len(b) - 1, 1)  # valve(t-1), ..., valve(t-n_hist)

    def body(carry, inp):
        u_prev, e1, e2, x_lag, x_rate, stic, vh, yh = carry
        r_t, dist_t, v_t = inp
        # Process output from past valve positions (b[0] term needs k >= 1).
        acc = jnp.zeros((), dtype)
        for i, bi in enumerate(b):
            if bi != 0.0:
                acc = acc + bi * (vh[k + i - 1] - off)
        for j in range(1, len(a)):
            acc = acc - a[j] * yh[j - 1]
        y_g = acc / a[0]
        pv_clean = y_g + dist_t
        pv = pv_clean + alpha * v_t
        if q is not None:
            pv = quantize(pv, q)
        # Controller (velocity form) on the measured PV.
        err = r_t - pv
        u = jnp.clip(u_prev + kc[0] * err + kc[1] * e1 + kc[2] * e2, op_lo, op_hi)
        # Valve chain.
        x_lag, x = actuator_lag_step(x_lag, u, lag)
        if rmax is not None:
            x_rate, x = rate_limit_step(x_rate, x, rmax)
        stic, x = stic_step(stic, x)
        if t_lo is not None:
            x = jnp.maximum(x, t_lo)
        if t_hi is not None:
            x = jnp.minimum(x, t_hi)
        if R is not None:
            x = equal_percentage(x, R)
        carry = (u, err, e1, x_lag, x_rate, stic, _push(vh, x), _push(yh, y_g))
        return carry, (u, pv, pv_clean, x)

    zero = jnp.zeros((), dtype)
    carry0 = (
        off,
        zero,
        zero,
        off,
        off,
        stic_init(off),
        jnp.full((n_hist,), off, dtype),
        jnp.zeros((len(a) - 1,), dtype),
    )
    _, out = jax.lax.scan(body, carry0, (r, dist, v_unit))
    return out


@eqx.filter_jit
def simulate_loop(config: LoopConfig, key: PRNGKeyArray, n: int) -> LoopRecord:
    """Simulate `n` samples of the closed loop described by `config`.

    The setpoint GBN, white noise $e$ and drift are drawn from `key` (split four ways);
    the noise gain $\\alpha$ is found with `config.nsr_iterations` closed-loop passes:
    fixed-point steps $\\alpha \\leftarrow \\sqrt{\\text{nsr}\\,
    \\mathrm{var}(\\text{pv\\_clean}(\\alpha)) / \\mathrm{var}(C/D\\,e)}$ from a
    noise-free pass, then bisection in $\\log\\alpha$ once the target is bracketed
    (with stiction, var(pv_clean) jumps with $\\alpha$ and the plain iteration cycles);
    the best $\\alpha$ seen is used and the achieved ratio is returned in
    `LoopRecord.nsr`. Jit-compiled; `vmap` over `key` (and over numeric
    config fields) works. Uses the float dtype of the config (float64 under x64).

    **Arguments:**

    - `config`: a [`jaxstiction.LoopConfig`][].
    - `key`: a JAX PRNG key.
    - `n`: number of samples (static Python int).

    **Returns:** a [`jaxstiction.LoopRecord`][].

    **Raises:** `ValueError` if `n` is not a Python int >= 2.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 2:
        raise ValueError(f"`n` must be a Python int >= 2, got {n!r}.")
    dtype = jnp.result_type(config.op_offset, config.kc, config.S)
    k_sign, k_switch, k_e, k_drift = jr.split(key, 4)
    # Setpoint: generalised binary noise.
    sign0 = jnp.where(jr.bernoulli(k_sign), 1.0, -1.0).astype(dtype)
    switch = (
        (jr.uniform(k_switch, (n,), dtype) < config.sp_switch_prob).at[0].set(False)
    )
    parity = jnp.cumsum(switch.astype(jnp.int32)) % 2
    r = config.sp_amplitude.astype(dtype) * sign0 * (1 - 2 * parity).astype(dtype)
    # Disturbances.
    e = jr.normal(k_e, (n,), dtype)
    v_unit = _lfilter(config.noise_c, config.noise_d, e)
    dist = sinusoid(
        n,
        config.sin_amplitude.astype(dtype),
        config.sin_period.astype(dtype),
        config.sin_phase.astype(dtype),
    ) + random_walk(k_drift, n, config.drift_std.astype(dtype))
    dist = dist.astype(dtype)
    var_v = jnp.var(v_unit)
    nsr = config.nsr.astype(dtype)
    nsr_safe = jnp.where(nsr > 0, nsr, 1.0)
    inf = jnp.asarray(jnp.inf, dtype)

    # Search for alpha with var(alpha v)/var(pv_clean(alpha)) = nsr. Fixed-point steps
    # alpha <- sqrt(nsr var(pv_clean(alpha)) / var(v)) (these converge in a few steps
    # for a smooth loop), switching to bisection in log(alpha) as soon as the target is
    # bracketed (stick-slip loops make var(pv_clean) jump with alpha, and the plain
    # iteration then cycles). The pass with the best alpha is returned as it is.
    def search(_, carry):
        alpha, lo, hi, best_err, best = carry
        out = _run_loop(config, r, dist, v_unit, alpha)
        var_c = jnp.var(out[2])
        ratio = alpha**2 * var_v / var_c
        err = jnp.where(alpha > 0, jnp.abs(jnp.log(ratio / nsr_safe)), inf)
        err = jnp.where(nsr > 0, err, 0.0)
        better = err < best_err
        best_err = jnp.where(better, err, best_err)
        best = jtu.tree_map(
            lambda new, old: jnp.where(better, new, old), (alpha, ratio, out), best
        )
        below = ratio < nsr
        lo, hi = jnp.where(below, alpha, lo), jnp.where(below, hi, alpha)
        proposal = jnp.sqrt(nsr * var_c / var_v)
        mid = jnp.where(lo > 0, jnp.sqrt(lo * hi), hi / 2)
        alpha = jnp.where(jnp.isfinite(hi), mid, proposal)
        return alpha, lo, hi, best_err, best

    zero = jnp.zeros((), dtype)
    empty = (zero, zero, (jnp.zeros((n,), dtype),) * 4)
    carry = (zero, zero, inf, inf, empty)
    *_, (alpha, achieved, (op, pv, pv_clean, valve)) = jax.lax.fori_loop(
        0, config.nsr_iterations, search, carry
    )
    return LoopRecord(
        op=op,
        pv=pv,
        pv_clean=pv_clean,
        sp=r,
        valve=valve,
        t=jnp.arange(n, dtype=dtype),
        noise_gain=alpha,
        nsr=achieved,
        ts=1.0,
    )
