"""Random concealed-effect cases: the P-cases' recipe with every number drawn.

    python benchmarks/concealed.py --seeds 0-9          # print what ten draws hide
    python benchmarks/concealed.py --seeds 3 --json     # one draw, its parameters

A draw hides one effect of the library in a closed loop (or an input effect and an
external oscillation at once, or nothing), and gives the nominal model a user would
have: the plant without the hidden effect. Everything else is drawn too:

- the process $K (b_1 q^{-1} + b_2 q^{-2}) / (1 - 2 r \\cos\\theta\\, q^{-1} + r^2 q^{-2})$:
  pole radius $r$ 0.6-0.9, angle $\\theta$ 0-0.5 rad (0: a double real pole), zero
  ratio $b_2/b_1$ 0-0.8, static gain $K$ 2-10 (PV units per % of OP);
- the PI controller $u(t) = u(t-1) + (k_p + k_i) e(t) - k_p e(t-1)$ with loop gains
  $K k_p$ 0.15-0.6 and $K k_i$ 0.03-0.15, redrawn until the linear loop (with the
  hidden dead time, lag or the characteristic's steepest slope in it) keeps its
  poles inside radius 0.98;
- the setpoint: a GBN of $\\pm K \\cdot$ 3-8 % of OP, switching with probability
  0.02-0.05; the operating point (OP at rest, the nominal's `op_offset`) 25-75 %;
- the noise: AR(1) colouring with pole 0.5-0.95, 2-10 % of the noise-free PV's
  power; the record 1500, 2000 or 3000 samples (a small set, so compiled programs
  are reused), the last third held out by `diagnose`.

The hidden effect and its size (`SIZES` names the size each power curve is drawn
against):

- stiction: Kano S 0.5-10 %, J = S x 0.2-0.6; size S (%);
- deadband: width 0.5-10 %; size the width (%);
- dead_time: +1 to +10 samples; size the samples;
- valve_characteristic: equal-percentage R 3-50 (log-uniform), three in four
  calibrated at the operating point (unit slope there: only the curvature differs),
  the rest P3-like (the nominal's linear valve passes OP unchanged, so the
  operating point moves); size the largest error of the nominal's valve position
  over the OP range the record visits (% of OP, measured: its 1st to 99th
  percentile), which R alone does not set: a calibrated characteristic errs only by
  its curvature over the few percent of OP a loop visits;
- saturation: a travel limit above or below the operating point, 0.2-1.2 setpoint
  excursions away; size the share of samples with OP beyond the limit (%, measured);
- actuator_lag: pole a 0.5-0.95; size a;
- external_oscillation: a sinusoid of period 10-100 samples, amplitude 0.3-4 noise
  std (log-uniform); size amplitude / noise std;
- drift: a random walk, step 0.01-0.1 noise std (log-uniform); size the standard
  deviation of the drift over the record / noise std (measured: a random walk of one
  step size wanders far on one record and little on another);
- quantization: a sensor step of 0.05-2 noise std (log-uniform); size step / noise std.

Output-side sizes are relative to the noise standard deviation of the effect-free
loop drawn with the same key: the simulation sets the noise gain from the noise-free
PV's power, which an output effect raises, so the loop is simulated once with the
effect to find the noise-to-signal ratio that keeps that noise level, then again.
The size recorded (`Case.size`) is the one measured on the record.

`build(seed)` is deterministic (NumPy's generator seeded by `(seed, SALT)` for the
numbers, `PRNGKey(seed)` folded with `SALT` for the simulation); `README_SEEDS` is the fixed
list the figures of docs/method/diagnosis-power.md use. `ranges` overrides any default range.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402

from jaxstiction import (  # noqa: E402
    ActuatorLag,
    Deadband,
    DeadTime,
    Drift,
    EqualPercentage,
    Experiment,
    Kano,
    LinearProcess,
    LoopModel,
    NoiseModel,
    Quantiser,
    simulate_loop,
    Sinusoid,
    TravelLimits,
)


SALT = 46  # the issue that asked for these draws: numbers never collide with other benchmarks' seeds
README_SEEDS = tuple(range(1000, 1200))  # the 200 draws docs/method/diagnosis-power.md quotes

INPUT_EFFECTS = ("stiction", "deadband", "dead_time", "valve_characteristic", "saturation", "actuator_lag")
OUTPUT_EFFECTS = ("external_oscillation", "drift", "quantization")
EFFECTS = INPUT_EFFECTS + OUTPUT_EFFECTS
SIZES = {"stiction": "S (%)", "deadband": "width (%)", "dead_time": "extra dead time (samples)",
         "valve_characteristic": "valve position error over the OP visited (% of OP)",
         "saturation": "samples at the limit (%)",
         "actuator_lag": "lag pole a", "external_oscillation": "amplitude / noise std",
         "drift": "drift std / noise std", "quantization": "step / noise std"}

DEFAULT_RANGES = {
    # what a draw hides: probabilities of nothing, of two effects, the rest one effect
    "p_none": 0.15, "p_pair": 0.10,
    # or a fixed choice: "none", one effect, or "effect+external_oscillation"
    "only": None,
    # the plant and its operation
    "pole_radius": (0.6, 0.9), "pole_angle": (0.0, 0.5), "zero_ratio": (0.0, 0.8), "gain": (2.0, 10.0),
    "kp_loop": (0.15, 0.6), "ki_loop": (0.03, 0.15), "op_excursion": (3.0, 8.0), "switch_prob": (0.02, 0.05),
    "operating_point": (25.0, 75.0), "noise_pole": (0.5, 0.95), "nsr": (0.02, 0.10),
    "lengths": (1500, 2000, 3000),
    # the effects' sizes
    "stiction_S": (0.5, 10.0), "stiction_J_share": (0.2, 0.6), "deadband": (0.5, 10.0), "dead_time": (1, 10),
    "rangeability": (3.0, 50.0), "p_calibrated": 0.75, "limit_excursions": (0.2, 1.2), "lag": (0.5, 0.95),
    "osc_period": (10.0, 100.0), "osc_amplitude": (0.3, 4.0), "drift_step": (0.01, 0.1),
    "quant_step": (0.05, 2.0),
}
STABLE_RADIUS = 0.98


@dataclasses.dataclass(frozen=True)
class Case:
    """One draw: the plant and its nominal model (the plant without the hidden
    effect), the experiment, the record length, what is hidden (`effects`, the
    first the one whose size is `size`; `()` for nothing) and every number drawn
    (`params`). `loop` is the simulated record (a [`jaxstiction.Loop`][])."""

    seed: int
    effects: tuple
    size: float | None
    params: dict
    plant: LoopModel
    nominal: LoopModel
    experiment: Experiment
    n: int
    loop: object = None

    @property
    def effect(self) -> str:
        return self.effects[0] if self.effects else "none"

    @property
    def label(self) -> str:
        return "+".join(self.effects) or "none"


def _u(rng, lo_hi):
    return float(rng.uniform(*lo_hi))


def _log_u(rng, lo_hi):
    return float(math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1]))))


def _eq_pct(x, R):
    return 100.0 * (R ** (x / 100.0) - 1.0) / (R - 1.0)


def _eq_pct_slope(x, R):
    return math.log(R) * R ** (x / 100.0) / (R - 1.0)


def _eq_pct_inverse(v, R):
    return 100.0 * math.log(1.0 + v * (R - 1.0) / 100.0) / math.log(R)


def closed_loop_radius(b, a, k0, k1, gain=1.0, delay=0, lag=0.0) -> float:
    """Largest pole modulus of the linear loop: process `b`/`a` (in $q^{-1}$), the
    velocity PI `k0`, `k1`, a static `gain` (a valve's slope), `delay` samples of
    dead time and a first-order lag with pole `lag` before the process."""
    den = np.convolve(np.convolve(a, [1.0, -1.0]), [1.0, -lag])
    num = gain * (1.0 - lag) * np.convolve([k0, k1], np.concatenate([np.zeros(delay), b]))
    m = max(len(den), len(num))
    poly = np.pad(den, (0, m - len(den))) + np.pad(num, (0, m - len(num)))
    return float(np.max(np.abs(np.roots(np.trim_zeros(poly, "b")))))


def _model(b, a, d, op_offset, chain=(), output=()) -> LoopModel:
    return LoopModel(chain=tuple(chain), process=LinearProcess(b=tuple(b), a=tuple(a)),
                     noise=NoiseModel(c=(1.0,), d=(1.0, -d)), op_offset=op_offset, pv_offset=0.0,
                     output=tuple(output))


def _pick(rng, r):
    """What a draw hides: `()`, one effect, or an input effect and an oscillation
    (`r["only"]` fixes it)."""
    u = rng.uniform()
    if r.get("only") is not None:
        return () if r["only"] == "none" else tuple(r["only"].split("+"))
    if u < r["p_none"]:
        return ()
    if u < r["p_none"] + r["p_pair"]:
        return (str(rng.choice(INPUT_EFFECTS)), "external_oscillation")
    return (str(rng.choice(EFFECTS)),)


def draw_params(seed: int, ranges: dict | None = None) -> dict:
    """Every number of draw `seed` (no simulation): the plant, controller, setpoint,
    noise, length and the hidden effects' parameters (output sizes relative to the
    noise std)."""
    r = {**DEFAULT_RANGES, **(ranges or {})}
    rng = np.random.default_rng([seed, SALT])
    effects = _pick(rng, r)
    rad, ang = _u(rng, r["pole_radius"]), _u(rng, r["pole_angle"])
    a = [1.0, -2 * rad * math.cos(ang), rad**2]
    zr = _u(rng, r["zero_ratio"])
    K = _u(rng, r["gain"])
    b_unit = np.array([0.0, 1.0, zr])
    b = b_unit * K * sum(a) / (1.0 + zr)  # static gain K
    p = {"effects": list(effects), "a": a, "b": [float(v) for v in b], "gain": K,
         "noise_pole": _u(rng, r["noise_pole"]), "nsr": _log_u(rng, r["nsr"]),
         "op0": _u(rng, r["operating_point"]), "op_excursion": _u(rng, r["op_excursion"]),
         "switch_prob": _u(rng, r["switch_prob"]), "n": int(rng.choice(r["lengths"]))}
    for eff in effects:
        if eff == "stiction":
            S = _u(rng, r["stiction_S"])
            p["stiction"] = {"S": S, "J": S * _u(rng, r["stiction_J_share"])}
        elif eff == "deadband":
            p["deadband"] = {"width": _u(rng, r["deadband"])}
        elif eff == "dead_time":
            p["dead_time"] = {"samples": int(rng.integers(r["dead_time"][0], r["dead_time"][1] + 1))}
        elif eff == "valve_characteristic":
            R = _log_u(rng, r["rangeability"])
            cal = bool(rng.uniform() < r["p_calibrated"])
            # a P3-like valve moves the operating point to E^-1(op0): only where it
            # stays clear of 100 % with room for the setpoint's excursions
            if not cal and _eq_pct_inverse(p["op0"], R) + 2.5 * p["op_excursion"] > 95.0:
                cal = True
            p["valve_characteristic"] = {"R": R, "calibrated": cal}
        elif eff == "saturation":
            side = "hi" if rng.uniform() < 0.5 else "lo"
            dist = _u(rng, r["limit_excursions"]) * p["op_excursion"]
            p["saturation"] = {side: p["op0"] + dist if side == "hi" else p["op0"] - dist}
        elif eff == "actuator_lag":
            p["actuator_lag"] = {"a": _u(rng, r["lag"])}
        elif eff == "external_oscillation":
            p["external_oscillation"] = {"period": _u(rng, r["osc_period"]),
                                         "amplitude_rel": _log_u(rng, r["osc_amplitude"]),
                                         "phase": _u(rng, (0.0, 2 * math.pi))}
        elif eff == "drift":
            p["drift"] = {"step_rel": _log_u(rng, r["drift_step"])}
        elif eff == "quantization":
            p["quantization"] = {"step_rel": _log_u(rng, r["quant_step"])}
    # the controller: redrawn until the linear loop is stable with the hidden
    # dynamics (dead time, lag, the characteristic's steepest slope) in it
    delay = p.get("dead_time", {}).get("samples", 0)
    lag = p.get("actuator_lag", {}).get("a", 0.0)
    slope = 1.0
    if "valve_characteristic" in p:
        R, op0, ex = p["valve_characteristic"]["R"], p["op0"], p["op_excursion"]
        if p["valve_characteristic"]["calibrated"]:
            slope = _eq_pct_slope(op0 + 1.5 * ex, R) / _eq_pct_slope(op0, R)
        else:
            slope = _eq_pct_slope(_eq_pct_inverse(op0, R) + 1.5 * ex, R)
    for _ in range(200):
        kp, ki = _u(rng, r["kp_loop"]) / K, _u(rng, r["ki_loop"]) / K
        k0, k1 = kp + ki, -kp
        worst = max(closed_loop_radius(b, a, k0, k1, g, delay, lag) for g in (1.0, slope))
        if worst < STABLE_RADIUS:
            break
        r = {**r, "kp_loop": (r["kp_loop"][0] * 0.8, r["kp_loop"][1] * 0.8),
             "ki_loop": (r["ki_loop"][0] * 0.8, r["ki_loop"][1] * 0.8)}  # detune until stable
    p.update(kc=[k0, k1], closed_loop_radius=worst)
    return p


def build(seed: int, ranges: dict | None = None) -> Case:
    """Draw `seed`: its numbers (`draw_params`), the plant, the nominal and the
    simulated record. Output-side effects are sized against the effect-free loop's
    noise (see the module notes)."""
    p = draw_params(seed, ranges)
    effects = tuple(p["effects"])
    a, b, d, op0 = p["a"], np.asarray(p["b"]), p["noise_pole"], p["op0"]
    nominal = _model(b, a, d, op0)
    key = jr.fold_in(jr.PRNGKey(seed), SALT)
    exp = Experiment(kc=(p["kc"][0], p["kc"][1], 0.0), sp_amplitude=p["gain"] * p["op_excursion"],
                     sp_switch_prob=p["switch_prob"], nsr=p["nsr"])
    n = p["n"]
    chain, output = [], []
    plant_b, plant_off = b, op0
    if "actuator_lag" in p:
        chain.append(ActuatorLag(p["actuator_lag"]["a"]))
    if "stiction" in p:
        chain.append(Kano(p["stiction"]["S"], p["stiction"]["J"]))
    if "deadband" in p:
        chain.append(Deadband(p["deadband"]["width"]))
    if "saturation" in p:
        chain.append(TravelLimits(**p["saturation"]))
    if "valve_characteristic" in p:
        R = p["valve_characteristic"]["R"]
        chain.append(EqualPercentage(R))
        if p["valve_characteristic"]["calibrated"]:  # unit slope at the operating point
            plant_b, plant_off = b / _eq_pct_slope(op0, R), _eq_pct(op0, R)
    if "dead_time" in p:
        chain.append(DeadTime(p["dead_time"]["samples"]))
    sigma = None
    if any(e in OUTPUT_EFFECTS for e in effects):
        sigma = _noise_std(simulate_loop(nominal, exp, key, n), d)
        if "external_oscillation" in p:
            o = p["external_oscillation"]
            o["amplitude"] = o["amplitude_rel"] * sigma
            output.append(Sinusoid(o["amplitude"], o["period"], o["phase"]))
        if "drift" in p:
            p["drift"]["step"] = p["drift"]["step_rel"] * sigma
            output.append(Drift(p["drift"]["step"], jr.key_data(jr.fold_in(key, 7))))
        if "quantization" in p:
            p["quantization"]["step"] = p["quantization"]["step_rel"] * sigma
            output.append(Quantiser(p["quantization"]["step"]))
    plant = _model(plant_b, a, d, plant_off, chain, output)
    rec = simulate_loop(plant, exp, key, n)
    if sigma is not None and any(isinstance(o, (Sinusoid, Drift)) for o in output):
        # keep the effect-free loop's noise level: the simulation sized the noise
        # from a noise-free PV that now holds the oscillation or the drift
        base = simulate_loop(_model(plant_b, a, d, plant_off, chain), exp, key, n)
        exp = dataclasses.replace(exp, nsr=jnp.asarray(p["nsr"] * float(jnp.var(base.pv_clean))
                                                       / float(jnp.var(rec.pv_clean))))
        rec = simulate_loop(plant, exp, key, n)
    size = measured_size(effects[0], p, rec, d, plant) if effects else None
    p["noise_std"] = _noise_std(rec, d)
    return Case(seed=seed, effects=effects, size=size, params=p, plant=plant, nominal=nominal, experiment=exp, n=n,
                loop=rec.loop)


def _noise_std(rec, pole) -> float:
    """The standard deviation of the record's AR(1) noise (its gain over the unit
    innovations' stationary spread)."""
    return float(rec.noise_gain) / math.sqrt(1.0 - pole**2)


