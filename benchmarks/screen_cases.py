"""The screen's stiction verdict on the concealed-effect cases P0-P10.

    python benchmarks/screen_cases.py                 # seeds 0-9
    python benchmarks/screen_cases.py --seeds 10-19

Each case's whole 3000-sample record (with its setpoint) goes through
`jaxstiction.screen_loops`, as `jaxstiction screen` runs it. P1 (Kano S 3, J 1) and
P10 (Kano S 4, J 1 beside an external sinusoid) hold a sticky valve; every other case
counts as not sticky, the P6 deadband (J = 0) included (a confounder here, although
the screen calls a valve band without a visible slip sticky). Prints each case's
verdicts and probabilities over the seeds and the balanced accuracy of
`stiction_detected`.
"""

import argparse

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _args import seeds_arg, seeds_text  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

import jaxstiction as js  # noqa: E402


CASES = tuple(f"P{k}" for k in range(11))
STICKY = ("P1", "P10")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-9"))
    parser.add_argument("--threads", type=int, default=0)
    args = parser.parse_args()
    loops = {}
    for seed in args.seeds:
        for case in CASES:
            rec = js.make_scenario(case, seed=seed).full
            loops[f"{case}/{seed}"] = js.make_loop(np.asarray(rec.op), np.asarray(rec.pv), 1.0, sp=np.asarray(rec.sp))
    entries = {e["name"]: e for e in js.screen_loops(loops, js.ScreenSettings(threads=args.threads))}
    print(f"P0-P10, seeds {seeds_text(args.seeds)}: verdicts (stiction / no_stiction / inconclusive), "
          "median probability, the model-based test alone (model_wins), gates")
    calls = []
    for case in CASES:
        mine = [entries[f"{case}/{s}"] for s in args.seeds]
        counts = [sum(e.get("verdict") == v for e in mine) for v in ("stiction", "no_stiction", "inconclusive")]
        probs = [e["stiction_probability"] for e in mine if e.get("stiction_probability") is not None]
        gates = sorted({e.get("gate") for e in mine if e.get("verdict") == "inconclusive"})
        wins = sum(bool(e.get("model_wins")) for e in mine)
        print(f"  {case:4s} {'sticky' if case in STICKY else '':6s} {counts[0]:3d} / {counts[1]:3d} / {counts[2]:3d}   "
              f"P {np.median(probs) if probs else float('nan'):.2f}   model {wins:3d}   {', '.join(gates)}")
        calls += [(bool(e["stiction_detected"]), case in STICKY) for e in mine]
    model = [(bool(e.get("model_wins")), e["name"].split("/")[0] in STICKY) for e in entries.values()]
    pos = [c for c, t in model if t]
    neg = [not c for c, t in model if not t]
    print(f"the model-based test alone: balanced accuracy {0.5 * (np.mean(pos) + np.mean(neg)):.3f}")
    pos = [c for c, t in calls if t]
    neg = [not c for c, t in calls if not t]
    print(f"balanced accuracy {0.5 * (np.mean(pos) + np.mean(neg)):.3f} (sticky {sum(pos)}/{len(pos)}, "
          f"not sticky {sum(neg)}/{len(neg)})")


if __name__ == "__main__":
    main()
