r"""Locate a mismatch: tests on the residuals of a nominal simulation.

Two residuals are examined: the simulation error $z = y - \hat y_{sim}$ and the
one-step prediction error $\varepsilon$ of an AR noise model refitted to $z$. Every
test uses a 99 % band. These are host-side NumPy functions on one record: they run
once per diagnosis, on arrays a person will read.
"""

from __future__ import annotations

import math

import numpy as np
from jax.scipy.special import gammaincc


Z99 = 2.5758  # two-sided 99 % normal quantile


def chi2_sf(x: float, dof: int) -> float:
    """Upper tail of the chi-squared distribution."""
    return float(gammaincc(dof / 2.0, max(x, 0.0) / 2.0))


def ar_whiten(z: np.ndarray, order: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One-step prediction errors of an AR(`order`) model fitted to `z` by least
    squares (QR). Returns `(eps, d)` with `d` the AR polynomial `[1, d1, ...]`."""
    z = np.asarray(z, float) - np.mean(z)
    X = np.stack([z[order - k - 1 : len(z) - k - 1] for k in range(order)], axis=1)
    coef, *_ = np.linalg.lstsq(X, z[order:], rcond=None)
    eps = z[order:] - X @ coef
    return np.concatenate([np.zeros(order), eps]), np.concatenate([[1.0], -coef])


def _acf(x: np.ndarray, lags: int) -> np.ndarray:
    x = x - x.mean()
    d = float(np.dot(x, x)) or 1.0
    return np.array([np.dot(x[k:], x[: len(x) - k]) / d for k in range(1, lags + 1)])


def whiteness(eps: np.ndarray, lags: int = 20, fitted: int = 2) -> dict:
    """Ljung–Box test of `eps` over `lags` lags (99 %), `fitted` parameters used."""
    n = len(eps)
    r = _acf(eps, lags)
    q = n * (n + 2) * float(np.sum(r**2 / (n - np.arange(1, lags + 1))))
    p = chi2_sf(q, lags - fitted)
    return {"statistic": round(q, 3), "p_value": p, "lags": lags, "white": bool(p > 0.01)}


def cross_correlation(u: np.ndarray, eps: np.ndarray, lags: int = 20) -> dict:
    """Correlation of the input increments (pre-whitened by an AR(2)) with the
    residual `eps` at positive lags only (input leads residual): in closed loop lag 0
    and negative lags reflect the feedback. 99 % band $\\pm 2.58/\\sqrt{N}$."""
    du, _ = ar_whiten(np.diff(u, prepend=u[0]), 2)
    e = eps - eps.mean()
    du = du - du.mean()
    n = len(e)
    den = math.sqrt(float(np.dot(du, du)) * float(np.dot(e, e))) or 1.0
    r = np.array([np.dot(e[k:], du[: n - k]) / den for k in range(1, lags + 1)])
    band = Z99 / math.sqrt(n)
    out = np.flatnonzero(np.abs(r) > band) + 1
    # at 99 % about one lag in a hundred leaves the band by chance: one is allowed
    return {"band": round(band, 5), "max_abs": round(float(np.max(np.abs(r))), 5),
            "lags_outside": out.tolist(), "passes": bool(len(out) <= max(1, lags // 50))}


def model_error_model(u: np.ndarray, eps: np.ndarray, taps: int = 20, nfreq: int = 64) -> dict:
    """FIR model from the (centred) input to the residual, by least squares, and the
    frequencies where its gain leaves the 99 % confidence band (delta method on the
    coefficient covariance)."""
    u = np.asarray(u, float) - np.mean(u)
    n = len(eps)
    X = np.stack([np.concatenate([np.zeros(k), u[: n - k]]) for k in range(1, taps + 1)], axis=1)
    Q, R = np.linalg.qr(X)
    g = np.linalg.solve(R, Q.T @ eps)
    res = eps - X @ g
    s2 = float(np.dot(res, res)) / max(n - taps, 1)
    Rinv = np.linalg.inv(R)
    cov = s2 * Rinv @ Rinv.T
    w = np.linspace(0, np.pi, nfreq + 1)[1:]
    E = np.exp(-1j * np.outer(w, np.arange(1, taps + 1)))
    G = E @ g
    # variance of |G| along its direction (delta method)
    dirn = np.conj(G) / np.maximum(np.abs(G), 1e-300)
    J = np.real(dirn[:, None] * E)
    sd = np.sqrt(np.maximum(np.einsum("fi,ij,fj->f", J, cov, J), 0.0))
    out = np.abs(G) > Z99 * sd
    return {"frequencies_outside": [round(float(v), 4) for v in w[out]],
            "fraction_outside": round(float(out.mean()), 4),
            "passes": bool(out.mean() <= 0.05)}


def spectrum_lines(z: np.ndarray, seg: int = 256) -> dict:
    """Welch spectrum of `z` and its narrow lines: bins above a running median by more
    than the 99 % quantile of a chi-squared(2K)/2K ratio for K averaged segments."""
    z = np.asarray(z, float) - np.mean(z)
    n = len(z)
    seg = int(min(seg, max(32, 2 ** int(math.log2(max(n // 4, 32))))))
    step = seg // 2
    win = np.hanning(seg)
    segs = [z[s : s + seg] for s in range(0, n - seg + 1, step)]
    P = np.mean([np.abs(np.fft.rfft(win * (s - s.mean()))) ** 2 for s in segs], axis=0) / np.sum(win**2)
    f = np.fft.rfftfreq(seg)  # cycles per sample
    k = len(segs)
    half = 4
    med = np.array([np.median(P[max(1, i - half) : i + half + 1]) for i in range(len(P))])
    # 99 % quantile of chi2(2k)/(2k) via Wilson-Hilferty
    nu = 2 * k
    q99 = (1 - 2 / (9 * nu) + Z99 * math.sqrt(2 / (9 * nu))) ** 3
    ratio = P / np.maximum(med, 1e-300)
    peaks = [i for i in range(2, len(P) - 1) if ratio[i] > 3 * q99 and P[i] >= P[i - 1] and P[i] >= P[i + 1]]
    peaks.sort(key=lambda i: -P[i])
    lines = [{"period_samples": round(1 / f[i], 2), "frequency": round(float(f[i]), 5),
              "power_ratio": round(float(ratio[i]), 2)} for i in peaks[:3]]
    lowfreq = float(np.sum(P[1:4]) / max(np.sum(P[1:]), 1e-300))
    return {"frequency": f, "power": P, "lines": lines, "narrow": bool(lines), "low_frequency_share": round(lowfreq, 4)}


def _circular_pvalue(stat_fn, indicator: np.ndarray, e2: np.ndarray, rng, shifts: int = 199) -> float:
    obs = stat_fn(indicator, e2)
    n = len(e2)
    ks = rng.integers(n // 10, n - n // 10, shifts)
    null = np.array([stat_fn(np.roll(indicator, k), e2) for k in ks])
    return float((1 + np.sum(null >= obs)) / (shifts + 1))


def segment_power(u: np.ndarray, eps: np.ndarray, seed: int = 0, after: int = 10) -> list[dict]:
    """Residual power in segments defined from past samples only (after an OP
    reversal, after a large move, near the OP range's ends, by OP level and by
    direction), each against the rest by a circular-shift permutation test (which
    keeps the residual's autocorrelation)."""
    u = np.asarray(u, float)
    e2 = (np.asarray(eps, float) - np.mean(eps)) ** 2
    n = len(u)
    du = np.diff(u, prepend=u[0])
    sgn = np.sign(du)
    last = np.zeros(n)
    cur = 0.0
    for t in range(n):  # last non-zero direction seen up to t - 1 (past only)
        last[t] = cur
        if sgn[t] != 0:
            cur = sgn[t]
    rev = (sgn != 0) & (last != 0) & (sgn != last)
    idx = np.flatnonzero(rev)
    after_rev = np.zeros(n, bool)
    for i in idx:
        after_rev[i : i + after] = True
    big = np.abs(du) > np.quantile(np.abs(du), 0.9)
    after_big = np.zeros(n, bool)
    for i in np.flatnonzero(big):
        after_big[i : i + after] = True
    lo, hi = np.quantile(u, [0.05, 0.95])
    segments = {
        "after_reversal": after_rev,
        "after_large_move": after_big,
        "near_high_limit": u >= hi,
        "near_low_limit": u <= lo,
        "op_low_third": u <= np.quantile(u, 1 / 3),
        "op_high_third": u >= np.quantile(u, 2 / 3),
        "moving_up": last > 0,
        "moving_down": last < 0,
    }

    def ratio(ind, e):
        a, b = e[ind], e[~ind]
        return float(a.mean() / max(b.mean(), 1e-300)) if 0 < ind.sum() < n else 1.0

    rng = np.random.default_rng(seed)
    out = []
    for name, ind in segments.items():
        ind = np.asarray(ind, bool)
        if ind.sum() < 20 or ind.sum() > n - 20:
            continue
        r = ratio(ind, e2)
        p = _circular_pvalue(ratio, ind, e2, rng)
        out.append({"segment": name, "power_ratio": round(r, 3), "p_value": p, "significant": bool(p <= 0.01)})
    return out


def time_windows(eps: np.ndarray, window: int = 100, start: int = 0) -> list[list[int]]:
    """Windows whose residual power exceeds the 99 % band of a chi-squared with
    `window` degrees of freedom scaled by the median window power (merged)."""
    e2 = (np.asarray(eps, float) - np.mean(eps)) ** 2
    n = len(e2)
    if n < 2 * window:
        return []
    pw = np.convolve(e2, np.ones(window) / window, mode="valid")
    base = np.median(pw)
    nu = window / 10  # residual autocorrelation lowers the effective degrees of freedom
    q = (1 - 2 / (9 * nu) + Z99 * math.sqrt(2 / (9 * nu))) ** 3
    hot = pw > base * q
    wins, t = [], 0
    while t < len(hot):
        if hot[t]:
            s = t
            while t < len(hot) and hot[t]:
                t += 1
            wins.append([start + s, start + t + window - 1])
        t += 1
    return wins[:10]


def op_ranges(u: np.ndarray, eps: np.ndarray, bins: int = 5) -> list[dict]:
    """Residual power by OP level (quantile bins), relative to the overall mean."""
    u = np.asarray(u, float)
    e2 = (np.asarray(eps, float) - np.mean(eps)) ** 2
    edges = np.quantile(u, np.linspace(0, 1, bins + 1))
    m = e2.mean() or 1.0
    out = []
    for i in range(bins):
        sel = (u >= edges[i]) & (u <= edges[i + 1])
        if sel.sum():
            out.append({"op_range": [round(float(edges[i]), 3), round(float(edges[i + 1]), 3)],
                        "power_ratio": round(float(e2[sel].mean() / m), 3)})
    return out


def locate(u: np.ndarray, z: np.ndarray, *, start: int = 0, seed: int = 0) -> dict:
    """All the locating tests on the OP `u` and simulation residual `z` of one record
    (typically its estimation part, beginning at sample `start`)."""
    eps, _ = ar_whiten(z, 2)
    spec = spectrum_lines(z)
    return {
        "whiteness": whiteness(eps),
        "cross_correlation": cross_correlation(u, eps),
        "model_error": model_error_model(u, eps),
        "spectrum": {k: spec[k] for k in ("lines", "narrow", "low_frequency_share")},
        "segments": segment_power(u, eps, seed=seed),
        "time_windows": time_windows(z, start=start),
        "op_ranges": op_ranges(u, eps),
    }