def measured_size(effect: str, p: dict, rec, pole: float, plant: LoopModel) -> float:
    """The size a power curve puts `effect` at (`SIZES`), measured on the record
    where it depends on the loop."""
    if effect == "stiction":
        return p["stiction"]["S"]
    if effect == "deadband":
        return p["deadband"]["width"]
    if effect == "dead_time":
        return float(p["dead_time"]["samples"])
    if effect == "valve_characteristic":
        return characteristic_error(p, np.asarray(rec.op))
    if effect == "saturation":
        lim = next(iter(p["saturation"].values()))
        op = np.asarray(rec.op)
        held = op > lim if "hi" in p["saturation"] else op < lim
        return 100.0 * float(np.mean(held))
    if effect == "actuator_lag":
        return p["actuator_lag"]["a"]
    sigma = _noise_std(rec, pole)
    if effect == "external_oscillation":
        return p["external_oscillation"]["amplitude"] / sigma
    if effect == "drift":
        drift = next(o for o in plant.output if isinstance(o, Drift))  # its random walk alone
        return float(np.std(np.asarray(drift(jnp.zeros(rec.op.shape[0]))))) / sigma
    return p[effect]["step"] / sigma


def characteristic_error(p: dict, op) -> float:
    """The largest error (% of OP) of the nominal's valve position against the
    plant's equal-percentage valve over the OP range `op` visits (1st to 99th
    percentile), both through the plant's process gain: calibrated, the plant's valve
    is scaled to unit slope at the operating point; otherwise the nominal's linear
    valve passes OP unchanged."""
    R, op0 = p["valve_characteristic"]["R"], p["op0"]
    lo, hi = np.percentile(op, [1, 99])
    u = np.linspace(lo, hi, 201)
    if p["valve_characteristic"]["calibrated"]:
        v = (_eq_pct(u, R) - _eq_pct(op0, R)) / _eq_pct_slope(op0, R) + op0
    else:
        v = _eq_pct(u, R)
    return float(np.max(np.abs(v - u)))


