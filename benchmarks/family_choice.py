"""Which model family `estimate` chooses on loops with processes drawn per loop, and
how each family simulates held out: the figures the README's *Choice* quotes.

    python benchmarks/family_choice.py                  # six kinds x seeds 0-7, 48 loops (~11 min)
    python benchmarks/family_choice.py --seeds 0-1      # 12 loops

The loops are `make_diverse` of `calibrate_verdict.py` (a flow, slow dead-time,
second-order or integrating process, SIMC-tuned PI, drawn noise and drift; kinds
stiction, none, tight, external, deadband, small_slip). Each chunk of 6 loops goes
through one vmapped `estimate` (the full estimator, `Settings()`). One row per loop:
the chosen family and its held-out and estimation fitness, every family's held-out
fitness and its fitness on the estimation part (initial state from the opening
samples, as every score), and the result code. A `<--` marks a loop whose chosen
model scores below zero on its estimation part or more than 10 points below the
better of the Kano and linear models held out.
"""

import argparse
import time

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402
from _args import seeds_arg  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from calibrate_verdict import KINDS, make_diverse  # noqa: E402

import jaxstiction as js  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(8)))
    p.add_argument("--chunk", type=int, default=6, help="loops per vmapped call")
    args = p.parse_args()
    items = []
    for kind in KINDS:
        for s in args.seeds:
            loop, truth, _ = make_diverse(kind, s)
            items.append((f"{kind}-{s}", truth["plant"], loop))
    fit = eqx.filter_jit(eqx.filter_vmap(js.estimate))
    print(f"{'loop':<14} {'process':<12} {'chosen':<8} {'held out':>8} {'est':>7} | held out: "
          f"{'spline':>7} {'kano':>7} {'linear':>7} | estimation: {'spline':>7} {'kano':>7} {'linear':>7} | code")
    kinds = {"spline": 0, "kano": 0, "linear": 0}
    t0 = time.time()
    for i in range(0, len(items), args.chunk):
        chunk = items[i:i + args.chunk]
        f = jax.tree.map(np.asarray, fit(js.stack([c[2] for c in chunk])))
        for j, (name, plant, _) in enumerate(chunk):
            g = lambda x: float(x[j])  # noqa: E731
            kind = ("spline", "kano", "linear")[int(f.kind[j])]
            kinds[kind] += 1
            flag = g(f.fitness_estimation) < 0 or g(f.fitness) < max(g(f.fitness_linear), g(f.fitness_physical)) - 10
            print(f"{name:<14} {plant:<12} {kind:<8} {g(f.fitness):8.1f} {g(f.fitness_estimation):7.1f} | "
                  f"{'':>10}{g(f.fitness_spline):7.1f} {g(f.fitness_physical):7.1f} {g(f.fitness_linear):7.1f} | "
                  f"{'':>12}{g(f.fitness_spline_estimation):7.1f} {g(f.fitness_physical_estimation):7.1f} "
                  f"{g(f.fitness_linear_estimation):7.1f} | {int(f.result._value[j])}" + ("  <--" if flag else ""),
                  flush=True)
    print(f"\n{len(items)} loops in {time.time() - t0:.0f} s; chosen: "
          + ", ".join(f"{k} {v}" for k, v in kinds.items()))


if __name__ == "__main__":
    main()
