"""Where S sits inside a slip cell, and what that does to paper_sim's validation score.

    python benchmarks/paper_sim_cells.py --seeds 0-29            # the plant's cells (~2 min)
    python benchmarks/paper_sim_cells.py --seeds 0-29 --fitted   # the fit's own cells (~8 min)

A Kano valve driven by a recorded OP slips where the OP's excursion first passes S
(or J), so a range of S (at fixed J), the *cell*, gives exactly the same slip samples
on a record; the estimation data cannot tell its points apart by their slip times.
For each seed this finds the cell on the estimation record (S on a grid of 0.0005 %
within +-0.3, the first 50 samples ignored) and scores, against the noise-free
validation PV (initial state estimated as `demo` does), a model whose S is moved to
fractions 0 (the cell's lower edge), 0.1, 0.25, 0.4, 0.5, 0.75 and 1 (its upper
edge) of the cell, everything else unchanged:

- by default the **plant** (true linear part, true J), in the plant's own cell;
- with `--fitted` the **fitted** model (`jaxstiction demo --seed S`'s fit), in the
  cell of its own slip path at its fitted J; the last column is the fit unmoved.

Prints one row per seed and, per fraction, how many seeds reach >= 95 % and >= 85 %.
"""

import argparse

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _args import seeds_arg  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from paper_sim_seeds import _CELL_GRID, _CELL_HALF, _kano_paths  # noqa: E402

from jaxstiction import (
    fit,  # noqa: E402
    fitness,  # noqa: E402
    Kano,  # noqa: E402
    make_scenario,  # noqa: E402
    simulate_scored,  # noqa: E402
)


BURN = 50  # samples ignored at the start, as paper_sim_seeds.py's cell
FRACTIONS = (0.0, 0.1, 0.25, 0.4, 0.5, 0.75, 1.0)
GRID = np.arange(-_CELL_HALF, _CELL_HALF + _CELL_GRID / 2, _CELL_GRID)


def cell(op, S, J, reference):
    """`(lo, hi)`: offsets from S of the contiguous run of grid points around S whose
    valve path moves at exactly the samples `reference` moves at."""
    moves = np.diff(np.asarray(reference)) != 0
    paths = np.asarray(_kano_paths(op, jnp.asarray(S + GRID), jnp.full(GRID.shape, J)))
    same = np.all((np.diff(paths, axis=1) != 0)[:, BURN:] == moves[None, BURN:], axis=1)
    i = lo = hi = int(np.argmin(np.abs(GRID)))
    if not same[i]:
        return 0.0, 0.0
    while lo > 0 and same[lo - 1]:
        lo -= 1
    while hi < GRID.size - 1 and same[hi + 1]:
        hi += 1
    return float(GRID[lo]), float(GRID[hi])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(range(30)))
    p.add_argument("--fitted", action="store_true", help="move the fitted model's S in its own cell")
    args = p.parse_args()
    columns = FRACTIONS + (("unmoved",) if args.fitted else ())
    counts = np.zeros((len(columns), 2), int)
    for seed in args.seeds:
        sc = make_scenario("paper_sim", seed=seed)
        est, val = sc.estimation, sc.validation
        if args.fitted:
            model = fit(np.asarray(est.op), np.asarray(est.pv), ts=1.0, validate=0.0, name="paper_sim").fit.model
            reference = None
        else:
            model, reference = sc.plant, est.valve
        k = model.chain[0]
        S, J = float(k.S), float(k.J)
        if reference is None:
            reference = _kano_paths(est.op, jnp.asarray([S]), jnp.asarray([J]))[0]
        lo, hi = cell(est.op, S, J, reference)
        whole = jnp.ones_like(val.op)
        scores = []
        for c in columns:
            Sx = S if c == "unmoved" else S + lo + c * (hi - lo)
            moved = eqx.tree_at(lambda m: m.chain[0], model, Kano(Sx, J))
            scores.append(float(fitness(val.pv_clean, simulate_scored(moved, val.op, val.pv, whole)[0])))
        counts += np.array([[s >= 95, s >= 85] for s in scores])
        where = f"{-lo / (hi - lo):.2f}" if hi > lo else "  - "
        print(f"seed {seed:3d}  S {S:8.4f}  J {J:6.4f}  cell [{S + lo:8.4f}, {S + hi:8.4f}]  S at {where}  | "
              + " ".join(f"{s:6.1f}" for s in scores), flush=True)
    print(f"\n{'fitted model in its own cell' if args.fitted else 'plant in its own cell'}, "
          f"{len(args.seeds)} seeds; seeds >= 95 % / >= 85 % per position of S:")
    for c, (a, b) in zip(columns, counts):
        print(f"  {c if isinstance(c, str) else f'fraction {c:.2f}'}: {a} / {b}")


if __name__ == "__main__":
    main()
