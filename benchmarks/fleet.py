"""Marginal cost of the full screen (batched estimate + verdict) per loop.

    python benchmarks/fleet.py                     # fleets of 8 and 24 loops
    python benchmarks/fleet.py --small 8 --large 1024
    python benchmarks/fleet.py --json
    python benchmarks/fleet.py --threads 1         # one batched call at a time
    python benchmarks/fleet.py --small 64 --large 1024 --chunk 256   # on a GPU
    python benchmarks/fleet.py --small 8 --large 128 --whatif   # what `screen --whatif` adds

Simulated 1500-sample loops (the paper's process; half with Kano stiction, half
with a linear valve; half following a GBN setpoint, half a setpoint that rarely moves), screened
exactly as `jaxstiction screen` does (`jaxstiction.screen_loops`: one length bucket,
chunks of loops per compiled call sized to the machine, or `--chunk`). A warm-up fleet of one
chunk is screened first (it pays the compilation), then the small and the large
fleet, both timed; the marginal seconds per loop are
(t_large - t_small) / (large - small), so any fixed cost per call cancels. Also
prints the balanced accuracy of `stiction_detected` on the fleet, and the status of
every loop that is not ok.

With `--whatif`, the same fleets are screened again with `ScreenSettings(whatif=
WhatIfSettings())` (`screen --whatif`: every loop called sticky gets its what-if),
after a warm-up of their own (which screens the paper's 1500-sample loop too, so
that the what-if program compiles there), and the what-if's marginal cost is the difference of
the two marginal costs, per screened loop and per loop called sticky. That
difference carries the noise of two fleets' timings, a few tenths of a second per
loop called sticky when few are; so the loops of the large fleet called sticky are
also screened alone, with and without the what-if, alternately three times each,
and the median difference per loop is the what-if's own cost per sticky loop.
"""

import argparse
import json
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402

from jaxstiction import (  # noqa: E402
    Experiment,
    Kano,
    make_loop,
    make_scenario,
    screen_loops,
    ScreenSettings,
    simulate_loop,
    WhatIfSettings,
)
from jaxstiction.internal import chunk_size, nominal_model  # noqa: E402


