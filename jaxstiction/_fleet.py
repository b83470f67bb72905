r"""A realistic simulated fleet, for calibrating and checking the stiction verdict.

Simulated loops are usually kind to an estimator: stationary excitation, a
self-regulating process, a fast dead time, clean samples. Plant records are not.
Each draw here is one closed loop under PI control with the nuisances of a plant
record drawn at random:

- the process: self-regulating (first or second order, time constants of 1–30
  samples) or integrating (a level: an integrator with a lag), dead times of 1–20
  samples;
- the controller: SIMC-tuned PI, detuned, on three loops in ten with little integral
  action (an integral time 3–20 times SIMC's, as many plant loops run), its gain
  lowered only where the loop would be unstable; or, for the `tight` confounder,
  tuned until the loop is lightly damped (an oscillatory pole, a complex pair or a
  negative real pole, of modulus 0.93–0.985);
- the setpoint: constant, a few steps, a ramp, or a binary noise;
- disturbances: coloured measurement noise, a slowly wandering load at the process
  input and load steps, a slow drift at the output;
- the historian: PV quantisation, deadband compression (the last stored value held
  until the signal moves away from it), OP quantisation;
- the record: 500–3000 samples, taken after 1000 samples of run-in, so that a limit
  cycle is under way when the record starts.

The valve is one of five kinds: `stiction` (Kano, S 1–10 % of span, J/S 0.1–1), and
four confounders that are *not* sticky valves: `deadband` (Kano with J = 0), `linear`
(a healthy valve, noise and loads only), `tight` (a healthy valve in a lightly damped
loop) and `external` (a healthy valve with a sinusoidal or square disturbance of
period 10–200 samples at the output, its phase wandering and its amplitude
breathing a little).

Everything is drawn from a NumPy generator seeded by the draw's seed, so a seed
names one loop; the loops themselves run in one jitted, vmapped `lax.scan`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._blocks import Kano


KINDS = ("stiction", "deadband", "linear", "tight", "external")
SHARES = (0.4, 0.1, 0.25, 0.125, 0.125)  # of each kind in a default draw
RUN_IN = 1000  # samples simulated before the record starts
LONGEST = 3000  # samples of the longest record
MAX_DELAY = 40


@dataclasses.dataclass(frozen=True)
class FleetLoop:
    """One drawn loop: the recorded `op`, `pv`, `sp` (NumPy arrays, after the
    historian), the true valve position `valve`, and its truth: `kind` (one of
    `KINDS`), `sticky` (`kind == "stiction"`), `integrating`, the process gain `gain`
    (PV units per % of OP; per sample for an integrating process), `delay`, `S`, `J`,
    the setpoint's `setpoint` profile, what the `historian` did, and `seed`."""

    op: np.ndarray
    pv: np.ndarray
    sp: np.ndarray
    valve: np.ndarray
    kind: str
    sticky: bool
    integrating: bool
    gain: float
    delay: int
    S: float
    J: float
    setpoint: str
    historian: tuple
    seed: int


def _loop(p, r, load, out):
    """One closed loop: PI (velocity form, OP clipped to [0, 100]) → Kano valve →
    process B/A with delay → + output disturbance → PV."""
    b, a, d, kp, ki, op0 = p["b"], p["a"], p["delay"], p["kp"], p["ki"], p["op0"]
    valve = Kano(p["S"], p["J"])

    def body(carry, inputs):
        u1, e1, vs, xs, ys = carry
        rt, lt, ot = inputs
        y = -jnp.dot(a[1:], ys) + jnp.dot(b, jnp.take(xs, d + jnp.arange(3)))
        pv = y + ot
        e = rt - pv
        u = jnp.clip(u1 + kp * (e - e1) + ki * e, 0.0, 100.0)
        vs, v = valve.step(vs, u)
        xs = jnp.concatenate([(v - op0 + lt)[None], xs[:-1]])
        ys = jnp.concatenate([y[None], ys[:-1]])
        return (u, e, vs, xs, ys), (u, pv, v)

    zero = jnp.zeros((), r.dtype)
    carry = (op0, zero, valve.init(op0), jnp.zeros((MAX_DELAY + 3,), r.dtype), jnp.zeros((3,), r.dtype))
    _, (u, pv, v) = jax.lax.scan(body, carry, (r, load, out))
    return u, pv, v


_run = jax.jit(jax.vmap(_loop))


def _ar1(rng, n, pole):
    """Unit-variance AR(1) noise of `pole`."""
    e = rng.standard_normal(n) * np.sqrt(1 - pole**2)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - pole**2)
    for t in range(1, n):
        x[t] = pole * x[t - 1] + e[t]
    return x


