"""Settings of [`jaxstiction.estimate`][] and the screen's presets of them.

A leaf: the estimator's stages, its result and the screen import their settings
from here, and nothing here imports them.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx

from .._checks import check_counts
from .._criteria import ScoreSettings


class SplineSettings(eqx.Module):
    """Static settings of the spline estimator (shapes), with the paper's defaults.

    **Arguments:**

    - `arx_order`: high-order ARX order $n$ (13).
    - `knot_counts`: candidate knot counts $m$ for FOE (22).
    - `max_order`: largest reduced order $l$ tried by ASYC (21).
    - `max_delay`: largest input delay (samples) tried in the reduction.
    - `relax_steps`: cap on relaxation sweeps; `compression`: `"qr"` or `"gram"`
      (faster, for noisy records only; see [`jaxstiction.internal.relax_problem`][]).
    - `welch_segment`: segment length of the spectral estimates in (18).
    - `polish`: run the output-error polish after the paper's steps.
    - `range_factor`: a candidate whose simulation leaves the estimation PV range by
      more than this many ranges is not chosen.
    """

    arx_order: int = eqx.field(static=True, default=10)
    knot_counts: tuple = eqx.field(static=True, default=(3, 4, 5, 6, 8, 10, 12))
    max_order: int = eqx.field(static=True, default=3)
    max_delay: int = eqx.field(static=True, default=3)
    relax_steps: int = eqx.field(static=True, default=300)
    compression: str = eqx.field(static=True, default="qr")
    welch_segment: int = eqx.field(static=True, default=128)
    polish: bool = eqx.field(static=True, default=True)
    polish_steps: int = eqx.field(static=True, default=60)
    range_factor: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        check_counts(self, positive=("arx_order", "max_order", "max_delay", "relax_steps", "welch_segment"),
                     nonnegative=("polish_steps",))
        if not self.knot_counts or any(isinstance(k, bool) or not isinstance(k, int) or k < 2
                                       for k in self.knot_counts):
            raise ValueError(f"`SplineSettings.knot_counts` must be whole numbers >= 2, got {self.knot_counts!r}")
        if self.compression not in ("qr", "gram"):
            raise ValueError(f"`SplineSettings.compression` must be 'qr' or 'gram', got {self.compression!r}")


class PhysicalSettings(eqx.Module):
    """Static settings of the physical (Kano) fit.

    - `num_S`, `num_J`: stage-1 grid; `S` spans 0 to `max_band` × OP range,
      `J` spans 0 to `S`.
    - `starts`: best stage-1 points refined on a `refine` × `refine` local grid.
    - `final`: points per axis of the output-error grid (stage 3, profile likelihood).
    - `interval_span`: the intervals of S and J also use a second `final` × `final`
      output-error grid around the same centre, this many times wider (0: none). The
      95 % region usually reaches past the first grid's edge, which alone gave
      intervals holding the truth on 21 (S) and 23 (J) of 30 `paper_sim` seeds.
    - `burn_in`: samples ignored after the model valve first moves (see
      `valve_from`); `init_count`: candidate stopping points per direction of the
      unknown initial valve state, tried in the line searches and the final stage.
    - `refine_S`: S points of the stage-2 grid; `polish_starts`, `line`, `rounds`:
      alternating fine line searches in S and J from that many stage-2 points.
    - `chunk`, `memory_budget`: grid points evaluated at once (at most `chunk`, and
      fewer when their regressors would exceed `memory_budget` bytes); the
      output-error fits of the final stage, too, run as many at once as fit in
      `memory_budget` (all 75 of the defaults on records up to ~3300 samples).
    - `arx_order`: order of the least-squares (ARX) linear part of the grid
      criterion. The noise is coloured, so an ARX criterion is biased; a high order
      approximates the Box-Jenkins model (the paper's argument for its order-10 ARX).
      At order 4 the grid preferred a wrong J (off by 0.5-1.7) on 3 of 20 `paper_sim`
      seeds; at 8, on 1 of 20, for ~20 % more search time.
    - `order`: order of the output-error linear part.
    - `max_delay`: delays 1..`max_delay` are tried.
    """

    num_S: int = eqx.field(static=True, default=61)
    num_J: int = eqx.field(static=True, default=11)
    max_band: float = eqx.field(static=True, default=1.0)
    arx_order: int = eqx.field(static=True, default=8)
    order: int = eqx.field(static=True, default=2)
    max_delay: int = eqx.field(static=True, default=3)
    starts: int = eqx.field(static=True, default=8)
    refine: int = eqx.field(static=True, default=21)
    refine_S: int = eqx.field(static=True, default=81)
    final: int = eqx.field(static=True, default=5)
    interval_span: float = eqx.field(static=True, default=4.0)
    oe_steps: int = eqx.field(static=True, default=40)
    chunk: int = eqx.field(static=True, default=64)
    memory_budget: int = eqx.field(static=True, default=100_000_000)
    init_count: int = eqx.field(static=True, default=5)
    polish_starts: int = eqx.field(static=True, default=3)
    line: int = eqx.field(static=True, default=41)
    rounds: int = eqx.field(static=True, default=3)
    burn_in: int = eqx.field(static=True, default=10)

    def __check_init__(self):
        check_counts(self, positive=("num_S", "num_J", "arx_order", "order", "max_delay", "starts", "refine",
                                     "refine_S", "final", "oe_steps", "chunk", "memory_budget", "init_count",
                                     "line"),
                     nonnegative=("polish_starts", "rounds", "burn_in"))
        if not self.max_band > 0 or not self.interval_span >= 0:
            raise ValueError("`PhysicalSettings.max_band` must be > 0 and `interval_span` >= 0, "
                             f"got {self.max_band!r} and {self.interval_span!r}")


class Settings(eqx.Module):
    """Settings of [`jaxstiction.estimate`][] (all static: they fix shapes).

    - `spline`: [`jaxstiction.SplineSettings`][]; `physical`:
      [`jaxstiction.PhysicalSettings`][]; `use_physical=False` skips the Kano model,
      `use_spline=False` the spline family and the paper's literal method (their
      fields are then NaN; the default of [`jaxstiction.ScreenSettings`][]).
    - `validate`: fraction of the real samples held out at the end and scored; 0
      scores on the estimation data (as the paper did for its industrial loop).
    - `robust_factor`: the robust direction threshold in OP-noise standard deviations.
    - `score`: how simulations are scored ([`jaxstiction.ScoreSettings`][]).
    """

    spline: SplineSettings = SplineSettings()
    physical: PhysicalSettings = PhysicalSettings()
    score: ScoreSettings = ScoreSettings()
    use_physical: bool = eqx.field(static=True, default=True)
    use_spline: bool = eqx.field(static=True, default=True)
    validate: float = eqx.field(static=True, default=1 / 3)
    robust_factor: float = eqx.field(static=True, default=3.0)

    def __check_init__(self):
        if not 0.0 <= self.validate < 1.0:
            raise ValueError(f"`validate` must be in [0, 1), got {self.validate}")
        if not (self.use_spline or self.use_physical):
            raise ValueError("`use_spline` and `use_physical` cannot both be False: no model family left")

    def with_max_delay(self, n: int) -> Settings:
        """A copy whose spline and physical fits (and the verdict's nulls) try input
        delays of 1 to `n` samples instead of 1 to 3: for a process whose dead time is
        longer than 3 samples. The search's cost grows with `n`."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"`max_delay` must be a positive whole number of samples, got {n!r}")
        return dataclasses.replace(self, spline=dataclasses.replace(self.spline, max_delay=n),
                                   physical=dataclasses.replace(self.physical, max_delay=n))


# The screen's estimator: what the verdict needs (the Kano valve and its linear and
# deadband nulls), not the spline family, with a lighter Kano search (fewer stage-2
# starts, coarser refinement and line searches, fewer initial valve states). About
# 7x cheaper than `Settings()` on a 1500-sample loop (1.2-1.3 s against 8.8 s, one
# loop, this 2-core machine, before the step budget below). The scoring keeps its 40
# initial-state candidates: with 16, CHEM1's held-out Kano simulation starts in the
# wrong state and its verdict flips. Its grid criterion keeps the order-4 ARX of the
# calibration (see `verdict`), cheaper per grid point than the full estimator's order 8.
# The verdict reads no interval, so the wider interval grid is off.
#
# Its Box-Jenkins fits (18 in the final Kano stage, 8 for the nulls: ~60 % of a loop's
# cost at 40 steps) stop after 15 Levenberg-Marquardt steps. On 72 stage-3 fits of
# 1500-sample loops the simulation loss was then within 7e-5 (relative) of a 100-step
# fit. With 40 steps and with 15, the 60 calibration loops (seeds 0-11) got the same
# verdicts and causes, and the 14 ISDB loops the same `stiction_detected`; CHEM13's
# cause moved from deadband to external_oscillation. The held-out evidence of poorly
# excited loops moves with the budget (CHEM13: 372 -> -20 points; PAP4's band 0.9 ->
# 12.6 %): their fits have not converged at 40 or at 100 steps either.
#
# Two polish starts (line searches and the final Box-Jenkins grid from each of the
# two best stage-2 points; the Box-Jenkins simulation loss decides between them). The
# order-4 ARX criterion of stage 2 alone often ranks a spurious wide band first under
# setpoint moves: with one start, P1 (S 3, J 1) seeds 11, 15 and 16 and P10 seeds 15
# and 18 were fitted bands of 13-15 % (fitness 65-72 %, against 74-78 % at the
# truth's band), and the screen left them inconclusive. With two, four of those five
# find the true band, the screen calls 39 of P1's and P10's 40 records (seeds 0-19)
# sticky instead of 33, and on the plant development half every sticky recording's
# leave-one-valve-out probability rose except L74's (0.500 -> 0.495, with the
# probability then fitted at the records' own odds; at even odds, as now, 0.64).
# The second start costs 40 % more per loop: `benchmarks/fleet.py --small
# 8 --large 1024` measured 0.52 s per 1500-sample loop marginal, against 0.37 s with one.
SCREEN_ESTIMATE = Settings(
    use_spline=False,
    physical=PhysicalSettings(arx_order=4, starts=4, refine=11, refine_S=41, line=21, rounds=2, polish_starts=2,
                              init_count=3, final=3, oe_steps=15, interval_span=0.0),
)


# `jaxstiction screen --full-search`: the full estimator's Kano search (its order-8
# grid criterion, finer refinement, three polish starts, 40-step Box-Jenkins fits),
# still without the spline family; ~15 times the light profile's cost per loop. It
# pays on integrating (level) loops, where the light search often misses the band
# (README, *Verdict calibration*).
FULL_SEARCH_ESTIMATE = Settings(use_spline=False)
