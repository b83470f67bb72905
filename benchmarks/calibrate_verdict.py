"""Calibration of the stiction verdict on simulated loops with and without stiction.

    python benchmarks/calibrate_verdict.py                # 6 loops per kind, seeds 0-5
    python benchmarks/calibrate_verdict.py --seeds 6-11   # other loops
    python benchmarks/calibrate_verdict.py --json
    python benchmarks/calibrate_verdict.py --plants diverse --seeds 0-23   # other processes
    python benchmarks/calibrate_verdict.py --seeds 0-5 --oversample 3      # faster sampling
    python benchmarks/calibrate_verdict.py --plants diverse --seeds 0-47 --processes integrating --full-search

Kinds (1500 samples each, the paper's process and noise colouring, 5 % noise power;
half of the loops follow a GBN setpoint (±20, switching with probability 0.05), half
a setpoint that rarely moves (±5, probability 0.004), as most plant loops do):

- `stiction`: Kano S in [2, 20] % and J in [0.25 S, S] (both drawn per loop), PI;
- `small_slip`: Kano S in [2, 20] % and a small slip, J in [0.02 S, 0.25 S];
- `none`: a linear valve, PI (noise alone);
- `tight`: a linear valve under an aggressive PI (an underdamped, oscillating loop);
- `external`: a linear valve plus a sinusoidal output disturbance (period 15-80
  samples, amplitude drawn per loop);
- `deadband`: a deadband (backlash) of 1-6 %: a valve band without slip, which the
  Kano fit cannot tell from a stickband, so it counts as a valve band to detect.

With `--plants diverse` every loop gets its own process instead of the paper's (a
fast flow loop, a slow loop with dead time, a second-order loop or an integrating
level loop), its own SIMC-tuned PI, noise colour and level, operating point, PV
units, length, and on a third of the loops a slow drift (see `make_diverse`). The
verdict's thresholds were never set on these loops: they measure how far its
calibration carries to other processes.

Each loop goes through `jaxstiction.screen_loops` (the batched estimate and the
verdict, exactly as `jaxstiction screen`). Prints one row per loop (held-out gain of
the Kano valve over the linear valve in simulation, the same on the estimation data,
both again in short-horizon prediction, the gains over a deadband, S, J, the
residual line's share and period, the verdict and cause), then the confusion of
"stiction detected" against the truth (a valve band: `stiction`, `small_slip`,
`deadband`), the balanced accuracy, and how often the slip was identified.
"""

import argparse
import json
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
from _args import seeds_arg  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

from jaxstiction import (  # noqa: E402
    Deadband,
    Drift,
    Experiment,
    Kano,
    LinearProcess,
    LoopModel,
    make_loop,
    NoiseModel,
    screen_loops,  # noqa: E402
    simulate_loop,
    Sinusoid,
)
from jaxstiction.internal import (
    nominal_model,  # noqa: E402
    screen_settings,  # noqa: E402
)


KINDS = ("stiction", "none", "tight", "external", "deadband", "small_slip")
BAND = ("stiction", "small_slip", "deadband")
N = 1500


def make(kind, seed):
    rng = np.random.default_rng(1000 * KINDS.index(kind) + seed)
    sp, switch = (20.0, 0.05) if seed % 2 == 0 else (5.0, 0.004)
    kc = (0.31, -0.3, 0.0)
    chain, output, truth = (), (), {}
    if kind in ("stiction", "small_slip"):
        S = float(rng.uniform(2.0, 20.0))
        J = float(S * (rng.uniform(0.25, 1.0) if kind == "stiction" else rng.uniform(0.02, 0.25)))
        chain, truth = (Kano(S, J),), {"S": round(S, 2), "J": round(J, 2)}
    elif kind == "tight":
        kc = (0.9, -0.75, 0.0)
    elif kind == "external":
        amp, period = float(rng.uniform(3.0, 10.0)), float(rng.uniform(15.0, 80.0))
        output, truth = (Sinusoid(amp, period),), {"amplitude": round(amp, 2), "period": round(period, 1)}
    elif kind == "deadband":
        d = float(rng.uniform(1.0, 6.0))
        chain, truth = (Deadband(d),), {"width": round(d, 2)}
    plant = nominal_model(chain=chain, output=output)
    exp = Experiment(kc=kc, sp_amplitude=sp, sp_switch_prob=switch, nsr=0.05)
    rec = simulate_loop(plant, exp, jr.PRNGKey(seed), N)
    return make_loop(np.asarray(rec.op), np.asarray(rec.pv)), truth, "GBN" if sp > 10 else "rare"


