"""Settings of [`jaxstiction.verdict`][]: the thresholds of the stiction verdict
(a leaf: the screen's and the diagnosis's settings import it)."""

from __future__ import annotations

import equinox as eqx

from .._checks import check_counts


class VerdictSettings(eqx.Module):
    """Thresholds of [`jaxstiction.verdict`][] (static).

    - `min_gain`: held-out simulation fitness (points) the Kano valve must gain over
      the linear valve; `min_gain_estimation`: the same on the estimation samples.
    - `min_band`: the smallest band `S` that counts, as a fraction of the OP range
      (a stiction limit cycle moves OP by about the band; a Kano fit with a band
      far below the OP's travel is mimicking something else).
    - `prediction_horizon` (samples), `prediction_band`: the second test (see the
      module notes): the Kano valve's gain in `prediction_horizon`-step prediction
      must exceed `min_gain` (held out) and `min_gain_estimation`, with a band of at
      least `prediction_band` × the OP range. `prediction_init_count`: candidate
      stopping points per direction in the search of the initial valve state before
      each prediction is scored.
    - `min_slip_gain`: points the Kano valve must gain over a deadband (J = 0), on
      the held-out or on the estimation samples, for the slip jump to count as
      identified (`slip_identified`; it does not change the verdict).
    - `oscillation`: share of the linear model's residual power in one narrow band
      (± one Fourier bin) above which the residual holds an external oscillation;
      `min_period`, `max_fraction`: lines with periods outside
      [`min_period`, `max_fraction` × record] samples are not oscillations.
    - `same_line`: relative difference of period within which the Kano model's
      strongest residual line is the linear model's (see the module notes).
    - `trend_degree`: the simulation gains are measured after a polynomial trend of
      this degree, fitted on each scored part, is removed from the PV and from the
      simulation error ([`jaxstiction.fitness_trend_free`][]; `None`: the plain
      fitness (34) that `estimate` scores). See the module notes.

    The thresholds above make the model-based test (`Verdict.model_wins`), one piece
    of evidence among several. The verdict itself:

    - `threshold`: the stiction probability at or above which a loop is called
      sticky. The probability is at even prior odds, so 0.5 weighs a missed sticky
      valve and a healthy one called sticky alike; lower it where a miss costs more.
    - the data-quality gate (see the verdict's module notes): `max_saturated`, the
      share of samples with OP at an extreme; `max_compressed`, the share of one
      signal's moves on which the other repeats its previous value, with no flat run
      longer than `max_flat_run` of the record (a longer one is a stuck valve's or a
      dead sensor's, not a historian's); `max_setpoint_share`,
      the setpoint's variance over PV's; `min_periods`, the periods of the dominant
      oscillation the record must hold.
    - under setpoint moves (the gate's `setpoint_moves`), the indicators look for a
      cycle the setpoint's answers hide, so the model-based test also decides: a loop
      is called sticky when `model_wins` holds, the Kano model simulates the held-out
      PV with a fitness of at least `setpoint_fitness` (%: the model explains the
      setpoint's answers, so the gain it measures is the valve's), and its band is
      at least `setpoint_band` of the OP range (a band comparable to the travel the
      setpoint moves make, not a small nonlinearity bending the fit).
    - `crossval_folds`, `crossval_horizon`: the blocked cross-validation's blocks
      and prediction horizon (samples).
    - `segment`: the indicators read a record of more than `segment` real samples
      in the fewest consecutive segments of equal length, at most `segment` each (a
      Welch-averaged periodogram for the dominant period, the median over the
      segments for the rest; see the module notes). The default is the longest
      record of the realistic fleet the probability is calibrated on, so a long
      record's indicators stay in the range the calibration has seen; `None`
      reads every record whole.
    - `runaway_fitness`: a fitted model whose simulation fitness (34) on the record
      is below this (%), or not finite, has run away (an unstable fit: its error
      is 10^4 times PV's spread at the default); its model-based evidence is then
      left out, and the verdict rests on the rest.
    """

    min_gain: float = eqx.field(static=True, default=1.0)
    min_gain_estimation: float = eqx.field(static=True, default=1.0)
    min_band: float = eqx.field(static=True, default=0.05)
    prediction_horizon: int = eqx.field(static=True, default=3)
    prediction_band: float = eqx.field(static=True, default=0.10)
    prediction_init_count: int = eqx.field(static=True, default=10)
    min_slip_gain: float = eqx.field(static=True, default=1.5)
    oscillation: float = eqx.field(static=True, default=0.25)
    min_period: float = eqx.field(static=True, default=3.0)
    max_fraction: float = eqx.field(static=True, default=0.25)
    same_line: float = eqx.field(static=True, default=0.1)
    trend_degree: int | None = eqx.field(static=True, default=2)
    threshold: float = eqx.field(static=True, default=0.5)
    max_saturated: float = eqx.field(static=True, default=0.3)
    max_compressed: float = eqx.field(static=True, default=0.5)
    max_flat_run: float = eqx.field(static=True, default=0.25)
    max_setpoint_share: float = eqx.field(static=True, default=0.5)
    min_periods: float = eqx.field(static=True, default=3.0)
    setpoint_fitness: float = eqx.field(static=True, default=50.0)
    setpoint_band: float = eqx.field(static=True, default=0.10)
    crossval_folds: int = eqx.field(static=True, default=4)
    crossval_horizon: int = eqx.field(static=True, default=5)
    runaway_fitness: float = eqx.field(static=True, default=-1e6)
    segment: int | None = eqx.field(static=True, default=3000)

    def __check_init__(self):
        check_counts(self, positive=("prediction_horizon", "prediction_init_count", "crossval_horizon"))
        if not (isinstance(self.crossval_folds, int) and self.crossval_folds >= 2):
            raise ValueError(f"`crossval_folds` must be a whole number of at least 2, got {self.crossval_folds!r}")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"`threshold` must be a probability in (0, 1), got {self.threshold!r}")
        if self.segment is not None:
            check_counts(self, positive=("segment",))
        if self.trend_degree is not None:
            check_counts(self, nonnegative=("trend_degree",))