def fleet(count, offset=0, n=1500):
    loops, truth = {}, {}
    for i in range(offset, offset + count):
        rng = np.random.default_rng(i)
        sticky = i % 2 == 0
        S = float(rng.uniform(2, 20))
        chain = (Kano(S, float(S * rng.uniform(0.25, 1.0))),) if sticky else ()
        # half follow a GBN setpoint, half a setpoint that rarely moves (as
        # calibrate_verdict.py; with no setpoint move at all the noise level, set
        # relative to the noise-free PV, would be zero and OP and PV constant)
        sp, switch = (20.0, 0.05) if (i // 2) % 2 == 0 else (5.0, 0.004)
        exp = Experiment(sp_amplitude=sp, sp_switch_prob=switch, nsr=0.05)
        rec = simulate_loop(nominal_model(chain=chain), exp, jr.PRNGKey(10_000 + i), n)
        loops[f"loop{i:05d}"] = make_loop(np.asarray(rec.op), np.asarray(rec.pv), sp=np.asarray(rec.sp))
        truth[f"loop{i:05d}"] = sticky
    return loops, truth


def timed(count, offset, settings=ScreenSettings()):
    loops, truth = fleet(count, offset)
    t0 = time.perf_counter()
    res = screen_loops(loops, settings)
    return time.perf_counter() - t0, res, truth


def marginal_cost(small=8, large=24, settings=ScreenSettings()) -> dict:
    """Screen a warm-up chunk (it compiles), then a fleet of `small` and one of
    `large` loops; the marginal seconds per loop, the balanced accuracy of
    `stiction_detected`, and the status of every loop that is not ok."""
    t_warm, _, _ = timed(chunk_size(1500, settings), 10 * (small + large), settings)  # compiles
    if settings.whatif is not None:  # the what-if compiles on a loop called sticky: the paper's
        rec = make_scenario("paper_sim").estimation
        t0 = time.perf_counter()
        screen_loops({"paper_sim": make_loop(np.asarray(rec.op), np.asarray(rec.pv), sp=np.asarray(rec.sp))},
                     settings)
        t_warm += time.perf_counter() - t0
    t_small, r1, tr1 = timed(small, 0, settings)
    t_large, r2, tr2 = timed(large, small, settings)
    marginal = (t_large - t_small) / (large - small)
    truth = {**tr1, **tr2}
    res = r1 + r2
    pos = [r for r in res if truth[r["name"]]]
    neg = [r for r in res if not truth[r["name"]]]
    tpr = np.mean([r["stiction_detected"] for r in pos])
    tnr = np.mean([not r["stiction_detected"] for r in neg])
    return dict(seconds_warm_up=t_warm, small=small, large=large, seconds_small=t_small, seconds_large=t_large,
                marginal_seconds_per_loop=marginal, ok=sum(r["status"] == "ok" for r in res), loops=len(res),
                balanced_accuracy=0.5 * (tpr + tnr), sticky_small=sum(bool(r["stiction_detected"]) for r in r1),
                sticky_large=sum(bool(r["stiction_detected"]) for r in r2),
                sticky_names_large=[r["name"] for r in r2 if r.get("verdict") == "stiction"],
                devices=len(jax.local_devices()), threads=settings.threads,
                failed={r["name"]: r["status"] for r in res if r["status"] != "ok"})


def sticky_only_cost(names, settings: ScreenSettings, with_whatif: ScreenSettings, repeats: int = 3) -> dict:
    """The loops `names` of the fleet (those called sticky) screened alone with
    `settings` and with `with_whatif`, alternately `repeats` times each (both warm):
    the median of the paired differences per loop."""
    offsets = [int(n.removeprefix("loop")) for n in names]
    loops = {}
    for i in offsets:
        loops.update(fleet(1, i)[0])
    diffs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        screen_loops(loops, settings)
        t1 = time.perf_counter()
        screen_loops(loops, with_whatif)
        t2 = time.perf_counter()
        diffs.append(((t2 - t1) - (t1 - t0)) / max(len(loops), 1))
    return dict(loops=len(loops), seconds_per_sticky_loop=float(np.median(diffs)),
                seconds_per_sticky_loop_all=diffs)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--small", type=int, default=8)
    p.add_argument("--large", type=int, default=24)
    p.add_argument("--threads", type=int, default=0,
                   help="batched calls at once (ScreenSettings.threads; 0: one per CPU core)")
    p.add_argument("--chunk", type=int, default=0,
                   help="loops per batched call (ScreenSettings.chunk; 0: sized to the machine)")
    p.add_argument("--whatif", action="store_true",
                   help="also screen with --whatif and report what it adds per loop")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    settings = ScreenSettings(threads=args.threads, chunk=args.chunk)
    out = marginal_cost(args.small, args.large, settings)
    out.pop("sticky_names_large")
    if args.whatif:
        w_settings = ScreenSettings(threads=args.threads, chunk=args.chunk, whatif=WhatIfSettings())
        w = marginal_cost(args.small, args.large, w_settings)
        added = w["marginal_seconds_per_loop"] - out["marginal_seconds_per_loop"]
        more_sticky = w["sticky_large"] - w["sticky_small"]
        names = w.pop("sticky_names_large")
        out["whatif"] = dict(w, added_seconds_per_loop=added,
                             added_seconds_per_sticky_loop=added * (args.large - args.small) / max(more_sticky, 1))
        if names:
            out["whatif"]["sticky_alone"] = sticky_only_cost(names, settings, w_settings)
    if args.json:
        print(json.dumps(out))
        return
    print(f"warm-up (compilation): {out['seconds_warm_up']:.1f} s; {args.small} loops: {out['seconds_small']:.1f} s; "
          f"{args.large} loops: {out['seconds_large']:.1f} s")
    print(f"marginal: {out['marginal_seconds_per_loop']:.2f} s per 1500-sample loop (estimate + verdict); "
          f"{out['ok']}/{out['loops']} ok; balanced accuracy {out['balanced_accuracy']:.2f}")
    for status in out["failed"].values():
        print(f"  {status}")  # a loop's error names the loop
    if args.whatif:
        w = out["whatif"]
        print(f"with --whatif: warm-up {w['seconds_warm_up']:.1f} s; {args.small} loops: {w['seconds_small']:.1f} s; "
              f"{args.large} loops: {w['seconds_large']:.1f} s; "
              f"marginal {w['marginal_seconds_per_loop']:.2f} s per loop")
        print(f"--whatif adds {w['added_seconds_per_loop']:.2f} s per screened loop, "
              f"{w['added_seconds_per_sticky_loop']:.2f} s per loop called sticky "
              f"(called sticky: {w['sticky_small']} of {args.small}, {w['sticky_large']} of {args.large})")
        if "sticky_alone" in w:
            a = w["sticky_alone"]
            print(f"the {a['loops']} loops called sticky screened alone: --whatif adds "
                  f"{a['seconds_per_sticky_loop']:.2f} s per loop (median of "
                  f"{', '.join(f'{x:.2f}' for x in a['seconds_per_sticky_loop_all'])})")


if __name__ == "__main__":
    main()
