r"""The stiction verdict of a fitted loop: `stiction`, `no_stiction` or
`inconclusive`, a calibrated probability, and the cause of a loop that is not sticky.

A plant record is not a simulation. It is short, it changes regime (setpoint moves,
load changes), its process may integrate, and its historian may have compressed it.
So no single number decides; the verdict weighs several kinds of evidence, each
robust to a different failure, and says `inconclusive` where the data cannot show a
valve at all.

**Evidence.**

1. *Model-based*: [`jaxstiction.estimate`][] fits a Kano valve and two nulls (a
   linear valve, a deadband), each with a Box–Jenkins linear part of the same
   structure. Their held-out gains in simulation (trend-free: a quadratic fitted on
   each scored part is removed, so a slow drift no model can simulate neither
   swamps nor tilts the comparison) and in `prediction_horizon`-step prediction,
   on the held-out last third and on the estimation samples, and the fitted band
   S as a fraction of the OP range. Where either fitted model's simulation has run
   away (`runaway`), the gains are left out and the band alone stays.
   `model_wins` is the old rule on these alone
   (the Kano valve beats the linear one by `min_gain` points on both parts, in
   simulation or, for a band of `prediction_band`, in prediction).
2. *Blocked cross-validation* (`crossval`): the record cut into
   `crossval_folds` blocks; each block predicted `crossval_horizon` samples ahead
   by cheap ARX models fitted on the other blocks, driven by a Kano valve and by a
   linear valve. Not one split, so one regime change cannot decide it; k-step
   prediction, so a slow wander cannot.
3. *Data-driven indicators* (`indicators`), the tests practitioners trust: the
   dominant oscillation's period, regularity (Thornhill et al. 2003) and share of
   the error's power; the phase between OP and the error at that period (Horch
   1999: odd cross-correlation for a sticky valve); the triangular-against-
   sinusoidal shape of OP's and PV's half-cycles (He et al. 2007); the
   bicoherence's non-Gaussianity (Choudhury et al. 2004); the share of OP's travel
   made while PV stands still (the PV–OP plot's flat tops). A record of more than
   `segment` real samples (the longest the calibration has seen) is read in
   segments: over days of data a slow swing can carry more power than a valve's
   fast limit cycle, and a whole-record periodogram would read the swing. The
   dominant period and its share come from the segments' averaged periodogram
   (Welch), every other indicator is the median over the segments of its value at
   that period, and `periods` counts the periods in the whole record.
4. *The limit cycle* (`limit_cycle`), reported beside the verdict: the fitted Kano
   model, and the same model with its valve repaired, closed again around the PI
   identified from the record, without noise. Does the fitted valve make the
   recorded oscillation (amplitude and period) where a repaired one would not? It
   is not weighed in the probability: as one more feature it moved the simulated
   fleet's check seeds by less than a point and lost a sticky plant recording left
   out (`benchmarks/calibrate_probability.py --limit-cycle`; the results page has
   the figures).

The error is `SP − PV` when the record carries a setpoint, else `−PV`.

**Probability.** The evidence becomes a feature vector (`features`, `FEATURES`)
and a logistic model, calibrated on a simulated realistic fleet and on labelled
real records (`jaxstiction.internal.CALIBRATION`, from
`benchmarks/calibrate_probability.py`), turns it into `probability`: the
probability at even prior odds (sticky and healthy loops weighed the same in the
fit), so that `threshold` 0.5 is the cut that maximises balanced accuracy. The
shipped calibration weighs the indicators only and gives the model-based gains,
the cross-validation and the band no weight: fitted on simulated loops alone, it
judges the labelled plant recordings at 0.94 (balanced accuracy, each valve left
out) with the indicators and at 0.65 with every feature; the model-based evidence
does not carry from simulated loops to real ones. That evidence still decides
under setpoint moves (the gate, below), and gives the band, the slip and the cause.

**Gate** (`gate`): a record whose PV is frozen, whose OP sits at a stop, or which
the historian compressed into flat runs is `inconclusive` whatever the evidence
says. A record whose setpoint moves carry most of PV's variance, or with fewer
than `min_periods` periods of any oscillation, is `inconclusive` unless the
probability calls it sticky. Under setpoint moves the indicators look for a cycle
that the setpoint's answers hide, so there the model-based test may call it sticky
as well: `model_wins`, with a Kano model that simulates the held-out PV well
(`setpoint_fitness`) and a band of at least `setpoint_band` of the OP range.

**Verdict.** `stiction` when the gate lets the loop through and the probability is
at least `threshold` (or, under setpoint moves, the model-based test above says
so); `no_stiction` when it is below and nothing gates the loop;
`inconclusive` otherwise. `stiction_detected` is `verdict == stiction`.

**Slip and cause.** A sticky valve is one with a band S (deadband + stickband) and
a slip jump J ≥ 0; `slip_identified` says the Kano valve also beats a deadband of
its width by `min_slip_gain` points (J = 0 cannot tell stickband from backlash). A
loop that is not sticky gets a cause: `external_oscillation` when the linear
valve's residual holds a narrow spectral line with more than `oscillation` of its
power (a periodic disturbance from elsewhere), else `none`.

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
from .calibration import CALIBRATION
from .crossval import crossval_gain
from .gate import gate_measures, gate_reason, GateMeasures, GATES, HARD, hard_checks
from .indicators import Indicators, indicators
from .limitcycle import limit_cycle, LimitCycle
from .probability import Calibration
from .settings import VerdictSettings


CAUSES = ("none", "stiction", "external_oscillation")
VERDICTS = ("no_stiction", "stiction", "inconclusive")  # `Verdict.verdict` indexes this

# The features of the probability, in order; `features` computes them.
FEATURES = ("horch", "log_regularity", "share", "shape_op", "shape_pv", "stuck_pv", "ngi", "crossval",
            "evidence", "evidence_prediction", "evidence_estimation", "band")


class Verdict(eqx.Module):
    """Result of [`jaxstiction.verdict`][] (arrays; a leading axis when batched).

    - `verdict`: an index into `VERDICTS` (`no_stiction`, `stiction`,
      `inconclusive`); `stiction_detected`: `verdict == stiction`;
      `probability`: the calibrated stiction probability; `gate`: an index into
      `GATES` (`ok` or why the data cannot show stiction); `gate_measures`: what
      the gate measured.
    - `cause`: an index into `CAUSES` (`none`, `stiction`, `external_oscillation`);
      `slip_identified`: the sticky valve's slip jump is seen in the data (else a
      deadband of its width fits as well).
    - `indicators`: the data-driven indicators (an `Indicators`);
      `crossval`: per fold, the share (%) of the linear valve's held-out k-step
      prediction error that a Kano valve removes.
    - `features`: the probability's inputs (`FEATURES`, in order).
    - `limit_cycle`: the fitted loop closed again around the identified controller
      (a `LimitCycle`: amplitudes, periods and the reproduction score, NaN where the
      fit is not usable or the check cannot judge).
    - `model_wins`: the model-based test alone (see the module notes).
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
      the threshold at the same period.
    """

    verdict: Int[Array, ""]
    stiction_detected: Bool[Array, ""]
    probability: Float[Array, ""]
    gate: Int[Array, ""]
    gate_measures: GateMeasures
    cause: Int[Array, ""]
    slip_identified: Bool[Array, ""]
    indicators: Indicators
    crossval: Float[Array, " folds"]
    features: Float[Array, " features"]
    limit_cycle: LimitCycle
    model_wins: Bool[Array, ""]
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


def features(ind: Indicators, crossval, evidence, evidence_prediction, evidence_estimation, band):
    """The probability's feature vector (`FEATURES`, in order) from the evidence of
    one loop: each indicator and gain on a bounded scale (a missing one at its
    uninformative value), so that no single wild number decides."""

    def clip(x, lo, hi, missing=0.0):
        return jnp.clip(jnp.where(jnp.isfinite(x), x, missing), lo, hi)

    return jnp.stack([
        clip(ind.horch, 0.0, 1.0, 0.5),
        jnp.log(clip(ind.regularity, 0.05, 100.0, 0.05)),
        clip(ind.share, 0.0, 1.0),
        clip(ind.shape_op, 0.0, 1.0, 0.5),
        clip(ind.shape_pv, 0.0, 1.0, 0.5),
        clip(ind.stuck_pv, 0.0, 1.0),
        clip(ind.ngi, -0.2, 0.5),
        clip(jnp.median(crossval), -30.0, 30.0) / 10.0,
        clip(evidence, -20.0, 20.0) / 10.0,
        clip(evidence_prediction, -20.0, 20.0) / 10.0,
        clip(evidence_estimation, -20.0, 20.0) / 10.0,
        clip(band, 0.0, 1.5),
    ])


def gate(g: GateMeasures, ind: Indicators, settings: VerdictSettings) -> Int[Array, ""]:
    """The gate's code (an index into `GATES`) from its measures and the
    indicators: the first check the loop fails, in the order of `GATES`."""
    few = ~jnp.isfinite(ind.period) | (ind.periods < settings.min_periods)
    checks = [*hard_checks(g, settings), g.setpoint_share > settings.max_setpoint_share, few]
    code = jnp.asarray(0, jnp.int32)
    for k, failed in reversed(list(enumerate(checks, start=1))):
        code = jnp.where(failed, k, code)
    return code


def decide(judged, code, probability, model_wins, fitness, band, settings: VerdictSettings) -> Int[Array, ""]:
    """The verdict (an index into `VERDICTS`) from the gate's `code`, the
    `probability` and the model-based test (`model_wins`, with the Kano model's
    held-out simulation `fitness` (%) and its `band` as a fraction of the OP range);
    `judged`: the fit left models to judge. See the module notes."""
    hard = jnp.zeros(jnp.shape(code), bool)
    for name in HARD:
        hard = hard | (code == GATES.index(name))
    # under setpoint moves the model-based test decides too, where the Kano model
    # explains the setpoint's answers and its band is a sizeable part of OP's travel
    by_model = ((code == GATES.index("setpoint_moves")) & model_wins
                & (fitness >= settings.setpoint_fitness) & (band >= settings.setpoint_band))
    sticky = judged & ~hard & ((probability >= settings.threshold) | by_model)
    conclusive = judged & ~hard & (sticky | (code == 0))
    return jnp.where(sticky, 1, jnp.where(conclusive, 0, 2)).astype(jnp.int32)


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


def runaway(fit, settings: VerdictSettings = VerdictSettings()) -> Bool[Array, ""]:
    """True where the fitted Kano or linear-valve model's simulation has run away:
    its fitness on the record is not finite or below `settings.runaway_fitness`. A
    simulation that has run away says nothing about the valve, and whether it ends
    at 1e30 or overflows depends on rounding, so both are treated alike."""
    bad = jnp.zeros(jnp.shape(fit.fitness_physical), bool)
    for f in (fit.fitness_physical, fit.fitness_linear):
        bad = bad | ~jnp.isfinite(f) | (f < settings.runaway_fitness)
    return bad


def usable(result) -> Bool[Array, ""]:
    """False for the data codes of [`jaxstiction.RESULTS`][] (too short, constant OP
    or PV, NaN/inf): a solver code (a budgeted fit that did not converge) still
    leaves fitted models to judge."""
    bad = jnp.zeros(jnp.shape(result._value), bool)
    for name in DATA_CODES:
        bad = bad | (result == getattr(RESULTS, name))
    return ~bad


@eqx.filter_jit  # its scored simulation and predictions cost seconds run eagerly
def verdict(fit, loop: Loop, settings: VerdictSettings = VerdictSettings(),
            calibration: Calibration = CALIBRATION) -> Verdict:
    """The stiction verdict and cause of one loop from its
    [`jaxstiction.LoopFit`][] (see the module notes). `loop.sp`, when recorded,
    gives the control error; `calibration`: the probability's coefficients. Pure
    and jitted; vmap it with `estimate`."""
    slip = fit.fitness_physical - fit.fitness_deadband
    slip_est = fit.fitness_physical_estimation - fit.fitness_deadband_estimation
    span = fit.op_range[1] - fit.op_range[0]
    band = fit.S / jnp.where(span > 0, span, 1.0)
    judged = usable(fit.result)
    ok = judged & ~runaway(fit, settings)  # the model-based evidence means something
    op = jnp.where(loop.mask > 0, loop.op, 0.0)
    pv = jnp.where(loop.mask > 0, loop.pv, 0.0)
    sp = loop.setpoint
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
    model_wins = ok & (band >= settings.min_band) & ~persists & (
        wins(gain, gain_est) | (wins(*pred) & (band >= settings.prediction_band)))

    ind = indicators(op, pv, sp, loop.mask, settings.segment)
    cv = crossval_gain(op, pv, loop.mask, folds=settings.crossval_folds, horizon=settings.crossval_horizon)
    nan = jnp.asarray(jnp.nan, op.dtype)
    x = features(ind, cv, jnp.where(ok, gain, nan), jnp.where(ok, pred[0], nan), jnp.where(ok, gain_est, nan),
                 jnp.where(judged, band, nan))
    cycle = limit_cycle(fit, op, pv, sp, loop.mask, segment=settings.segment)
    cycle = eqx.tree_at(lambda c: c.reproduction, cycle, jnp.where(ok, cycle.reproduction, nan))
    probability = calibration.probability(x)
    measures = gate_measures(op, pv, sp, loop.mask)
    code = gate(measures, ind, settings)
    which = decide(judged, code, probability, model_wins, fit.fitness_physical, band, settings)
    sticky = which == 1
    slips = jnp.maximum(slip, slip_est) > settings.min_slip_gain
    external = ok & (share > settings.oscillation)
    cause = jnp.where(sticky, 1, jnp.where(external, 2, 0))
    return Verdict(
        verdict=which,
        stiction_detected=sticky,
        probability=probability,
        gate=code,
        gate_measures=measures,
        cause=cause.astype(jnp.int32),
        slip_identified=sticky & ok & slips,
        indicators=ind,
        crossval=cv,
        features=x,
        limit_cycle=cycle,
        model_wins=model_wins,
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


def verdict_reason(v: Verdict, settings: VerdictSettings = VerdictSettings()) -> str:
    """The one-line reason of one (unbatched) verdict's gate, "" when it passed: the
    text the screen and `diagnose` report, filled in from `v.gate_measures`."""
    g = v.gate_measures
    return gate_reason(int(v.gate), saturated=float(g.saturated), compressed=float(g.compressed),
                       setpoint_share=float(g.setpoint_share), min_periods=settings.min_periods)
