"""What the realistic fleet's records can show at best: an oracle test of each sticky valve.

    python benchmarks/verdict_oracle.py                      # check seeds 400-599, ~1 min
    python benchmarks/verdict_oracle.py --seeds 600-799 --loops

The verdict's balanced accuracy on the realistic simulated fleet
(`jaxstiction.internal.realistic_fleet`) is measured by
`calibrate_probability.py`. This script asks how well *any* detector could do on
the same records. For each sticky draw, an oracle that knows the process (its `B`,
`A` and dead time), the disturbance's spectrum and the valve's true path tests, by
the likelihood ratio of a Gaussian linear model, whether PV carries the process
driven by that valve path beyond what the process driven by OP explains:

    PV = c P(OP) + g P(valve) + nuisance + disturbance,    H0: g = 0,

with the nuisance spanning a PV offset, a constant valve offset and every initial
state of the process (the record starts after a run-in), and the disturbance
whitened by a 20th-order AR model fitted to its true realisation. Under H0 the
statistic is chi-square with one degree of freedom; under the sticky valve it is
non-central with `lambda = ||residual of P(valve) on the rest, whitened||^2 /
innovation variance` (g = 1). So the oracle's sensitivity at a threshold t is
P(chi2_1(lambda) > t) per valve, its specificity on a healthy twin 1 - P(chi2_1 > t),
and the best balanced accuracy over t is an upper bound for a detector that does
not know the valve path, the process or the noise, and must also tell the deadband,
tight-tuning and external-oscillation confounders apart.

Two versions:

- **free gain** (`c` fitted): a valve that never moves in the record is a constant,
  which a healthy loop with `c = 0` explains exactly, so it cannot be seen;
- **known gain** (`c = 1`, the alternative is the same process driven by OP): a
  valve that does not move while OP does is then evidence too, an "OP that PV does
  not answer", which a detector could only use with the process gain known from
  elsewhere.

The screen's hard gates (`jaxstiction.internal.gate_measures` with
`VerdictSettings`' thresholds, `_gate.hard_gated`) stop a record that the historian compressed or
quantised coarsely, or whose OP sits at a stop, as `inconclusive` whatever the
evidence; counted as not sticky, such a sticky valve is a miss for any detector that
keeps them.

Printed: per sticky draw with `--loops`, its slip count, both lambdas and whether a
hard gate stops it; then the number of valves that never slip, each version's best
balanced accuracy, and the bound for a detector that honours the hard gates and
makes no false alarm: half of (sticky valves neither stopped nor with a free-gain
lambda under 9, over all sticky valves, plus one). The historian's compression and
quantisation stay in PV, as recorded.
"""

import argparse

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _args import seeds_arg, seeds_text, slip_count  # noqa: E402
from _gate import hard_gated  # noqa: E402
from scipy.signal import lfilter  # noqa: E402
from scipy.stats import norm  # noqa: E402

from jaxstiction.internal import fleet_draw, realistic_fleet  # noqa: E402


AR = 20  # order of the disturbance's whitening filter


def process(b, a, delay, x):
    """`B/A` with `delay` extra samples (the fleet's convention: PV(t) takes the
    valve at t - 1 - delay), from rest."""
    return lfilter(np.concatenate([np.zeros(1 + delay), b]), a, x)


def oracle_lambdas(loop, params):
    """(free-gain lambda, known-gain lambda) of one sticky draw (module notes)."""
    b, a, delay = params["b"], params["a"], int(params["delay"])
    n = len(loop.pv)
    px, pu = process(b, a, delay, loop.valve), process(b, a, delay, loop.op)
    free = []
    for k in range(len(a) + delay + 3):  # every initial state: the first samples free, then A's recursion
        impulse = np.zeros(n)
        impulse[k] = 1.0
        free.append(lfilter([1.0], a, impulse))
    nuisance = np.column_stack([np.ones(n), process(b, a, delay, np.ones(n))] + free)
    y = loop.pv
    # the disturbance as the oracle knows it (up to the nuisance), and its whitening
    z = y - px
    dist = z - nuisance @ np.linalg.lstsq(nuisance, z, rcond=None)[0]
    lags = np.column_stack([dist[AR - k - 1 : n - k - 1] for k in range(AR)])
    phi = np.linalg.lstsq(lags, dist[AR:], rcond=None)[0]
    w = np.concatenate([[1.0], -phi])

    def white(v):
        return lfilter(w, [1.0], v, axis=0)[AR:]

    var = float(np.mean(white(dist) ** 2))

    def lam(target, others):
        t, m = white(target), white(others)
        r = t - m @ np.linalg.lstsq(m, t, rcond=None)[0]
        return float(r @ r / var)

    return lam(px, np.column_stack([pu, nuisance])), lam(px - pu, nuisance)


def power(lam, t):
    """P(chi2_1(lam) > t)."""
    s = np.sqrt(np.asarray(lam))
    return norm.cdf(s - np.sqrt(t)) + norm.cdf(-s - np.sqrt(t))


def best_balanced(lams):
    """The best balanced accuracy over thresholds t, and that t."""
    ts = np.linspace(0.01, 100.0, 10000)
    ba = [0.5 * (np.mean(power(lams, t)) + 1.0 - 2.0 * norm.cdf(-np.sqrt(t))) for t in ts]
    i = int(np.argmax(ba))
    return float(ba[i]), float(ts[i])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=seeds_arg, default=seeds_arg("400-599"))
    parser.add_argument("--loops", action="store_true", help="print every sticky draw")
    args = parser.parse_args()
    rows = []
    for loop in realistic_fleet(args.seeds):
        if not loop.sticky:
            continue
        slips = slip_count(loop.valve)
        free, known = oracle_lambdas(loop, fleet_draw(loop.seed, None)[0])
        rows.append((loop.seed, slips, free, known, hard_gated(loop.op, loop.pv, loop.sp)))
        if args.loops:
            print(f"  seed {loop.seed:4d}  slips {slips:4d}  lambda free gain {free:12.1f}  known gain {known:12.1f}"
                  f"  {'integrating' if loop.integrating else 'self-regulating'}, delay {loop.delay}, "
                  f"{len(loop.pv)} samples, setpoint {loop.setpoint}{', hard-gated' if rows[-1][4] else ''}")
    slips = np.array([r[1] for r in rows])
    free = np.array([r[2] for r in rows])
    known = np.array([r[3] for r in rows])
    gated = np.array([r[4] for r in rows])
    print(f"seeds {seeds_text(args.seeds)}: {len(rows)} sticky valves; {int(np.sum(slips == 0))} never slip in "
          f"their record, {int(np.sum(slips < 4))} slip fewer than 4 times")
    for name, lam in (("free gain", free), ("known gain", known)):
        ba, t = best_balanced(lam)
        print(f"  oracle, {name:10s}: best balanced accuracy {ba:.3f} (threshold {t:.1f}); lambda < 9 on "
              f"{int(np.sum(lam < 9))} valves, of which {int(np.sum((lam < 9) & (slips == 0)))} never slip; "
              f"smallest lambda of a valve that slips: {np.min(lam[slips > 0]) if np.any(slips > 0) else np.nan:.1f}")
    seen = int(np.sum(~gated & (free >= 9.0)))
    print(f"  the screen's hard gates stop {int(gated.sum())} of them; {seen} are neither stopped nor below lambda 9 "
          f"with the gain free: a detector that honours the gates, with no false alarm, reaches at most "
          f"{0.5 * (seen / len(rows) + 1.0):.3f}")


if __name__ == "__main__":
    main()