PLANT_TYPES = ("flow", "fopdt", "second_order", "integrating")


def _closed_loop_radius(b, a, k0, k1):
    """Largest closed-loop pole radius of B/A under the velocity PI k0, k1 (linear valve)."""
    n = max(len(a) + 1, len(b) + 1)
    den = np.zeros(n)
    den[: len(a)] += a
    den[1: len(a) + 1] -= a
    den[: len(b)] += k0 * np.asarray(b)
    den[1: len(b) + 1] += k1 * np.asarray(b)
    return float(np.max(np.abs(np.roots(np.trim_zeros(den, "b")))))


def make_diverse(kind, seed):
    """A loop of `kind` on a process drawn per loop (not the paper's one):

    - process: a fast first-order flow loop (pole 0.3-0.8, delay 1-2), a slow first-order
      loop with dead time (pole 0.9-0.98, delay 2-8), a second-order loop (two real
      poles 0.5-0.9, delay 1-3) or an integrating level loop (pole 1, delay 1-4);
    - PI tuned by SIMC (Skogestad 2003) with a closed-loop time constant lambda of
      0.5-3 times the delay (`tight`: 0.05-0.3 times, underdamped but stable);
    - noise: AR(1) with pole 0-0.95, 1-20 % of the noise-free PV's power, a slow
      random-walk drift on a third of the loops of every kind;
    - OP around 25-75 %, PV around 0-200 in its own units, setpoint steps moving OP
      by 2-15 % (GBN on even seeds, a rarely moving setpoint on odd ones);
    - 1000, 1500 or 2000 samples.
    """
    rng = np.random.default_rng(50_000 + 1000 * KINDS.index(kind) + seed)
    ptype = PLANT_TYPES[rng.integers(len(PLANT_TYPES))]
    d_op = float(rng.uniform(2.0, 15.0))
    sp_amp = float(rng.uniform(2.0, 50.0))
    if ptype == "integrating":
        delay = int(rng.integers(1, 5))
        kp_proc = sp_amp / d_op / float(rng.uniform(10.0, 60.0))  # PV units per sample per % OP
        b, a = (kp_proc,), (1.0, -1.0)
        theta, tau = delay + 0.5, None
    else:
        gain = sp_amp / d_op
        if ptype == "flow":
            poles, delay = (float(rng.uniform(0.3, 0.8)),), int(rng.integers(1, 3))
        elif ptype == "fopdt":
            poles, delay = (float(rng.uniform(0.9, 0.98)),), int(rng.integers(2, 9))
        else:
            poles, delay = tuple(sorted(rng.uniform(0.5, 0.9, 2), reverse=True)), int(rng.integers(1, 4))
        a = np.poly(poles)
        b = (gain * float(np.sum(a)),)
        a = tuple(float(x) for x in a)
        # First-order-plus-delay approximation (Skogestad's half rule) for the tuning.
        taus = [-1.0 / np.log(p) for p in poles]
        tau = taus[0] + (taus[1] / 2 if len(taus) > 1 else 0.0)
        theta = delay + 0.5 + (taus[1] / 2 if len(taus) > 1 else 0.0)
    lam_lo, lam_hi = (0.05, 0.3) if kind == "tight" else (0.5, 3.0)
    for _ in range(200):
        lam = float(rng.uniform(lam_lo, lam_hi)) * theta
        if tau is None:
            kc, ti = 1.0 / (b[0] * (lam + theta)), 4.0 * (lam + theta)
        else:
            kc, ti = tau / (gain * (lam + theta)), min(tau, 4.0 * (lam + theta))
        k0, k1 = kc * (1.0 + 1.0 / ti), -kc
        bd = (0.0,) * delay + tuple(b)
        radius = _closed_loop_radius(bd, a, k0, k1)
        if radius < 0.995:
            break
        lam_lo, lam_hi = lam_lo * 1.2, lam_hi * 1.2
    op0, pv0 = float(rng.uniform(25.0, 75.0)), float(rng.uniform(0.0, 200.0))
    rare = seed % 2 == 1
    sp, switch = (sp_amp, 0.05) if not rare else (sp_amp / 4, 0.004)
    nsr, noise_pole = float(np.exp(rng.uniform(np.log(0.01), np.log(0.2)))), float(rng.uniform(0.0, 0.95))
    chain, output = [], []
    truth = {"plant": ptype, "delay": delay, "lambda/theta": round(float(lam / theta), 2), "nsr": round(nsr, 3),
             "noise_pole": round(noise_pole, 2)}
    if kind in ("stiction", "small_slip"):
        S = float(rng.uniform(2.0, 20.0))
        J = float(S * (rng.uniform(0.25, 1.0) if kind == "stiction" else rng.uniform(0.02, 0.25)))
        chain.append(Kano(S, J))
        truth.update(S=round(S, 2), J=round(J, 2))
    elif kind == "external":
        amp, period = float(rng.uniform(0.1, 0.5)) * sp_amp, float(rng.uniform(10.0, 100.0))
        output.append(Sinusoid(amp, period))
        truth.update(amplitude=round(amp, 2), period=round(period, 1))
    elif kind == "deadband":
        d = float(rng.uniform(1.0, 6.0))
        chain.append(Deadband(d))
        truth.update(width=round(d, 2))
    if rng.uniform() < 1 / 3:
        step = float(rng.uniform(0.002, 0.02)) * sp_amp
        output.append(Drift(step, jr.key_data(jr.PRNGKey(10_000 + seed))))
        truth.update(drift=round(step, 3))
    n = int(rng.choice([1000, 1500, 2000]))
    plant = LoopModel(chain=tuple(chain), process=LinearProcess(b=(0.0,) * delay + tuple(b), a=a),
                      noise=NoiseModel(c=(1.0,), d=(1.0, -noise_pole)), op_offset=op0, pv_offset=pv0,
                      output=tuple(output))
    exp = Experiment(kc=(k0, k1, 0.0), sp_amplitude=sp, sp_switch_prob=switch, nsr=nsr)
    rec = simulate_loop(plant, exp, jr.PRNGKey(seed), n)
    return make_loop(np.asarray(rec.op), np.asarray(rec.pv)), truth, "rare" if rare else "GBN"


