"""paper_sim over many seeds: the table the README quotes.

    python benchmarks/paper_sim_seeds.py                 # seeds 0-9
    python benchmarks/paper_sim_seeds.py --seeds 10-19   # other seeds
    python benchmarks/paper_sim_seeds.py --json          # one JSON object

For each seed: fit the 1500-sample estimation record, score the chosen model on the
independent 1500-sample validation record with its initial state estimated from the
opening samples of the measured PV (exactly what `jaxstiction demo --seed S` does),
and compare with the truth (Kano S = 20, J = 2). Prints per seed and a summary
against the targets: noise-free fitness >= 95 % (>= 85 % on all), within 2 points of
the ceiling, S within +-1 of 20 and J within +-0.5 of 2.
"""

import argparse
import json
import statistics
import sys
import time

import jax


jax.config.update("jax_enable_x64", True)

from _args import seeds_arg  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

from jaxstiction._demo import paper_sim_case  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(10)), help="e.g. 0-9 or 3,5,7")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    rows = []
    t_all = time.time()
    for seed in args.seeds:
        t = time.time()
        pay, _, _ = paper_sim_case(seed)
        st = pay["stiction"]
        row = dict(
            seed=seed,
            noise_free=pay["fitness_noise_free"],
            measured=pay["fitness_validation"],
            ceiling=pay["ceiling"],
            gap=pay["ceiling"] - pay["fitness_validation"],
            S=st["S"],
            J=st["J"],
            model=pay["fit"]["model"]["kind"],
            paper_method=pay["fitness_paper_method"],
            seconds=time.time() - t,
        )
        rows.append(row)
        if not args.json:
            print(
                f"seed {seed:3d}: noise-free {row['noise_free']:7.2f} %  measured {row['measured']:6.2f} % "
                f"(ceiling {row['ceiling']:.2f}, gap {row['gap']:+.2f})  S {row['S']:.3f}  J {row['J']:.3f}  "
                f"{row['model']:<8s} paper's method {row['paper_method']:.4g} %  [{row['seconds']:.0f} s]",
                flush=True,
            )
    nf = [r["noise_free"] for r in rows]
    summary = dict(
        seeds=args.seeds,
        noise_free_min=min(nf),
        noise_free_median=statistics.median(nf),
        noise_free_ge95=sum(v >= 95 for v in nf),
        noise_free_ge85=sum(v >= 85 for v in nf),
        within_2_of_ceiling=sum(r["gap"] <= 2 for r in rows),
        gap_max=max(r["gap"] for r in rows),
        S_within_1=sum(abs(r["S"] - 20) <= 1 for r in rows),
        J_within_half=sum(abs(r["J"] - 2) <= 0.5 for r in rows),
        SJ_both=sum(abs(r["S"] - 20) <= 1 and abs(r["J"] - 2) <= 0.5 for r in rows),
        total_seconds=time.time() - t_all,
    )
    if args.json:
        json.dump({"rows": rows, "summary": summary}, sys.stdout)
        print()
    else:
        n = len(rows)
        print(
            f"\n{n} seeds ({args.seeds[0]}..{args.seeds[-1]}): noise-free min {summary['noise_free_min']:.2f} %, "
            f"median {summary['noise_free_median']:.2f} %, >= 95 %: {summary['noise_free_ge95']}/{n}, "
            f">= 85 %: {summary['noise_free_ge85']}/{n}; within 2 of ceiling: {summary['within_2_of_ceiling']}/{n} "
            f"(largest gap {summary['gap_max']:.2f}); S within 1: {summary['S_within_1']}/{n}, "
            f"J within 0.5: {summary['J_within_half']}/{n}, both: {summary['SJ_both']}/{n}; "
            f"{summary['total_seconds']:.0f} s"
        )


if __name__ == "__main__":
    main()
