"""CHEM23's fast residual oscillation: where it is, and what modelling it buys.

    python benchmarks/chem23_oscillation.py [CHEM23.csv]

1. Fits the stiction model (`jaxstiction.fit`, last third held out) and takes the
   simulation residual PV - PV_sim over the whole record.
2. Finds the residual's narrow spectral line (period in samples) and measures its
   power in a band around it, separately where the fitted model valve is stuck and
   where it moves, and in the recorded OP.
3. Adds the line to the model two ways and scores on the held-out third:
   a phase-locked sinusoid at the process output (a `Sinusoid` block), and a
   resonant noise model (second-order D with its poles on the line), judged by
   one-step and k-step prediction errors.
"""

import argparse
from pathlib import Path

import jax
import numpy as np


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from jaxstiction import fit, NoiseModel, read_loop, simulate_scored, Sinusoid  # noqa: E402
from jaxstiction.internal import spectrum_lines  # noqa: E402


def band_power(x, period, width=0.15):
    """Fraction of the (demeaned) signal's power within +-width of 1/period (FFT)."""
    x = np.asarray(x, float) - np.mean(x)
    X = np.abs(np.fft.rfft(x)) ** 2
    f = np.fft.rfftfreq(len(x))
    f0 = 1.0 / period
    sel = np.abs(f - f0) <= width * f0
    return float(X[sel].sum() / max(X[1:].sum(), 1e-300)), float(np.sqrt(2 * X[sel].sum()) / len(x))


def main():
    default = Path(__file__).resolve().parents[2] / "shared/data/isdb/CHEM23.csv"
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("path", nargs="?", type=Path, default=default, metavar="CHEM23.csv",
                   help="the loop file (default: CHEM23 in ../shared/data/isdb beside the repository)")
    path = p.parse_args().path
    loop = read_loop(path)
    op, pv = np.asarray(loop.op), np.asarray(loop.pv)
    n = len(op)
    r = fit(op, pv, ts=float(loop.ts), validate=1 / 3, name="CHEM23")
    n_est = r.n_estimation
    z = pv - r.pv_sim
    spec = spectrum_lines(z[:n_est], seg=128)
    f, Pw = spec["frequency"], spec["power"]
    band = (f >= 1 / 12) & (f <= 1 / 5)
    i = int(np.argmax(np.where(band, Pw, 0.0)))
    P = float(1 / f[i])
    print(f"model: {r.model_kind}, held-out fitness {r.fitness:.2f} %")
    print(f"residual spectrum peak between 5 and 12 samples: period {P:.2f} samples, "
          f"{Pw[i] / np.median(Pw[f > 0.05]):.0f} x the median level above 0.05 cycles/sample")
    # where is the model valve stuck? (Kano fit of the estimator, on the recorded OP)
    from jaxstiction import Kano

    xk = np.asarray(Kano(r.S, r.J)(jnp.asarray(op)))
    stuck = np.concatenate([[False], np.diff(xk) == 0])
    # contiguous stuck / moving runs of at least 4 periods, line power in each
    def runs(mask):
        out, t = [], 0
        while t < n:
            if mask[t]:
                s = t
                while t < n and mask[t]:
                    t += 1
                if t - s >= 4 * P:
                    out.append((s, t))
            t += 1
        return out

    for name, mask in (("stuck", stuck), ("moving", ~stuck)):
        rs = runs(mask)
        if rs:
            amps = [band_power(z[s:e], P)[1] for s, e in rs]
            share = [band_power(z[s:e], P)[0] for s, e in rs]
            print(f"valve {name}: {len(rs)} runs of >= {4 * P:.0f} samples, "
                  f"line amplitude median {np.median(amps):.4g}, "
                  f"share of residual power median {np.median(share):.2f}")
    print(f"line share of power: residual {band_power(z, P)[0]:.3f}, PV {band_power(pv, P)[0]:.3f}, "
          f"OP {band_power(op, P)[0]:.3f}")
    # model it: phase-locked sinusoid, and a resonant noise model
    m = r.fit.model
    t = np.arange(n)
    A = np.stack([np.sin(2 * np.pi * t / P), np.cos(2 * np.pi * t / P)], 1)
    coef, *_ = np.linalg.lstsq(A[:n_est], z[:n_est] - z[:n_est].mean(), rcond=None)
    amp, ph = float(np.hypot(*coef)), float(np.arctan2(coef[1], coef[0]))
    ms = eqx.tree_at(lambda mm: mm.output, m, (Sinusoid(amp, P, ph + 2 * np.pi * n_est / P),))
    w = jnp.asarray((t >= n_est).astype(float))
    f0 = float(simulate_scored(m, jnp.asarray(op), jnp.asarray(pv), w)[1])
    f1 = float(simulate_scored(ms, jnp.asarray(op), jnp.asarray(pv), w)[1])
    print(f"held-out simulation fitness: model {f0:.2f} %, + phase-locked sinusoid (amplitude {amp:.4g}) {f1:.2f} %")
    rho = 0.95
    d_res = np.convolve(np.asarray(m.noise.d), [1.0, -2 * rho * np.cos(2 * np.pi / P), rho**2])
    mr = eqx.tree_at(lambda mm: mm.noise, m, NoiseModel(c=m.noise.c, d=d_res))
    h = slice(n_est + 20, n)
    for k in (1, 3, 10):
        e0 = pv[h] - np.asarray(m.predict(jnp.asarray(op), jnp.asarray(pv), k))[h]
        e1 = pv[h] - np.asarray(mr.predict(jnp.asarray(op), jnp.asarray(pv), k))[h]
        print(f"{k:2d}-step prediction RMS on held-out data: model {np.sqrt(np.mean(e0**2)):.4g}, "
              f"+ resonant noise model {np.sqrt(np.mean(e1**2)):.4g}")


if __name__ == "__main__":
    main()
