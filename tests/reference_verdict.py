"""Slow, plain-NumPy references of the stiction verdict's pieces (tests only): the
indicators, written out segment by segment and lag by lag, the ARX k-step
predictor as a plain recursion, and a logistic regression by Newton steps."""

import numpy as np


def detrend(x, degree=2):
    t = np.linspace(-1.0, 1.0, len(x))
    V = np.stack([t**k for k in range(degree + 1)], axis=1)
    coef, *_ = np.linalg.lstsq(V, x, rcond=None)
    return x - V @ coef


def autocorrelation(x):
    x = x - x.mean()
    n = len(x)
    return np.array([np.dot(x[: n - k], x[k:]) for k in range(n)]) / np.dot(x, x)


def periodogram(x, length, taper=False):
    """The periodogram of `x` (detrended, with `taper` times a Hann window,
    zero-padded to 4 × `length`), smoothed over nine bins, on its frequencies."""
    x = detrend(x) * (np.hanning(len(x)) if taper else 1.0)
    P = np.abs(np.fft.rfft(x, n=4 * length)) ** 2
    return np.arange(len(P)) / (4 * length), P, np.convolve(P, np.ones(9), mode="same")


def peak(f, P, smooth, count, min_period=4.0, min_periods=3.0, local=False, below=None):
    ok = (f >= min_periods / count) & (f <= 1 / min_period)
    if local:
        ok &= np.array([0 < i < len(smooth) - 1 and smooth[i - 1] <= smooth[i] >= smooth[i + 1]
                        for i in range(len(smooth))])
    k = np.argmax(np.where(ok, smooth, -1))
    j = np.arange(len(P))
    band = (3 * j >= 2 * k) & (2 * j <= 3 * k)
    total = P[1:].sum() if below is None else P[1:][f[1:] >= f[k] / below].sum()
    return 1 / f[k], P[band].sum() / total


def dominant_period(e, min_period=4.0, min_periods=3.0):
    return peak(*periodogram(e, len(e)), len(e), min_period, min_periods)


def oscillation(e, crossings=11, p0=None):
    if p0 is None:
        p0, share = dominant_period(e)
    else:
        share = np.nan
    r = autocorrelation(lowpass(e, p0, 3.0))
    z = []
    for k in range(len(r) - 2):  # the last lag, one product, is left out
        if (r[k] >= 0) != (r[k + 1] >= 0):
            z.append(k + r[k] / (r[k] - r[k + 1]))
            if len(z) == crossings:
                break
    if len(z) < 4:
        return np.nan, 0.0, share
    T = np.array([z[i + 2] - z[i] for i in range(len(z) - 2)])
    return T.mean(), T.mean() / (3 * T.std(ddof=1)), share


def segmented(op, pv, segment):
    """The indicators of a record cut into the fewest equal pieces of at most
    `segment` samples (`segment` must divide its length): the period from the
    pieces' averaged periodogram, the rest the median over the pieces."""
    n = len(pv)
    k = n // segment
    assert k * segment == n
    cut = lambda x: x.reshape(k, segment)  # noqa: E731
    ops, pvs = cut(op), cut(pv)
    spectra = [periodogram(-y, segment, taper=True) for y in pvs]
    f = spectra[0][0]
    p0, share = peak(f, np.mean([s[1] for s in spectra], axis=0), np.mean([s[2] for s in spectra], axis=0), segment,
                    local=True, below=3.0)
    rows = []
    for u, y in zip(ops, pvs):
        u, y = highpass(u, p0), highpass(y, p0)
        T, reg, _ = oscillation(-y, p0=p0)
        dy = np.concatenate([[0.0], np.diff(y)])
        rows.append(dict(period=T, regularity=reg, horch=horch_phase(u, -y, T), shape_op=shape_index(u, T),
                         shape_pv=shape_index(y, T), ngi=bicoherence(-y)[0], nli=bicoherence(-y)[1],
                         stuck_pv=stuck_share(u, y, T), stuck_dpv=stuck_share(u, dy, T)))
    out = {key: float(np.nanmedian([r[key] for r in rows])) for key in rows[0]}
    return dict(out, share=share, periods=n / out["period"])


def cycle_segmented(e, segment, min_periods=3.0):
    """`(amplitude, period)` of the oscillation in `e` cut into equal pieces of
    `segment` samples (`segment` must divide its length): the period and share from
    the pieces' averaged Hann-windowed periodogram, the amplitude sqrt(2 share) times
    the root mean square of the whole `e` high-passed at a third of that frequency."""
    k = len(e) // segment
    assert k * segment == len(e)
    spectra = [periodogram(x, segment, taper=True) for x in e.reshape(k, segment)]
    p0, share = peak(spectra[0][0], np.mean([s[1] for s in spectra], axis=0), np.mean([s[2] for s in spectra], axis=0),
                     segment, min_periods=min_periods, local=True, below=3.0)
    return np.sqrt(2 * share) * np.sqrt(np.mean(highpass(e, p0) ** 2)), p0