def right(case: Case, d) -> bool:
    """Does diagnosis `d` name what `case` hides? One effect: the verdict is it (an
    oscillation or a quantiser with no stiction accepted besides, as P5 and P7
    require); two: the verdict is the input effect and the oscillation is accepted
    on top of it; nothing: the verdict is `none`."""
    acc = {f.effect for f in d.findings if f.accepted}
    if not case.effects:
        return d.verdict == "none"
    if d.verdict != case.effects[0]:
        return False
    if len(case.effects) == 2:
        return case.effects[1] in acc
    if case.effect in ("external_oscillation", "quantization", "drift"):
        return "stiction" not in acc
    return True


def main():
    from _args import seeds_arg  # benchmarks/ is on sys.path when run as a script

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(10)), help="e.g. 0-9 or 3,5,7")
    p.add_argument("--json", action="store_true", help="one JSON object per draw (its numbers), nothing simulated")
    args = p.parse_args()
    for seed in args.seeds:
        prm = draw_params(seed)
        if args.json:
            print(json.dumps({"seed": seed, **prm}))
            continue
        what = ", ".join(f"{e} {prm[e]}" for e in prm["effects"]) or "nothing"
        print(f"draw {seed}: n {prm['n']}, OP {prm['op0']:.1f} %, K {prm['gain']:.2f}, nsr {prm['nsr']:.3f}, "
              f"PI {prm['kc'][0]:.4f}/{prm['kc'][1]:.4f} (radius {prm['closed_loop_radius']:.3f}); hides {what}")


if __name__ == "__main__":
    main()