def _poles(a, b, d, kp, ki):
    """(largest pole modulus, largest modulus of an oscillatory pole: a complex
    pair with a period under 200 samples, or a negative real pole) of the closed
    loop."""
    den = np.convolve(a, [1.0, -1.0])
    num = np.concatenate([np.zeros(d + 1), np.convolve(b, [kp + ki, -kp])])
    c = np.zeros(max(len(den), len(num)))
    c[: len(den)] += den
    c[: len(num)] += num
    z = np.roots(np.trim_zeros(c, "b"))
    osc = z[np.abs(np.angle(z)) > 2 * np.pi / 200]
    return float(np.max(np.abs(z))), float(np.max(np.abs(osc))) if osc.size else 0.0


def _tune(a, b, d, kp, ratio, tight):
    """The PI's gain, from `kp` (integral gain `kp * ratio`): lowered until the
    closed loop is stable or, for a `tight` loop, searched (bisection on its
    logarithm) until the loop is lightly damped, its largest oscillatory pole of
    modulus 0.93–0.985.

    Only instability lowers the gain: a slow pole near 1 (a slow integral action
    on a slow or integrating process) is a controlled loop, and a smaller gain
    would only slow it further."""

    def state(k):
        rho, osc = _poles(a, b, d, k, k * ratio)
        if rho >= 1.0:
            return 1
        if not tight:
            return 0
        return -1 if osc < 0.93 else (1 if osc > 0.985 else 0)

    s = state(kp)
    if s == 0:
        return kp
    lo, hi = (kp, None) if s < 0 else (None, kp)
    for _ in range(200):  # bracket: lo below the target, hi above it
        if hi is None:
            kp = lo * 1.5
        elif lo is None:
            kp = hi / 1.5
        else:
            kp = float(np.sqrt(lo * hi))
        s = state(kp)
        if s == 0:
            return kp
        lo, hi = (kp, hi) if s < 0 else (lo, kp)
        if lo is not None and hi is not None and hi / lo < 1.0 + 1e-9:
            break
    return lo if lo is not None else kp


def _draw(seed: int, kind: str | None):
    """The parameters and input signals of draw `seed` (see the module notes): the
    setpoint, load and output disturbance, run-in first, each held at its last value
    up to `RUN_IN + LONGEST` samples; the `n` after the run-in are the record."""
    rng = np.random.default_rng(seed)
    kind = kind if kind is not None else str(rng.choice(KINDS, p=SHARES))
    n = int(rng.integers(500, LONGEST + 1))
    nn = n + RUN_IN
    integrating = bool(rng.random() < 0.35)
    gain = float(np.exp(rng.uniform(np.log(0.2), np.log(5.0))))
    delay = int(np.round(np.exp(rng.uniform(0.0, np.log(20.0))))) - 1  # 0-19 extra samples
    if integrating:
        lag = rng.uniform(0.0, 0.8)
        k = gain * rng.uniform(0.005, 0.05)  # PV units per % per sample
        a = np.array([1.0, -(1.0 + lag), lag, 0.0])
        b = np.array([k * (1.0 - lag), 0.0, 0.0])
        theta = delay + 1 + (-1.0 / np.log(lag) if lag > 0.01 else 0.0)
        lam = theta * rng.uniform(1.0, 3.0)
        kc, ti = 1.0 / (k * (lam + theta)), 4.0 * (lam + theta)
        gain = k
    else:
        tau = float(np.exp(rng.uniform(0.0, np.log(30.0))))
        p1 = np.exp(-1.0 / tau)
        tau2 = tau * rng.uniform(0.1, 0.5) if rng.random() < 0.5 else 0.0
        p2 = np.exp(-1.0 / tau2) if tau2 > 0 else 0.0
        a = np.array([1.0, -(p1 + p2), p1 * p2, 0.0])
        b = np.array([gain * (1.0 - p1) * (1.0 - p2), 0.0, 0.0])
        theta = delay + 1 + tau2
        lam = theta * rng.uniform(0.8, 3.0)
        kc, ti = tau / (gain * (lam + theta)), min(tau, 4.0 * (lam + theta))
    if rng.random() < 0.3:  # a proportional-heavy PI, as many plant loops run: little integral action
        ti *= rng.uniform(3.0, 20.0)
    kp, ratio = kc, 1.0 / max(ti, 1.0)
    kp = _tune(a, b, delay, kp, ratio, kind == "tight")
    S = J = 0.0
    if kind in ("stiction", "deadband"):
        S = float(np.exp(rng.uniform(0.0, np.log(10.0))))
        J = S * rng.uniform(0.1, 1.0) if kind == "stiction" else 0.0
    op0 = rng.uniform(15.0, 85.0)
    sigma = float(np.exp(rng.uniform(np.log(0.03), np.log(0.3)))) * (gain if not integrating else gain * 10)
    out = sigma * (0.7 * rng.standard_normal(nn) + 0.7 * _ar1(rng, nn, rng.uniform(0.0, 0.9)))
    setpoint = str(rng.choice(["constant", "steps", "ramp", "binary"], p=[0.6, 0.2, 0.1, 0.1]))
    scale = gain if not integrating else gain * 10
    r = np.zeros(n)
    if setpoint == "steps":
        for t0 in np.sort(rng.integers(50, n, rng.integers(1, 5))):
            r[t0:] += scale * rng.uniform(-8.0, 8.0)
    elif setpoint == "ramp":
        t0, t1 = np.sort(rng.integers(0, n, 2))
        if t1 > t0:
            r[t0:t1] = np.linspace(0.0, scale * rng.uniform(-10.0, 10.0), t1 - t0)
            r[t1:] = r[t1 - 1]
    elif setpoint == "binary":
        switch = rng.random(n) < rng.uniform(0.01, 0.05)
        r = scale * rng.uniform(1.0, 6.0) * (1 - 2 * (np.cumsum(switch) % 2))
    r = np.concatenate([np.full(RUN_IN, r[0]), r])
    load = np.zeros(nn)
    if rng.random() < 0.6:
        load += rng.uniform(0.02, 0.2) * _ar1(rng, nn, rng.uniform(0.95, 0.995))
    if rng.random() < 0.3:
        for t0 in rng.integers(0, nn, rng.integers(1, 4)):
            load[t0:] += rng.uniform(-1.0, 1.0)
    if kind == "external":
        # a periodic disturbance from elsewhere (another loop's cycle, a batch unit):
        # its phase wanders and its amplitude breathes, as a real one's do
        amp, period = scale * rng.uniform(0.5, 6.0), rng.uniform(10.0, 200.0)
        phase = 2 * np.pi * np.arange(nn) / period + rng.uniform(0, 2 * np.pi)
        phase += np.cumsum(rng.normal(0.0, rng.uniform(0.0, 0.05), nn))
        breath = 1.0 + rng.uniform(0.0, 0.3) * _ar1(rng, nn, 0.995)
        wave = np.sin(phase)
        out += amp * breath * (wave if rng.random() < 0.7 else np.sign(wave))
    if rng.random() < 0.1:
        out += np.cumsum(rng.standard_normal(nn)) * sigma * rng.uniform(0.02, 0.2)
    historian = []
    if rng.random() < 0.15:
        historian.append(("compress", sigma * rng.uniform(1.0, 4.0)))
    if rng.random() < 0.25:
        historian.append(("quantise_pv", sigma * rng.uniform(0.5, 3.0)))
    if rng.random() < 0.1:
        historian.append(("quantise_op", float(rng.choice([0.1, 0.2, 0.5]))))
    params = dict(b=b, a=a, delay=delay, kp=kp, ki=kp * ratio, op0=op0, S=S, J=J)
    # every draw's signals at the fleet's one length (held at their last value), so
    # a simulation of any draw compiles once for the whole fleet
    r, load, out = (np.concatenate([x, np.full(RUN_IN + LONGEST - nn, x[-1])]) for x in (r, load, out))
    truth = dict(kind=kind, sticky=kind == "stiction", integrating=integrating, gain=gain, delay=delay + 1, S=S,
                 J=J, setpoint=setpoint, historian=tuple(historian), seed=int(seed))
    return params, r, load, out, n, truth


