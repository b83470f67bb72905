"""Throughput of the high-order Hammerstein ARX relaxation, (13)-(16) of the paper.

Compares, in one run and on the same loops,

- JAX: `jax.jit(jax.vmap(relax(relax_problem(y, phi, n, method=C), method=M)))`
  over a batch of loops (float64, CPU); by default C = "gram" (the Gram-tensor
  route, for noisy records such as these) and M = "anderson" (accelerated
  alternation); choose with `--compression qr` and `--method alternation` or
  `variable_projection`; the batch runs `--first-steps` (40) steps, then the members
  not converged continue alone for the rest of the 200 (see `jax_fit`); and
- NumPy: `tests/reference.py::relax_reference`, the plain full-data implementation
  (explicit regression matrices, `numpy.linalg.lstsq`), one loop at a time,

and shows how time grows with the record length N, the ARX order n, the knot count m
and the batch size. Loops are paper_sim-like closed loops (BJ process, PI control,
Kano stiction S=20, J=2, 5 % noise power; `jaxstiction.simulate_loop` with
the paper_sim plant), one PRNG seed per loop.

    python benchmarks/bench_relax.py [--quick] [--json]

See benchmarks/README.md for the columns.
"""

import argparse
import json
import os
import sys
import time


os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The NumPy reference solves small least-squares problems one loop at a time: a
# multi-threaded BLAS only adds overhead there, and collapses when the cores are shared
# with another process. Set these yourself to override.
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optimistix as optx

from jaxstiction import Kano, simulate_loop
from jaxstiction.internal import (
    hysteresis_regressors,
    nominal_model,
    paper_experiment,
    relax,
    relax_problem,
    scale_input,
    uniform_knots,
)


sys.path.insert(
    0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests")
)
import reference as ref  # noqa: E402


def simulate(batch, N, seed=0):
    """`batch` paper_sim-like loops of N samples (op, pv as NumPy arrays)."""
    plant, exp = nominal_model(chain=(Kano(20.0, 2.0),)), paper_experiment()  # the paper_sim loop
    keys = jax.vmap(lambda s: jr.PRNGKey(s))(jnp.arange(seed, seed + batch))
    rec = jax.vmap(lambda k: simulate_loop(plant, exp, k, N))(keys)
    return np.asarray(rec.op), np.asarray(rec.pv)


@jax.jit
def _scaled(op, pv):
    y = (pv - pv.mean()) / pv.std()
    u = scale_input(op, op.min(), op.max())
    h = jnp.concatenate(
        [jnp.ones((1,)), (jnp.diff(u) >= 0).astype(u.dtype)]
    )  # rule (5)
    return y, u, h


def prepare(op, pv, m):
    """Scaled output y (B, N) and spline regressors phi (B, N, 2(m+2))."""
    y, u, h = jax.vmap(_scaled)(jnp.asarray(op), jnp.asarray(pv))
    knots = uniform_knots(m, jnp.float64)
    phi = jax.vmap(lambda u, h: hysteresis_regressors(u, h, knots))(u, h)
    return jax.block_until_ready(y), jax.block_until_ready(phi)


_FITS = {}
MAX_STEPS = 200  # relax's default budget, every step counted
FIRST_STEPS = 40  # --first-steps


def jax_fit(n):
    """The batched kernel: `jit(vmap(relax))` over the batch with a budget of
    FIRST_STEPS steps, then, for the members that have not converged (a few), the
    rest of the 200-step budget from where they stopped, in a batch of their own
    (padded to a power of two, so it compiles once per size). Under `vmap` every
    member runs as long as the slowest, so one loop that needs 200 steps would
    otherwise hold the whole batch for 200. FIRST_STEPS = 0: one call, 200 steps."""
    if n not in _FITS:
        first_budget = FIRST_STEPS or MAX_STEPS

        def first(y, phi):
            sol = relax(relax_problem(y, phi, n, method=COMPRESSION), method=METHOD, max_steps=first_budget)
            return sol.loss, sol.num_steps, sol.result == optx.RESULTS.successful, sol.model

        def rest(y, phi, model):
            sol = relax(relax_problem(y, phi, n, method=COMPRESSION), model, method=METHOD,
                        max_steps=MAX_STEPS - first_budget)
            return sol.loss, sol.num_steps, sol.result == optx.RESULTS.successful

        f1, f2 = jax.jit(jax.vmap(first)), jax.jit(jax.vmap(rest))

        def run(y, phi):
            loss, steps, ok, model = f1(y, phi)
            idx = np.flatnonzero(~np.asarray(ok))
            if FIRST_STEPS and idx.size:
                size = 1 << int(np.ceil(np.log2(idx.size)))
                pad = np.concatenate([idx, np.full(size - idx.size, idx[0])])
                l2, s2, o2 = f2(y[pad], phi[pad], jax.tree.map(lambda x: x[pad], model))
                k = idx.size
                loss = loss.at[idx].set(l2[:k])
                steps = steps.at[idx].add(s2[:k])
                ok = ok.at[idx].set(o2[:k])
            return loss, steps, ok

        _FITS[n] = run
    return _FITS[n]