def oversampled(loop, r: int):
    """The record interpolated linearly onto `r` times as many samples."""
    op, pv = np.asarray(loop.op), np.asarray(loop.pv)
    t, fine = np.arange(op.shape[0]), np.arange((op.shape[0] - 1) * r + 1) / r
    return make_loop(np.interp(fine, t, op), np.interp(fine, t, pv))


def confusion(rows):
    """`(valve bands detected, valve bands, false alarms, loops without a band)`."""
    band = [r["kind"] in BAND for r in rows]
    hit = [bool(r["stiction_detected"]) for r in rows]
    return (sum(b and h for b, h in zip(band, hit)), sum(band),
            sum(h and not b for b, h in zip(band, hit)), len(rows) - sum(band))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(6)))
    p.add_argument("--kinds", default=",".join(KINDS))
    p.add_argument("--json", action="store_true")
    p.add_argument("--plants", choices=("paper", "diverse"), default="paper",
                   help="the paper's process for every loop, or a process drawn per loop (see make_diverse)")
    p.add_argument("--full-search", action="store_true",
                   help="the estimator's full Kano search (PhysicalSettings()) instead of the screen's lighter one")
    p.add_argument("--oversample", type=int, default=1, metavar="R",
                   help="interpolate every record linearly onto R times as many samples (a crude stand-in "
                        "for a loop sampled R times faster)")
    p.add_argument("--processes", default=",".join(PLANT_TYPES), metavar="LIST",
                   help="with --plants diverse: only the loops whose drawn process is one of these "
                        f"({', '.join(PLANT_TYPES)})")
    p.add_argument("--max-delay", type=int, default=None, metavar="N",
                   help="try process dead times of 1..N samples (Settings.with_max_delay; default 3)")
    p.add_argument("--threads", type=int, default=0, metavar="N",
                   help="batched calls run at once (as `jaxstiction screen --threads`; 0: one per core)")
    args = p.parse_args()
    settings = screen_settings(args)  # as `jaxstiction screen [--full-search] [--max-delay N]`
    processes = args.processes.split(",")
    if unknown := set(processes) - set(PLANT_TYPES):
        p.error(f"unknown process(es) {', '.join(sorted(unknown))}; choose from {', '.join(PLANT_TYPES)}")
    kinds = args.kinds.split(",")
    loops, meta = {}, {}
    for kind in kinds:
        for s in args.seeds:
            loop, truth, setpoint = (make if args.plants == "paper" else make_diverse)(kind, s)
            if args.plants == "diverse" and truth["plant"] not in processes:
                continue
            if args.oversample > 1:
                loop = oversampled(loop, args.oversample)
            name = f"{kind}-{s}"
            loops[name] = loop
            meta[name] = dict(kind=kind, seed=s, setpoint=setpoint, truth=truth)
    t0 = time.time()
    results = screen_loops(loops, settings)
    dt = time.time() - t0
    rows = []
    for r in results:
        m = meta[r["name"]]
        rows.append({**m, **{k: r.get(k) for k in ("status", "stiction_detected", "cause", "evidence",
                                                   "evidence_estimation", "evidence_prediction",
                                                   "evidence_prediction_estimation", "slip_evidence", "slip_identified",
                                                   "slip_evidence_estimation", "band_fraction", "S", "J",
                                                   "oscillation", "oscillation_kano", "period_samples", "fitness",
                                                   "fitness_kano", "fitness_linear", "fitness_deadband", "delay")}})
    rows.sort(key=lambda r: (kinds.index(r["kind"]), r["seed"]))
    tp, pos, fa, neg = confusion(rows)
    tn = neg - fa
    bacc = 0.5 * (tp / max(pos, 1) + tn / max(neg, 1))
    detected = {k: sum(r["kind"] == k and r["stiction_detected"] for r in rows) for k in kinds}
    slips = {k: sum(r["kind"] == k and bool(r["slip_identified"]) for r in rows) for k in kinds}
    total = {k: sum(r["kind"] == k for r in rows) for k in kinds}
    if args.json:
        print(json.dumps({"rows": rows, "balanced_accuracy": bacc, "detected": detected, "slip_identified": slips,
                          "seconds": dt}))
        return
    print(f"{'loop':<14} {'setpoint':<8} {'gain':>7} {'gain_est':>8} {'pred':>6} {'pred_est':>8} {'slip':>6} "
          f"{'slip_est':>8} {'S/rng':>6} "
          f"{'S':>6} {'J':>6} {'line':>5} {'period':>6} {'verdict':<8} cause")
    for r in rows:
        f = lambda v, d=2: "nan" if v is None else f"{v:.{d}f}"  # noqa: E731
        print(f"{r['kind'] + '-' + str(r['seed']):<14} {r['setpoint']:<8} {f(r['evidence']):>7} "
              f"{f(r['evidence_estimation']):>8} {f(r['evidence_prediction']):>6} "
              f"{f(r['evidence_prediction_estimation']):>8} {f(r['slip_evidence']):>6} "
              f"{f(r['slip_evidence_estimation']):>8} "
              f"{f(r['band_fraction']):>6} {f(r['S']):>6} {f(r['J']):>6} {f(r['oscillation']):>5} "
              f"{f(r['period_samples'], 1):>6} {'STICKY' if r['stiction_detected'] else '-':<8} {r['cause']}"
              + (" (slip identified)" if r["slip_identified"] else "")
              + ("" if r["status"] == "ok" else f"  [{r['status']}]")
              + (f"  {r['truth']}" if args.plants == "diverse" else ""))
    print(f"\nstiction detected on {tp}/{pos} loops with a valve band, not detected on {tn}/{neg} others: "
          f"balanced accuracy {bacc:.2f}; {len(rows)} loops in {dt:.0f} s")
    print("per kind, detected / slip identified / loops: "
          + ", ".join(f"{k} {detected[k]}/{slips[k]}/{total[k]}" for k in kinds))
    if args.plants == "diverse":
        parts = []
        for pt in PLANT_TYPES:
            rows_pt = [r for r in rows if r["truth"]["plant"] == pt]
            if not rows_pt:
                continue
            hit, pos_pt, fa_pt, neg_pt = confusion(rows_pt)
            parts.append(f"{pt} {hit}/{pos_pt} found, {fa_pt}/{neg_pt} false alarms")
        print("per process: " + "; ".join(parts))


if __name__ == "__main__":
    main()
