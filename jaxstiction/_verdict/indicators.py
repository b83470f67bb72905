r"""Data-driven stiction indicators: pure, vmappable JAX functions of one loop.

Each takes the loop's samples (`op`, `pv`, and the control error `e = SP - PV`
where a setpoint is recorded, else `-PV`) with a `mask` of real samples, and
returns plain scalars. They are the established tests practitioners use beside a
model:

- `oscillation`: the period and regularity of an
  oscillation, from the zero crossings of the autocorrelation (Thornhill, Huang &
  Zhang 2003). A regularity above 1 is a regular oscillation.
- `horch_phase`: the phase between OP and the
  error at the oscillation's frequency, as |sin φ| (Horch 1999: the cross-correlation
  of OP and PV is odd for a sticky valve in a self-regulating loop, even for an
  external or tuning oscillation).
- `shape_index`: triangular against sinusoidal
  half-cycles (He, Wang, Pottmann & Qin 2007): above 0.5 the signal is closer to a
  triangle (OP of a self-regulating loop with a sticky valve; PV of an integrating
  one), below 0.5 closer to a sine.
- `bicoherence`: the non-Gaussianity and
  non-linearity indices NGI and NLI of the squared bicoherence (Choudhury, Shah &
  Thornhill 2004): both above zero for a signal from a non-linear loop.
- `stuck_share`: the share of OP's travel during
  which the valve's footprint (PV in a self-regulating loop, ΔPV in an integrating
  one) stands still, the PV–OP and OP–ΔPV shapes made a number.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._linalg import lstsq


def _weighted_detrend(x, w, degree: int):
    """`x` minus its weighted least-squares polynomial of `degree` in time (0 where
    `w` is 0)."""
    n = x.shape[0]
    t = jnp.linspace(-1.0, 1.0, n, dtype=x.dtype)
    V = jnp.stack([t**k for k in range(degree + 1)], axis=1) * w[:, None]
    coef = lstsq(V, x * w)
    return w * (x - V @ coef / jnp.where(w > 0, w, 1.0))


def _count(w):
    return jnp.maximum(jnp.sum(w), 1.0)


def autocorrelation(x: Float[Array, " time"], mask: Float[Array, " time"]) -> Float[Array, " lag"]:
    """Biased autocorrelation of the real samples of `x` (mean removed), lags 0 to
    `len(x) - 1`; 1 at lag 0."""
    n = x.shape[0]
    w = (mask > 0).astype(x.dtype)
    x = w * (x - jnp.sum(w * x) / _count(w))
    F = jnp.fft.rfft(x, n=2 * n)
    r = jnp.fft.irfft(jnp.abs(F) ** 2, n=2 * n)[:n]
    return r / jnp.where(r[0] > 0, r[0], 1.0)


CROSSINGS = 11  # zero crossings of the autocorrelation read by `oscillation`


def _periodogram(e, mask, taper: bool = False):
    """`(f, P, smooth, count)`: the periodogram of `e` (a quadratic trend removed,
    zero-padded four times; with `taper`, times a Hann window over the real samples,
    which are then the first ones) on the frequencies `f`, smoothed over ± one
    natural bin, and the count of real samples."""
    n = e.shape[0]
    w = (mask > 0).astype(e.dtype)
    x = _weighted_detrend(e, w, 2)
    if taper:
        j = jnp.arange(n, dtype=e.dtype)
        x = x * (0.5 - 0.5 * jnp.cos(2 * jnp.pi * j / jnp.maximum(_count(w) - 1.0, 1.0)))
    pad = 4
    P = jnp.abs(jnp.fft.rfft(x, n=pad * n)) ** 2
    f = jnp.arange(P.shape[0], dtype=e.dtype) / (pad * n)
    smooth = jnp.convolve(P, jnp.ones((2 * pad + 1,), P.dtype), mode="same")
    return f, P, smooth, _count(w)


def _peak(f, P, smooth, count, min_period: float, min_periods: float, local: bool = False,
          below: float | None = None):
    """`(period, share)` of the sharpest line of `smooth` (see `dominant_period`);
    with `local`, of its highest local maximum (not the slope of a slower swing's
    lobe at the edge of the periods searched); with `below`, the share is of the
    power at frequencies of at least a `below`-th of the line's (as `highpass`
    leaves)."""
    ok = (f >= min_periods / count) & (f <= 1.0 / min_period)
    if local:
        ok = ok & (smooth >= jnp.roll(smooth, 1)) & (smooth >= jnp.roll(smooth, -1))
    k = jnp.argmax(jnp.where(ok, smooth, -1.0))
    f0 = f[k]
    j = jnp.arange(P.shape[0])
    band = (3 * j >= 2 * k) & (2 * j <= 3 * k)  # f0 / 1.5 <= f <= 1.5 f0, on whole bins
    total = P[1:] if below is None else jnp.where(f[1:] >= f0 / below, P[1:], 0.0)
    share = jnp.sum(jnp.where(band, P, 0.0)) / jnp.maximum(jnp.sum(total), 1e-300)
    return jnp.where(jnp.any(ok), 1.0 / jnp.maximum(f0, 1e-12), jnp.nan), jnp.clip(share, 0.0, 1.0)


def dominant_period(e, mask, min_period: float = 4.0, min_periods: float = 3.0):
    """`(period, share)`: the period (samples) of the strongest component of `e` (a
    quadratic trend removed) among periods from `min_period` to the record's length
    over `min_periods`, from its periodogram (zero-padded four times, smoothed over
    ± one natural bin), and the share of the signal's power within a factor 1.5 of
    that frequency."""
    return _peak(*_periodogram(e, mask), min_period, min_periods)


def cycle(e: Float[Array, " time"], w: Float[Array, " time"], min_periods: float = 3.0,
          segment: int | None = None):
    r"""`(amplitude, period)` of the oscillation in `e` over the samples with `w > 0`:
    the period of its strongest component (`dominant_period`, at least `min_periods`
    of them in the samples counted) and $\sqrt{2\,\text{share}}\;\sigma_e$, the
    amplitude of the sine that carries the power within a factor 1.5 of it.

    Over more than `segment` real samples (consecutive ones) the period and share
    are read as the indicators read them (`welch_period`), and $\sigma_e$ is that of
    `e` with the components slower than a third of the line's frequency removed
    (`highpass`), so a slow swing does not pass for the oscillation."""
    period, share = dominant_period(e, w, min_periods=min_periods)
    count = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(w * e) / count
    std = jnp.sqrt(jnp.sum(w * (e - mean) ** 2) / count)
    whole = (jnp.sqrt(2.0 * share) * std, period)
    if segment is None or e.shape[0] <= segment:
        return whole
    p0, share_long = welch_period(e, w, segment, min_periods)
    x = highpass(e, w, p0)
    std_long = jnp.sqrt(jnp.sum(w * x**2) / count)
    long = jnp.sum(w) > segment
    return tuple(jnp.where(long, a, b) for a, b in zip((jnp.sqrt(2.0 * share_long) * std_long, p0), whole))


def oscillation(e: Float[Array, " time"], mask: Float[Array, " time"]):
    """`(period, regularity, share)` of the oscillation in `e`.

    The dominant period (`dominant_period`) sets a low-pass at three times its
    frequency (`lowpass`), which keeps a limit cycle's shape and drops fast noise;
    the autocorrelation of what is left crosses zero at z_1 < z_2 < …, and each
    z_{i+2} − z_i estimates the period. The period is their mean and the regularity
    r = mean / (3 std) (Thornhill, Huang & Zhang 2003): an oscillation is regular
    when r > 1. Read from the first 11 crossings; fewer than 4 (under two periods)
    give a NaN period and r = 0. `share`: the share of the power of `e` within a
    factor 1.5 of the dominant frequency.
    """
    w = (mask > 0).astype(e.dtype)
    p0, share = dominant_period(e, w)
    return *regularity(e, w, p0), share


def regularity(e: Float[Array, " time"], mask: Float[Array, " time"], p0):
    """`(period, regularity)` of the oscillation in `e` whose dominant period is
    `p0` (see `oscillation`)."""
    w = (mask > 0).astype(e.dtype)
    n_real = _count(w)
    r = autocorrelation(lowpass(e, w, p0, harmonics=3.0), w)
    lags = jnp.arange(r.shape[0], dtype=e.dtype)
    valid = lags < n_real - 1
    s = r >= 0
    cross = (s[1:] != s[:-1]) & valid[1:]
    (idx,) = jnp.nonzero(cross, size=CROSSINGS, fill_value=-1)
    found = idx >= 0
    i = jnp.maximum(idx, 0)
    z = i + r[i] / jnp.where(r[i] != r[i + 1], r[i] - r[i + 1], 1.0)  # interpolated crossing
    T = z[2:] - z[:-2]
    ok = found[2:] & found[:-2]
    k = jnp.sum(ok)
    mean = jnp.sum(jnp.where(ok, T, 0.0)) / jnp.maximum(k, 1)
    var = jnp.sum(jnp.where(ok, (T - mean) ** 2, 0.0)) / jnp.maximum(k - 1, 1)
    enough = (jnp.sum(found) >= 4) & jnp.isfinite(p0)
    period = jnp.where(enough, mean, jnp.nan)
    return period, jnp.where(enough, mean / (3.0 * jnp.sqrt(var) + 1e-12 * mean), 0.0)


def horch_phase(op, e, mask, period):
    """|sin φ| of the phase φ between OP and the error `e` at the frequency 1/`period`
    (each with a quadratic trend removed): near 1 when their cross-correlation is
    odd (Horch's stiction pattern in a self-regulating loop), near 0 when it is even.
    NaN when the period is not finite."""
    w = (mask > 0).astype(op.dtype)
    u = _weighted_detrend(op, w, 2)
    x = _weighted_detrend(e, w, 2)
    t = jnp.arange(op.shape[0], dtype=op.dtype)
    f = 1.0 / jnp.where(jnp.isfinite(period) & (period > 0), period, 1.0)
    z = jnp.exp(-2j * jnp.pi * f * t)
    c = jnp.sum(u * z) * jnp.conj(jnp.sum(x * z))
    return jnp.where(jnp.isfinite(period), jnp.abs(jnp.sin(jnp.angle(c))), jnp.nan)


def _brickwall(x, mask, period, keep):
    """`x` (a quadratic trend removed) with only the frequencies `f` (cycles per
    sample) where `keep(f, period)` holds (an FFT brick wall); the whole detrended
    signal when `period` is not finite."""
    n = x.shape[0]
    w = (mask > 0).astype(x.dtype)
    x = _weighted_detrend(x, w, 2)
    F = jnp.fft.rfft(x)
    f = jnp.fft.rfftfreq(n)
    finite = jnp.isfinite(period) & (period > 0)
    return w * jnp.fft.irfft(jnp.where(~finite | keep(f, jnp.where(finite, period, 1.0)), F, 0.0), n=n)


def lowpass(x, mask, period, harmonics: float = 7.5):
    """`x` (a quadratic trend removed) with every component faster than `harmonics`
    times the oscillation's frequency 1/`period` removed (an FFT brick wall); the
    whole detrended signal when `period` is not finite."""
    return _brickwall(x, mask, period, lambda f, p: f <= harmonics / p)


def highpass(x, mask, period, below: float = 3.0):
    """`x` (a quadratic trend removed) with every component slower than a `below`-th
    of the oscillation's frequency 1/`period` removed (an FFT brick wall); the whole
    detrended signal when `period` is not finite."""
    return _brickwall(x, mask, period, lambda f, p: f >= 1.0 / (below * p))


def shape_index(x, mask, period, min_length: int = 5):
    """He et al. (2007)'s curve-fitting index: `x` is low-passed (`lowpass`) and cut
    at its zero crossings into half-cycles; each complete half-cycle of at least
    `min_length` samples is fitted by a half sine and by a triangle with its apex at
    the half-cycle's peak. Returns SSE_sine / (SSE_sine + SSE_triangle): above 0.5
    closer to triangles, below 0.5 closer to sines; NaN with no complete half-cycle.
    """
    n = x.shape[0]
    w = (mask > 0).astype(x.dtype)
    y = lowpass(x, w, period)
    s = y >= 0
    t = jnp.arange(n)
    change = jnp.concatenate([jnp.zeros((1,), bool), s[1:] != s[:-1]]) & (w > 0)
    seg = jnp.cumsum(change)  # half-cycle number
    last = jnp.max(jnp.where(w > 0, seg, 0))
    inner = (seg > 0) & (seg < last) & (w > 0)  # the first and last are incomplete
    seg = jnp.where(inner, seg, 0)
    ones = inner.astype(x.dtype)
    length = jax.ops.segment_sum(ones, seg, num_segments=n)
    start = jax.ops.segment_min(jnp.where(inner, t, n), seg, num_segments=n)
    peak = jax.ops.segment_max(jnp.where(inner, jnp.abs(y), -1.0), seg, num_segments=n)
    apex = jax.ops.segment_min(jnp.where(inner & (jnp.abs(y) >= peak[seg]), t, n), seg, num_segments=n)
    L = jnp.maximum(length[seg], 1.0)
    tau = (t - start[seg] + 0.5) / L
    p = jnp.clip((apex[seg] - start[seg] + 0.5) / L, 0.05, 0.95)
    sine = jnp.sin(jnp.pi * tau)
    tri = jnp.where(tau < p, tau / p, (1.0 - tau) / (1.0 - p))
    use = inner & (length[seg] >= min_length)

    def sse(b):
        xb = jax.ops.segment_sum(jnp.where(use, y * b, 0.0), seg, num_segments=n)
        bb = jax.ops.segment_sum(jnp.where(use, b * b, 0.0), seg, num_segments=n)
        xx = jax.ops.segment_sum(jnp.where(use, y * y, 0.0), seg, num_segments=n)
        return jnp.sum(jnp.where(bb > 0, xx - xb**2 / jnp.where(bb > 0, bb, 1.0), 0.0))

    es, et = sse(sine), sse(tri)
    return jnp.where(jnp.any(use) & (es + et > 0), es / jnp.where(es + et > 0, es + et, 1.0), jnp.nan)


def bicoherence(x, mask, segment: int = 64, alpha_chi2: float = 5.991):
    """`(ngi, nli)`: Choudhury, Shah & Thornhill (2004)'s non-Gaussianity and
    non-linearity indices of the squared bicoherence of `x` (a quadratic trend
    removed, unit variance), from Hann-windowed segments of `segment` samples
    overlapping by half (a segment with a padded sample is left out). NGI is the mean
    squared bicoherence of the significant bifrequencies minus the critical value
    χ²₂(0.95) / 2K (K segments); NLI = |max − (mean + 2 std)|. Both above 0: the
    loop behaves non-linearly."""
    n = x.shape[0]
    w = (mask > 0).astype(x.dtype)
    x = _weighted_detrend(x, w, 2)
    x = x / jnp.sqrt(jnp.sum(x * x) / _count(w) + 1e-300)
    step = segment // 2
    count = max(1, (n - segment) // step + 1)
    starts = jnp.arange(count) * step
    idx = starts[:, None] + jnp.arange(segment)[None, :]
    seg_ok = jnp.all(w[idx] > 0, axis=1).astype(x.dtype)
    win = jnp.hanning(segment).astype(x.dtype)
    xs = x[idx]
    xs = xs - jnp.mean(xs, axis=1, keepdims=True)
    X = jnp.fft.fft(xs * win, axis=1)
    M = segment // 2
    f1, f2 = np.meshgrid(np.arange(1, M), np.arange(1, M), indexing="ij")
    keep = (f2 <= f1) & (f1 + f2 < M)
    f1, f2 = f1[keep], f2[keep]  # the principal domain (static)
    K = jnp.maximum(jnp.sum(seg_ok), 1.0)
    X1, X2, X3 = X[:, f1], X[:, f2], X[:, f1 + f2]
    B = jnp.sum(seg_ok[:, None] * X1 * X2 * jnp.conj(X3), axis=0) / K
    d1 = jnp.sum(seg_ok[:, None] * jnp.abs(X1 * X2) ** 2, axis=0) / K
    d2 = jnp.sum(seg_ok[:, None] * jnp.abs(X3) ** 2, axis=0) / K
    b2 = jnp.abs(B) ** 2 / jnp.maximum(d1 * d2, 1e-300)
    crit = alpha_chi2 / (2.0 * K)
    sig = b2 > crit
    ngi = jnp.where(jnp.any(sig), jnp.sum(jnp.where(sig, b2, 0.0)) / jnp.maximum(jnp.sum(sig), 1), 0.0) - crit
    nli = jnp.abs(jnp.max(b2) - (jnp.mean(b2) + 2.0 * jnp.std(b2)))
    return ngi, nli


def stuck_share(op, v, mask, period, still: float = 0.15):
    """Share of OP's travel made while the valve's footprint `v` (PV in a
    self-regulating loop, ΔPV in an integrating one) stands still: both low-passed
    (`lowpass`), a sample of `v` stands still when its move is under `still` times
    the 90th percentile of its moves. A sticky valve's PV–OP plot has flat tops
    (OP moves, the valve does not): near or above 0.3; a linear loop's ellipse much
    less."""
    w = (mask > 0).astype(op.dtype)
    u = lowpass(op, w, period)
    y = lowpass(v, w, period)
    pair = (w[1:] > 0) & (w[:-1] > 0)
    du = jnp.where(pair, jnp.abs(jnp.diff(u)), 0.0)
    dv = jnp.abs(jnp.diff(y))
    q = jnp.nanquantile(jnp.where(pair, dv, jnp.nan), 0.9)
    stands = dv < still * q
    return jnp.sum(jnp.where(stands, du, 0.0)) / jnp.maximum(jnp.sum(du), 1e-300)


class Indicators(eqx.Module):
    """The indicators of one loop (arrays; a leading axis when batched).

    - `period` (samples), `regularity`, `share`: the dominant oscillation of the
      control error (`oscillation`); `periods`: how many of its periods the record
      holds.
    - `horch`: |sin φ| between OP and the error at that period (`horch_phase`).
    - `shape_op`, `shape_pv`: triangular against sinusoidal half-cycles of OP and of
      PV (`shape_index`).
    - `ngi`, `nli`: the error's bicoherence indices (`bicoherence`).
    - `stuck_pv`, `stuck_dpv`: share of OP's travel made while PV, or ΔPV, stands
      still (`stuck_share`).
    """

    period: Float[Array, ""]
    regularity: Float[Array, ""]
    share: Float[Array, ""]
    periods: Float[Array, ""]
    horch: Float[Array, ""]
    shape_op: Float[Array, ""]
    shape_pv: Float[Array, ""]
    ngi: Float[Array, ""]
    nli: Float[Array, ""]
    stuck_pv: Float[Array, ""]
    stuck_dpv: Float[Array, ""]


def control_error(pv, sp, mask):
    """`SP − PV` where a setpoint is recorded (`sp` finite on every real sample),
    else `−PV`: the error the controller acts on, up to a constant."""
    w = mask > 0
    has_sp = jnp.all(jnp.where(w, jnp.isfinite(sp), True))
    return jnp.where(has_sp, jnp.where(w, sp, 0.0) - pv, -pv)


def _at(op, pv, e, w, p0, ngi, nli) -> Indicators:
    """The indicators of one record whose dominant period is `p0`."""
    period, reg = regularity(e, w, p0)
    pair = jnp.concatenate([jnp.zeros((1,), w.dtype), w[1:] * w[:-1]])
    dpv = jnp.concatenate([jnp.zeros((1,), pv.dtype), jnp.diff(pv)]) * pair
    return Indicators(
        period=period, regularity=reg, share=jnp.zeros_like(reg), periods=_count(w) / period,
        horch=horch_phase(op, e, w, period), shape_op=shape_index(op, w, period), shape_pv=shape_index(pv, w, period),
        ngi=ngi, nli=nli, stuck_pv=stuck_share(op, pv, w, period), stuck_dpv=stuck_share(op, dpv, w, period))


def _whole(op, pv, e, w) -> Indicators:
    p0, share = dominant_period(e, w)
    ind = _at(op, pv, e, w, p0, *bicoherence(e, w))
    return eqx.tree_at(lambda i: i.share, ind, share)


def _cuts(w, segment: int):
    """`(lo, hi, used, k)`: the fewest consecutive segments of equal length, at most
    `segment` samples each, that cover the real samples (`w > 0`, consecutive): the
    i-th spans `lo[i]:hi[i]` where `used[i]`; `k` of them are used."""
    n = w.shape[0]
    count = _count(w)
    first = jnp.argmax(w > 0).astype(jnp.int32)
    k = jnp.ceil(count / segment)
    m = -(-n // segment)  # the most segments a record of n samples needs
    s = jnp.arange(m)
    lo = first + jnp.floor(s * count / k).astype(jnp.int32)
    hi = first + jnp.floor((s + 1) * count / k).astype(jnp.int32)
    return lo, hi, s < k, k


def _pieces(signals, w, lo, hi, used, segment: int):
    """The segments `lo:hi` (`_cuts`) of the rows of `signals` and of the weights
    `w`, each `segment` samples long with the weights 0 past its end."""
    stack = jnp.concatenate([signals, w[None]])
    stack = jnp.concatenate([stack, jnp.zeros((stack.shape[0], segment), stack.dtype)], axis=1)  # room for the last cut

    def take(a, b, on):
        piece = jax.lax.dynamic_slice(stack, (jnp.zeros_like(a), a), (stack.shape[0], segment))
        return piece[:-1], piece[-1] * (jnp.arange(segment) < jnp.where(on, b - a, 0))

    return jax.vmap(take)(lo, hi, used)


def _welch(es, ws, used, k, min_periods: float):
    """`(period, share)` of the line of the segments' averaged Hann-windowed
    periodogram (see `welch_period`)."""
    f, P, smooth, counts = jax.vmap(lambda x, ww: _periodogram(x, ww, taper=True))(es, ws)
    weight = used.astype(es.dtype)[:, None]
    P_mean, smooth_mean = (jnp.sum(weight * x, axis=0) / jnp.maximum(k, 1.0) for x in (P, smooth))
    return _peak(f[0], P_mean, smooth_mean, jnp.min(jnp.where(used, counts, jnp.inf)), 4.0, min_periods,
                 local=True, below=3.0)


def welch_period(e, w, segment: int, min_periods: float = 3.0):
    """`(period, share)` of the oscillation in `e`, its real samples (consecutive) cut
    into the fewest segments of equal length, at most `segment` each: the line of the
    segments' averaged Hann-windowed periodogram (Welch: the window keeps a slow
    swing's leakage off the line), which must be a local maximum (not the swing's
    lobe at the longest period searched, `min_periods` periods in a segment), and the
    share of the power left when the components slower than a third of the line's
    frequency are removed that lies within a factor 1.5 of it."""
    lo, hi, used, k = _cuts(w, segment)
    signals, ws = _pieces(e[None], w, lo, hi, used, segment)
    return _welch(signals[:, 0], ws, used, k, min_periods)


def _segmented(op, pv, e, w, segment: int) -> Indicators:
    """The indicators of a record longer than `segment` samples, read in the fewest
    consecutive segments of equal length (at most `segment` real samples each): the
    dominant period and its share from `welch_period`, every other indicator the
    median over the segments of its value at that period, with the components slower
    than a third of its frequency removed (`highpass`: a swing that fills a segment
    would otherwise set the zero crossings); `periods` counts the periods in the
    whole record."""
    lo, hi, used, k = _cuts(w, segment)
    signals, ws = _pieces(jnp.stack([op, pv, e]), w, lo, hi, used, segment)
    ops, pvs, es = signals[:, 0], signals[:, 1], signals[:, 2]
    p0, share = _welch(es, ws, used, k, 3.0)

    def one(u, y, x, ww):
        u, y, x = (highpass(v, ww, p0) for v in (u, y, x))
        return _at(u, y, x, ww, p0, *bicoherence(x, ww))

    each = jax.vmap(one)(ops, pvs, es, ws)
    median = jax.tree.map(lambda x: jnp.nanmedian(jnp.where(used, x, jnp.nan)), each)
    return eqx.tree_at(lambda i: (i.share, i.periods), median, (share, _count(w) / median.period))


def indicators(op, pv, sp, mask, segment: int | None = None) -> Indicators:
    """Every indicator of one loop (see `Indicators`); `sp` all NaN when no
    setpoint was recorded. A record of more than `segment` real samples is read in
    segments (see the verdict's module notes); `None`: whole. Pure and vmappable."""
    w = (mask > 0).astype(op.dtype)
    e = control_error(pv, sp, mask)
    whole = _whole(op, pv, e, w)
    if segment is None or op.shape[0] <= segment:
        return whole
    long = _count(w) > segment
    return jax.tree.map(lambda a, b: jnp.where(long, a, b), _segmented(op, pv, e, w, segment), whole)