def time_jax(y, phi, n, min_time):
    f = jax_fit(n)
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(y, phi))
    first = time.perf_counter() - t0
    best, total, reps = np.inf, 0.0, 0
    while reps < 2 or total < min_time:
        t0 = time.perf_counter()
        jax.block_until_ready(f(y, phi))
        dt = time.perf_counter() - t0
        best, total, reps = min(best, dt), total + dt, reps + 1
    loss, steps, result = (np.asarray(o) for o in out)
    return dict(
        compile=max(first - best, 0.0), t=best, loss=loss, steps=steps, ok=result
    )


def time_numpy(y, phi, n, count):
    y, phi = np.asarray(y[:count]), np.asarray(phi[:count])
    sols = []
    t0 = time.perf_counter()
    for i in range(count):
        sols.append(ref.relax_reference(y[i], phi[i], n))
    dt = time.perf_counter() - t0
    return dict(
        t=dt,
        loss=np.array([s.loss for s in sols]),
        steps=np.array([s.num_steps for s in sols]),
        ok=np.array([s.converged for s in sols]),
    )


HEAD = (
    "{:<6} {:>5} {:>3} {:>3} {:>5} | {:>9} {:>10} {:>9} {:>7} {:>5} | "
    "{:>5} {:>9} {:>7} {:>5} | {:>7} {:>9}"
)
COLS = (
    "sweep",
    "N",
    "n",
    "m",
    "batch",
    "compile_s",
    "batch_ms",
    "jax_lps",
    "j_step",
    "j_ok",
    "np_k",
    "np_lps",
    "n_step",
    "n_ok",
    "speedup",
    "dloss_rel",
)


_DONE = {}
OUT = sys.stdout
COMPRESSION, METHOD = "gram", "anderson"