def horch_phase(op, e, period):
    u, x = detrend(op), detrend(e)
    t = np.arange(len(op))
    z = np.exp(-2j * np.pi * t / period)
    return abs(np.sin(np.angle(np.sum(u * z) * np.conj(np.sum(x * z)))))


def lowpass(x, period, harmonics=7.5):
    x = detrend(x)
    F = np.fft.rfft(x)
    F[np.fft.rfftfreq(len(x)) > harmonics / period] = 0
    return np.fft.irfft(F, n=len(x))


def highpass(x, period, below=3.0):
    x = detrend(x)
    F = np.fft.rfft(x)
    F[np.fft.rfftfreq(len(x)) < 1 / (below * period)] = 0
    return np.fft.irfft(F, n=len(x))


def shape_index(x, period, min_length=5):
    y = lowpass(x, period)
    s = y >= 0
    cuts = [i for i in range(1, len(y)) if s[i] != s[i - 1]]
    es = et = 0.0
    for a, b in zip(cuts[:-1], cuts[1:]):
        seg = y[a:b]
        L = len(seg)
        if L < min_length:
            continue
        tau = (np.arange(L) + 0.5) / L
        p = min(max((np.argmax(np.abs(seg)) + 0.5) / L, 0.05), 0.95)
        for basis, acc in ((np.sin(np.pi * tau), "s"), (np.where(tau < p, tau / p, (1 - tau) / (1 - p)), "t")):
            A = seg @ basis / (basis @ basis)
            sse = np.sum((seg - A * basis) ** 2)
            if acc == "s":
                es += sse
            else:
                et += sse
    return es / (es + et) if es + et > 0 else np.nan


def bicoherence(x, segment=64, chi2=5.991):
    x = detrend(x)
    x = x / np.sqrt(np.mean(x * x))
    step = segment // 2
    win = np.hanning(segment)
    segs = [x[k : k + segment] for k in range(0, len(x) - segment + 1, step)]
    X = [np.fft.fft(win * (s - s.mean())) for s in segs]
    K = len(X)
    M = segment // 2
    b2 = []
    for f1 in range(1, M):
        for f2 in range(1, f1 + 1):
            if f1 + f2 >= M:
                continue
            B = sum(Xk[f1] * Xk[f2] * np.conj(Xk[f1 + f2]) for Xk in X) / K
            d1 = sum(abs(Xk[f1] * Xk[f2]) ** 2 for Xk in X) / K
            d2 = sum(abs(Xk[f1 + f2]) ** 2 for Xk in X) / K
            b2.append(abs(B) ** 2 / (d1 * d2))
    b2 = np.array(b2)
    crit = chi2 / (2 * K)
    sig = b2[b2 > crit]
    ngi = (sig.mean() if sig.size else 0.0) - crit
    return ngi, abs(b2.max() - (b2.mean() + 2 * b2.std()))


def stuck_share(op, v, period, still=0.15):
    u, y = lowpass(op, period), lowpass(v, period)
    du, dv = np.abs(np.diff(u)), np.abs(np.diff(y))
    q = np.quantile(dv, 0.9)
    return du[dv < still * q].sum() / du.sum()


def kstep(theta, y, x, na, nb, d, k):
    """The ARX model's k-step prediction of every sample, by the plain recursion:
    for each t, iterate the model from the measured outputs up to t - k (samples
    before the record repeat its first one)."""
    a, b, c = theta[:na], theta[na:na + nb], theta[-1]

    def at(s, i):
        return s[max(i, 0)]

    out = np.empty(len(y))
    for t in range(len(y)):
        pred = {}
        for s in range(t - k + 1, t + 1):
            acc = c + sum(b[j] * at(x, s - d - j) for j in range(nb))
            for i in range(1, na + 1):
                acc += a[i - 1] * (pred[s - i] if s - i in pred else at(y, s - i))
            pred[s] = acc
        out[t] = pred[t]
    return out


def logistic(X, y, w, l2):
    """L2-penalised logistic regression on standardised features by Newton steps."""
    mean = np.average(X, axis=0, weights=w)
    scale = np.sqrt(np.average((X - mean) ** 2, axis=0, weights=w))
    Z = np.column_stack([np.ones(len(X)), (X - mean) / scale])
    pen = l2 * np.diag([0.0] + [1.0] * X.shape[1])
    theta = np.zeros(Z.shape[1])
    for _ in range(100):
        p = 1 / (1 + np.exp(-Z @ theta))
        H = Z.T @ (Z * (w * p * (1 - p))[:, None]) + pen
        theta = theta + np.linalg.solve(H, Z.T @ (w * (y - p)) - pen @ theta)
    return mean, scale, theta[1:], theta[0]
