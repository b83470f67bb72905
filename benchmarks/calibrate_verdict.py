"""Calibration of the stiction verdict on simulated loops with and without stiction.

    python benchmarks/calibrate_verdict.py                # 6 loops per kind, seeds 0-5
    python benchmarks/calibrate_verdict.py --seeds 6-11   # other loops
    python benchmarks/calibrate_verdict.py --json

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

from jaxstiction import Deadband, Experiment, Kano, make_loop, simulate_loop, Sinusoid  # noqa: E402
from jaxstiction._scenarios import nominal_model  # noqa: E402
from jaxstiction._screen import screen_loops, ScreenSettings, Settings  # noqa: E402


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
    return make_loop(np.asarray(rec.op), np.asarray(rec.pv)), truth, sp


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(6)))
    p.add_argument("--kinds", default=",".join(KINDS))
    p.add_argument("--json", action="store_true")
    p.add_argument("--full-search", action="store_true",
                   help="the estimator's full Kano search (PhysicalSettings()) instead of the screen's lighter one")
    args = p.parse_args()
    settings = ScreenSettings()
    if args.full_search:
        settings = ScreenSettings(estimate=Settings(use_spline=False))
    kinds = args.kinds.split(",")
    loops, meta = {}, {}
    for kind in kinds:
        for s in args.seeds:
            loop, truth, sp = make(kind, s)
            name = f"{kind}-{s}"
            loops[name] = loop
            meta[name] = dict(kind=kind, seed=s, setpoint="GBN" if sp > 10 else "rare", truth=truth)
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
                                                   "oscillation", "period_samples", "fitness")}})
    rows.sort(key=lambda r: (kinds.index(r["kind"]), r["seed"]))
    tp = sum(r["kind"] in BAND and r["stiction_detected"] for r in rows)
    pos = sum(r["kind"] in BAND for r in rows)
    tn = sum(r["kind"] not in BAND and not r["stiction_detected"] for r in rows)
    neg = len(rows) - pos
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
              + ("" if r["status"] == "ok" else f"  [{r['status']}]"))
    print(f"\nstiction detected on {tp}/{pos} loops with a valve band, not detected on {tn}/{neg} others: "
          f"balanced accuracy {bacc:.2f}; {len(rows)} loops in {dt:.0f} s")
    print("per kind, detected / slip identified / loops: "
          + ", ".join(f"{k} {detected[k]}/{slips[k]}/{total[k]}" for k in kinds))


if __name__ == "__main__":
    main()