def _compress(x, deviation):
    """Deadband compression: the last stored value is held until the signal moves
    more than `deviation` away from it."""
    out = np.empty_like(x)
    kept = x[0]
    for i, v in enumerate(x):
        if abs(v - kept) > deviation:
            kept = v
        out[i] = kept
    return out


def realistic_fleet(seeds, kind: str | None = None) -> list[FleetLoop]:
    """Draw and simulate one loop per seed (see the module notes); `kind` forces
    every draw's valve kind (one of `KINDS`), else it is drawn (shares `SHARES`).
    The loops run in one jitted, vmapped call (float64 when enabled)."""
    if kind is not None and kind not in KINDS:
        raise ValueError(f"`kind` must be one of {KINDS} or None, got {kind!r}")
    draws = [_draw(int(s), kind) for s in seeds]
    if not draws:
        return []
    params = {k: jnp.asarray(np.stack([np.asarray(d[0][k], float) for d in draws])) for k in draws[0][0]}
    params["delay"] = params["delay"].astype(jnp.int32)
    signals = [jnp.asarray(np.stack([d[i] for d in draws])) for i in (1, 2, 3)]
    u, pv, v = (np.asarray(x)[:, RUN_IN:] for x in _run(params, *signals))
    out = []
    for i, (_, r, _, _, n, truth) in enumerate(draws):
        op, y, sp = u[i, :n].copy(), pv[i, :n].copy(), r[RUN_IN : RUN_IN + n] + 50.0
        for what, size in truth["historian"]:
            if what == "compress":
                y = _compress(y, size)
            elif what == "quantise_pv":
                y = size * np.round(y / size)
            else:
                op = size * np.round(op / size)
        out.append(FleetLoop(op=op, pv=y + 50.0, sp=sp, valve=v[i, :n], **truth))
    return out
