"""How often can a drift like P8's be found at all? The drift test's power against
the most powerful test there is.

    python benchmarks/drift_power.py                        # seeds 0-199, drift steps 0.2-0.5, ~9 min
    python benchmarks/drift_power.py --seeds 0-49 --steps 0.3 --json

P8 hides a random walk (step standard deviation 0.3) in the PV of a loop whose noise
is AR(1) with pole 0.9. `diagnose` tests for it on the nominal model's simulation
residual over the 2000 estimation samples (`jaxstiction.internal.drift_test`: the
likelihood gained by a random walk over the best stationary AR(1) model, the pole
unknown). With the nominal right, that residual is exactly the noise plus the drift,
so the question is purely statistical: how often does a record of 2000 samples show
the drift at all?

Per drift step, over the same seeds (the P-cases' setpoint and noise draws; P0 is the
same loop without the drift), this prints the power at false-alarm rates of 1, 2 and
5 % on P0 of

- `glr`: the drift test as `diagnose` computes it, its threshold set on P0's own
  statistics (an exactly calibrated test, not the conservative chi-bar-squared
  bound `diagnose` uses);
- `oracle`: the Neyman-Pearson likelihood ratio of AR(1) noise against AR(1) noise
  plus the random walk with the true pole (0.9), the true drift-to-noise ratio and
  the noise scale of P0's residual: the most powerful test of any at that
  false-alarm rate. No test that does not know the noise model can do better;

and the power and false-alarm rate of `diagnose`'s own rule (the chi-bar-squared
tail of twice the statistic, Bonferroni-corrected over the eight families at
`alpha` = 0.05: statistic >= 3.12).
"""

import argparse
import json
import math
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
from _args import seeds_arg, seeds_text  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

from jaxstiction import (  # noqa: E402
    DiagnoseSettings,  # noqa: E402
    Drift,
    simulate_loop,
)
from jaxstiction.internal import (  # noqa: E402  # noqa: E402  # noqa: E402
    drift_test,
    INPUT_FAMILIES,
    neg_loglik,
    nominal_model,
    OUTPUT_FAMILIES,
    p_experiment,
    P_N,
    P_SPLIT,
)


POLE = 0.9  # the P-cases' noise colouring 1/(1 - 0.9 q^-1)
FALSE_ALARMS = (0.01, 0.02, 0.05)


def rule_threshold(alpha=DiagnoseSettings().alpha, families=len(INPUT_FAMILIES) + len(OUTPUT_FAMILIES)):
    """The smallest statistic `diagnose` calls significant: families/2 erfc(sqrt T) <= alpha."""
    lo, hi = 0.0, 50.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if families * 0.5 * math.erfc(math.sqrt(mid)) <= alpha else (mid, hi)
    return hi


@jax.jit
def _oracle(z, q):
    """Log-likelihood ratio of the random walk + AR(1) model against AR(1) alone, both
    with the true pole and ratio `q` (the noise scale concentrated out)."""
    y = z - jnp.mean(z)
    a = jnp.asarray(POLE, z.dtype)
    return neg_loglik(y, a, jnp.zeros((), z.dtype))[0] - neg_loglik(y, a, q)[0]


def residual(seed, step):
    """The nominal's simulation residual over the estimation samples of P0 (`step` 0)
    or of P8 with a drift of that step, simulated as `make_scenario` does."""
    key = jr.PRNGKey(seed)
    output = (Drift(step, jr.key_data(jr.fold_in(key, 7))),) if step > 0 else ()
    rec = simulate_loop(nominal_model(output=output), p_experiment(), jr.fold_in(key, 3), P_N)
    return np.asarray(rec.pv - nominal_model().simulate(rec.op))[:P_SPLIT]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(200)), help="e.g. 0-199 or 3,5,7")
    p.add_argument("--steps", default="0.2,0.3,0.4,0.5", help="drift step standard deviations, comma-separated")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    steps = [float(s) for s in args.steps.split(",")]
    t0 = time.time()
    glr = {s: [] for s in [0.0, *steps]}  # diagnose's statistic on P0 (step 0) and on each drift
    orc = {s: [] for s in steps}  # per drift: the oracle's statistic on P0 and on that drift
    for seed in args.seeds:
        z0 = residual(seed, 0.0)
        sigma_e = float(np.std(z0[1:] - POLE * z0[:-1]))  # the AR(1) innovation scale
        glr[0.0].append(float(drift_test(jnp.asarray(z0))[0]))
        for step in steps:
            z = residual(seed, step)
            glr[step].append(float(drift_test(jnp.asarray(z))[0]))
            # the oracle's ratio depends on the drift, so P0 is scored once per drift: its own null
            q = jnp.asarray(step**2 / sigma_e**2)
            orc[step].append([float(_oracle(jnp.asarray(zz), q)) for zz in (z0, z)])
    rule = rule_threshold()
    T0 = np.array(glr[0.0])
    out = {"seeds": seeds_text(args.seeds), "rule_threshold": rule, "rule_false_alarms": float(np.mean(T0 >= rule)),
           "steps": {}}
    for step in steps:
        T = np.array(glr[step])
        L = np.array(orc[step])  # (seeds, 2): the oracle's statistic on P0, on P8
        row = {"rule_power": float(np.mean(T >= rule))}
        for fa in FALSE_ALARMS:
            row[f"glr_power_{fa:g}"] = float(np.mean(T > np.quantile(T0, 1 - fa)))
            row[f"oracle_power_{fa:g}"] = float(np.mean(L[:, 1] > np.quantile(L[:, 0], 1 - fa)))
        out["steps"][f"{step:g}"] = row
    out["seconds"] = round(time.time() - t0, 1)
    if args.json:
        print(json.dumps(out))
        return
    n = len(args.seeds)
    print(f"{n} seeds ({out['seeds']}); diagnose's rule (statistic >= {rule:.2f}): "
          f"false alarms on P0 {out['rule_false_alarms']:.1%}")
    print("drift step | rule | " + " | ".join(f"glr @{fa:.0%} | oracle @{fa:.0%}" for fa in FALSE_ALARMS))
    for step, row in out["steps"].items():
        print(f"{step:>10} | {row['rule_power']:.1%} | " + " | ".join(
            f"{row[f'glr_power_{fa:g}']:.1%} | {row[f'oracle_power_{fa:g}']:.1%}" for fa in FALSE_ALARMS))
    print(f"({out['seconds']} s; power = share of seeds whose drift is found; each test's threshold is the "
          f"quantile of its own statistic on P0 at that false-alarm rate)")


if __name__ == "__main__":
    main()
