r"""The stiction verdict of a fitted loop, and its cause when it is not stiction.

A loop is called sticky when Kano's stiction model *beats a linear valve* on data it
was not fitted on: [`jaxstiction.estimate`][] fits both with a Box–Jenkins linear
part of the same structure (orders, delays tried), each refitted with its valve, so
the two differ by the valve and by what the linear part makes of it.
The apparent band alone is no test: every fit has one.

The Kano valve must win on the held-out and on the estimation samples, either

- in simulation (each part from an initial state estimated on its opening
  samples, a slow trend removed: see below), or
- in `prediction_horizon`-step-ahead prediction, for a band of at least
  `prediction_band` of the OP range. A sticky valve in a loop whose setpoint rarely
  moves holds the loop in a limit cycle; a simulation of it drifts out of phase
  with the recorded cycle over hundreds of samples and can lose to a linear valve's
  simulation (which predicts little more than the mean), while every slip still
  shows a few samples later. On the calibration loops with such setpoints the
  simulation test missed 10 of 24 sticky valves (seeds 0–23) and the prediction
  test found 9 of those 10. A tightly tuned linear loop also gains a few points of
  short-horizon prediction from a small Kano band (its fitted band was at most 8 %
  of the OP range there, those sticky valves' 17–35 %), hence the band bound
  (`benchmarks/calibrate_verdict.py`).

Both simulation gains are measured *trend-free*: a quadratic trend, fitted on each
scored part, is removed from the PV and from each model's simulation error before
the fitness (34) is taken ([`jaxstiction.fitness_trend_free`][],
`VerdictSettings.trend_degree`). A slow drift at the output (a random walk, a load
that wanders), which real loops often carry and no model from OP to PV can
simulate, otherwise sits in both errors: it swamps the valve's difference, and
through the two fits' different offsets and slow poles it tilts the comparison
either way. The valve's cycles and the loop's steps, faster than a few hundred
samples, are left. Formed on the drawn loops of seeds 0–23 (polynomial degrees 0–11
compared; degree 2 found 48 of 72 valve bands against the plain fitness's 43, false
alarms 5 either way) and checked unchanged on seeds 24–47 (44 against 40, false
alarms 4 against 3) and 48–71 (49 against 44, 3 against 5); on the paper's process
(seeds 0–47) the same 128 of 144 bands and no false alarm
(`benchmarks/calibrate_verdict.py`).

A sticky valve is one with a band S (deadband + stickband) and a slip jump
J ≥ 0; J = 0 is a valve that sticks without slipping, and the Kano model cannot tell
its stickband from a deadband (backlash). The slip is reported apart
(`slip_identified`: the Kano valve beats a deadband of about its width), not used to
clear the valve: on 12 simulated valves with a small slip (J/S 0.02–0.25) the
slip was identified on 5, although S and J were fitted well, and the J fitted to
pure deadbands spans the same J/S (0.02–0.27), so a rule "no visible slip, so
backlash" would miss sticky valves without naming backlash reliably
(`benchmarks/calibrate_verdict.py`).

A Kano valve that wins is still not called sticky when its own residual keeps the
oscillation of the linear valve's: a narrow line holding more than `oscillation` of
the residual power in both, at the same period (within `same_line`). A sticky
valve's limit cycle is what the Kano model explains; a line it leaves in place is a
disturbance from elsewhere, which a Kano valve with a band only mimics in part. The
loop's cause is then `external_oscillation`. Formed on the drawn loops of seeds
0-23 (one false alarm of six cleared, no valve band lost) and then checked, unchanged,
on seeds 24-47 (two of five false alarms cleared, none lost), 48-71 (five of ten
cleared, one band of 45 lost) and on the paper's process at seeds 0-47 (its one
false alarm cleared, none of 128 bands lost); it changes no ISDB verdict. A sticky
valve beside a strong external oscillation is the price: it is named the
oscillation. (The P10 scenario, Kano S 4, J 1 beside a sinusoid of amplitude 4 and
period 30, keeps its screen verdicts at seeds 0-5: its linear residual holds the
line at 6-10 % of its power.)

When the valve is not sticky, the cause of the loop's behaviour is named from what
the linear fit leaves:

- `external_oscillation`: the linear valve explains OP → PV, yet its residual holds
  a narrow spectral line: a periodic disturbance entering at the output (a loop
  oscillating from tight tuning is explained by the linear model and is `none`);
- `none`: nothing of the above.

The thresholds ([`jaxstiction.VerdictSettings`][]) were calibrated on simulated loops
with and without stiction and with its confounders (external oscillation, deadband,
tight tuning, noise alone): see `benchmarks/calibrate_verdict.py`.

Pure JAX: it vmaps with `estimate` over a batch of loops.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._criteria import predicted, ScoreSettings, simulate_scored
from .._estimate.estimate import estimation_parts
from .._estimate.result import RESULTS
from .._filters import fitness, fitness_trend_free
from .._loop import Loop
from .settings import VerdictSettings


CAUSES = ("none", "stiction", "external_oscillation")


class Verdict(eqx.Module):
    """Result of [`jaxstiction.verdict`][] (arrays; a leading axis when batched).

    - `stiction_detected`; `cause`: an index into `CAUSES` (`none`, `stiction`,
      `external_oscillation`); `slip_identified`: the sticky valve's slip jump is
      seen in the data (else a deadband of its width fits as well).
    - `evidence`: held-out simulation fitness gain of the Kano valve over the linear
      valve (points; trend removed, see `VerdictSettings.trend_degree`);
      `evidence_estimation`: the same on the estimation samples.
    - `evidence_prediction`, `evidence_prediction_estimation`: the same gains in
      `prediction_horizon`-step prediction.
    - `slip_evidence`, `slip_evidence_estimation`: the Kano valve's gain over a
      deadband (J = 0), in the plain fitness (34) that `estimate` scored.
    - `band_fraction`: Kano's S as a fraction of the OP range.
    - `oscillation`: share of the linear model's residual power in its strongest
      narrow band, at period `period` (samples); `oscillation_kano`, `period_kano`:
      the same for the Kano model's residual; `line_persists`: both hold a line above
      the threshold at the same period, so a winning Kano valve is not called sticky.
    """

    stiction_detected: Bool[Array, ""]
    cause: Int[Array, ""]
    slip_identified: Bool[Array, ""]
    evidence: Float[Array, ""]
    evidence_estimation: Float[Array, ""]
    evidence_prediction: Float[Array, ""]
    evidence_prediction_estimation: Float[Array, ""]
    slip_evidence: Float[Array, ""]
    slip_evidence_estimation: Float[Array, ""]
    band_fraction: Float[Array, ""]
    oscillation: Float[Array, ""]
    period: Float[Array, ""]
    oscillation_kano: Float[Array, ""]
    period_kano: Float[Array, ""]
    line_persists: Bool[Array, ""]


def residual_line(r, weights, min_period: float, max_fraction: float):
    """Share of the power of `r` (weighted samples only, mean removed) in its
    strongest narrow band of periods in [`min_period`, `max_fraction` × count], and
    that band's period (samples). A periodogram zero-padded 4 times; the band is ± one
    natural Fourier bin (± 4 padded bins)."""
    n = r.shape[0]
    count = jnp.maximum(jnp.sum(weights), 1.0)
    r = weights * (r - jnp.sum(weights * r) / count)
    pad = 4
    P = jnp.abs(jnp.fft.rfft(r, n=pad * n)) ** 2
    f = jnp.arange(P.shape[0]) / (pad * n)  # cycles per sample
    ok = (f >= 1.0 / (max_fraction * count)) & (f <= 1.0 / min_period)
    total = jnp.maximum(jnp.sum(P[1:]), 1e-300)
    band = jnp.convolve(P, jnp.ones((2 * pad + 1,), P.dtype), mode="same")
    band = jnp.where(ok, band, 0.0)
    k = jnp.argmax(band)
    share = band[k] / total
    return jnp.clip(share, 0.0, 1.0), 1.0 / jnp.maximum(f[k], 1e-12)


DATA_CODES = ("too_short", "constant_op", "constant_pv", "nonfinite_data")


def usable(result) -> Bool[Array, ""]:
    """False for the data codes of [`jaxstiction.RESULTS`][] (too short, constant OP
    or PV, NaN/inf): a solver code (a budgeted fit that did not converge) still
    leaves fitted models to judge."""
    bad = jnp.zeros(jnp.shape(result._value), bool)
    for name in DATA_CODES:
        bad = bad | (result == getattr(RESULTS, name))
    return ~bad


@eqx.filter_jit  # its scored simulation and predictions cost seconds run eagerly
def verdict(fit, loop: Loop, settings: VerdictSettings = VerdictSettings()) -> Verdict:
    """The stiction verdict and cause of one loop from its
    [`jaxstiction.LoopFit`][] (see the module notes). Pure and jitted; vmap it with
    `estimate`."""
    slip = fit.fitness_physical - fit.fitness_deadband
    slip_est = fit.fitness_physical_estimation - fit.fitness_deadband_estimation
    span = fit.op_range[1] - fit.op_range[0]
    band = fit.S / jnp.where(span > 0, span, 1.0)
    ok = usable(fit.result) & jnp.isfinite(fit.fitness_physical) & jnp.isfinite(fit.fitness_linear)
    op = jnp.where(loop.mask > 0, loop.op, 0.0)
    pv = jnp.where(loop.mask > 0, loop.pv, 0.0)
    w_est, w_val = estimation_parts(loop.mask, fit.n_estimation, fit.n_validation)
    if settings.trend_degree is None:
        gain = fit.fitness_physical - fit.fitness_linear
        gain_est = fit.fitness_physical_estimation - fit.fitness_linear_estimation
    else:
        # Each part simulated as `estimate` scored it, the trend then removed; one
        # simulation at a time in a `lax.map` (memory of one, as in `estimate`).
        def trend_free(mw):
            m, w = mw
            return fitness_trend_free(pv, simulate_scored(m, op, pv, w)[0], w, settings.trend_degree)

        pairs = [(fit.physical, w_val), (fit.linear, w_val), (fit.physical, w_est), (fit.linear, w_est)]
        tf = jax.lax.map(trend_free, jax.tree.map(lambda *x: jnp.stack(x), *pairs))
        gain, gain_est = tf[0] - tf[1], tf[2] - tf[3]
    # Each model's prediction over the whole record, from an initial state estimated
    # at its start, then scored on both parts. A k-step prediction forgets its start
    # within k samples of the valve's first move, so a coarse search of the initial
    # valve state does (the search is most of the cost).
    score = ScoreSettings(init_count=settings.prediction_init_count)
    k = settings.prediction_horizon
    fits = [[fitness(pv, p, w) for w in (w_val, w_est)]
            for p in (predicted(m, op, pv, loop.mask, k, score) for m in (fit.physical, fit.linear))]
    pred = (fits[0][0] - fits[1][0], fits[0][1] - fits[1][1])

    def wins(g, g_est):
        return jnp.isfinite(g) & (g > settings.min_gain) & (g_est > settings.min_gain_estimation)

    (share, period), (share_k, period_k) = (
        residual_line(pv - simulate_scored(m, op, pv, loop.mask)[0], loop.mask, settings.min_period,
                      settings.max_fraction) for m in (fit.linear, fit.physical))
    persists = (share > settings.oscillation) & (share_k > settings.oscillation) & (
        jnp.abs(period_k - period) <= settings.same_line * period)
    sticky = ok & (band >= settings.min_band) & ~persists & (
        wins(gain, gain_est) | (wins(*pred) & (band >= settings.prediction_band)))
    slips = jnp.maximum(slip, slip_est) > settings.min_slip_gain
    external = ok & (share > settings.oscillation)
    cause = jnp.where(sticky, 1, jnp.where(external, 2, 0))
    return Verdict(
        stiction_detected=sticky,
        cause=cause.astype(jnp.int32),
        slip_identified=sticky & slips,
        evidence=gain,
        evidence_estimation=gain_est,
        evidence_prediction=pred[0],
        evidence_prediction_estimation=pred[1],
        slip_evidence=slip,
        slip_evidence_estimation=slip_est,
        band_fraction=band,
        oscillation=share,
        period=period,
        oscillation_kano=share_k,
        period_kano=period_k,
        line_persists=ok & persists,
    )