def row(label, op, pv, N, n, m, batch, np_count, min_time):
    key = (N, n, m, batch, min(np_count, batch))
    if key in _DONE:  # the same case in another sweep: reuse its timing
        print(f"{label:<6}" + _DONE[key][6:] + "  (same case as above)", flush=True, file=OUT)
        return None
    y, phi = prepare(op[:batch, :N], pv[:batch, :N], m)
    j = time_jax(y, phi, n, min_time)
    k = min(np_count, batch)
    r = time_numpy(y, phi, n, k)
    jax_lps = batch / j["t"]
    np_lps = k / r["t"]
    rel = (j["loss"][:k] - r["loss"]) / r["loss"]
    dloss = rel[
        np.argmax(np.abs(rel))
    ]  # signed: > 0 means the JAX fit has the higher loss
    line = HEAD.format(
        label,
        N,
        n,
        m,
        batch,
        f"{j['compile']:.2f}",
        f"{1e3 * j['t']:.2f}",
        f"{jax_lps:.1f}",
        int(j["steps"].max()),
        f"{j['ok'].mean():.2f}",
        k,
        f"{np_lps:.1f}",
        f"{r['steps'].mean():.0f}",
        f"{r['ok'].mean():.2f}",
        f"{jax_lps / np_lps:.1f}x",
        f"{dloss:+.1e}",
    )
    _DONE[key] = line
    print(line, flush=True, file=OUT)
    return dict(sweep=label, N=N, n=n, m=m, batch=batch, compile_s=j["compile"], jax_ms_per_loop=1e3 * j["t"] / batch,
                numpy_ms_per_loop=1e3 * r["t"] / k, speedup=jax_lps / np_lps, jax_steps_max=int(j["steps"].max()),
                numpy_steps_mean=float(r["steps"].mean()), jax_ok=float(j["ok"].mean()),
                numpy_ok=float(r["ok"].mean()), dloss_rel=float(dloss))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--quick", action="store_true", help="a ~30 s version (fewer, smaller cases)"
    )
    ap.add_argument(
        "--numpy-loops",
        type=int,
        default=None,
        help="loops timed with NumPy per row (default 16, quick 4)",
    )
    ap.add_argument("--compression", choices=("gram", "qr"), default="gram",
                    help="relax_problem(method=...) of the JAX kernel (default gram: these loops are noisy)")
    ap.add_argument("--method", choices=("alternation", "anderson", "variable_projection"), default="anderson",
                    help="relax(method=...) of the JAX kernel")
    ap.add_argument("--first-steps", type=int, default=40,
                    help="steps of the whole batch before the unconverged members continue alone (0: one call)")
    ap.add_argument("--seed", type=int, default=0,
                    help="PRNG seed of the first loop (loop i uses seed + i; default 0)")
    ap.add_argument("--json", action="store_true",
                    help="print one JSON object on stdout (the table goes to stderr)")
    ap.add_argument("--screen", type=int, nargs=2, default=None, metavar=("SMALL", "LARGE"),
                    help="also time the full screen (estimate + verdict, fleet.py) on fleets of SMALL and LARGE "
                         "1500-sample loops; 0 0 skips it (default 8 24, skipped with --quick)")
    args = ap.parse_args()
    global OUT, COMPRESSION, METHOD, FIRST_STEPS
    OUT = sys.stderr if args.json else sys.stdout
    FIRST_STEPS = min(max(args.first_steps, 0), MAX_STEPS - 1)
    COMPRESSION, METHOD = args.compression, args.method
    q = args.quick
    np_count = args.numpy_loops or (8 if q else 16)
    min_time = 0.1 if q else 0.5
    base = dict(N=1500, n=10, m=6, batch=8 if q else 32)
    Ns = (750, 1500) if q else (750, 1500, 3000)
    ns = (5, 10) if q else (5, 10, 20)
    ms = (4, 6) if q else (4, 6, 10)
    batches = (1, 8) if q else (1, 8, 32, 128)
    sweep_batch = 8 if q else 16

    print(
        f"jax {jax.__version__}, numpy {np.__version__}, device {jax.devices()[0]}, "
        f"float64, {os.cpu_count()} CPU(s), "
        f"OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}",
        file=OUT,
    )
    t0 = time.perf_counter()
    op, pv = simulate(max(max(batches), base["batch"]), max(Ns), seed=args.seed)
    print(
        f"simulated {op.shape[0]} paper_sim-like loops of {op.shape[1]} samples (seeds {args.seed}..) "
        f"in {time.perf_counter() - t0:.1f} s\n",
        file=OUT,
    )
    print(HEAD.format(*COLS), file=OUT)
    print("-" * len(HEAD.format(*COLS)), file=OUT)
    b = base
    rows = [row("main", op, pv, b["N"], b["n"], b["m"], b["batch"], b["batch"], min_time)]
    for N in Ns:
        rows.append(row("N", op, pv, N, b["n"], b["m"], sweep_batch, np_count, min_time))
    for n in ns:
        rows.append(row("n", op, pv, b["N"], n, b["m"], sweep_batch, np_count, min_time))
    for m in ms:
        rows.append(row("m", op, pv, b["N"], b["n"], m, sweep_batch, np_count, min_time))
    for B in batches:
        rows.append(row("batch", op, pv, b["N"], b["n"], b["m"], B, np_count, min_time))
    screen = None
    small, large = args.screen or ((0, 0) if q else (8, 24))
    if large > small >= 0:
        # the whole pipeline beside the kernel: what a loop costs the screen
        from fleet import marginal_cost  # benchmarks/ is on sys.path when run as a script

        screen = marginal_cost(small, large)
        print(f"\nfull screen (estimate + verdict, fleet.py): {screen['marginal_seconds_per_loop']:.3f} s per "
              f"1500-sample loop marginal (fleets of {small} and {large}; "
              f"{screen['ok']}/{screen['loops']} ok)", file=OUT)
    total = time.perf_counter() - t0
    print(f"\ntotal {total:.0f} s", file=OUT)
    if args.json:
        head = rows[0]
        print(json.dumps({"headline": head, "jax_ms_per_loop": head["jax_ms_per_loop"],
                          "numpy_ms_per_loop": head["numpy_ms_per_loop"], "speedup": head["speedup"],
                          "screen_seconds_per_loop": screen and screen["marginal_seconds_per_loop"],
                          "rows": [r for r in rows if r is not None], "total_s": total}))


if __name__ == "__main__":
    main()
