"""Settings of [`jaxstiction.whatif`][] and [`jaxstiction.compensate`][] (a leaf:
the room's modules import their settings from here, and nothing here imports them).
"""

from __future__ import annotations

import equinox as eqx

from .._checks import check_counts


class KnockerGrid(eqx.Module):
    """The knocker parameters [`jaxstiction.compensate`][] searches (static: they fix
    the grid's shape).

    - `amplitudes`: pulse amplitudes as multiples of the fitted band S (the OP step
      that moves a stuck valve either way is at most S), so one grid serves valves of
      any size;
    - `widths`: pulse widths, in samples;
    - `periods`: pulse periods, in samples (pairs with a period shorter than twice
      the width are left out: a knocker whose pulses touch is a bias, not a knock);
    - `reinforcement`: amplitudes, as multiples of S, of constant reinforcement (a
      bias of that size added to OP in the direction of its last move, every sample:
      the knocker with width and period 1; Ivan and Lakshminarayanan 2009), searched
      beside the knocks; `()` for knocks only.
    """

    amplitudes: tuple = eqx.field(static=True, default=(0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0, 1.3))
    widths: tuple = eqx.field(static=True, default=(1, 2, 3))
    periods: tuple = eqx.field(static=True, default=(2, 3, 4, 5, 6, 8, 10, 14, 20))
    reinforcement: tuple = eqx.field(static=True, default=(0.3, 0.4, 0.45, 0.5, 0.55, 0.6))

    def __check_init__(self):
        if not self.amplitudes or any(not (isinstance(a, (int, float)) and a > 0) for a in self.amplitudes):
            raise ValueError(f"`KnockerGrid.amplitudes` must be positive numbers, got {self.amplitudes!r}")
        if not isinstance(self.reinforcement, tuple) or any(
                isinstance(a, bool) or not (isinstance(a, (int, float)) and a > 0) for a in self.reinforcement):
            raise ValueError(f"`KnockerGrid.reinforcement` must be a tuple of positive numbers, got "
                             f"{self.reinforcement!r}")
        for name in ("widths", "periods"):
            v = getattr(self, name)
            if not v or any(isinstance(k, bool) or not isinstance(k, int) or k < 1 for k in v):
                raise ValueError(f"`KnockerGrid.{name}` must be whole numbers >= 1, got {v!r}")
        if not self.points():
            raise ValueError("`KnockerGrid` has no candidate: no (width, period) pair with period >= 2 x width "
                             "and no `reinforcement`")

    def points(self) -> tuple[tuple[float, int, int], ...]:
        """Every `(amplitude factor, width, period)` of the grid, the knocks first,
        then constant reinforcement (width and period 1)."""
        knocks = tuple((a, w, h) for a in self.amplitudes for w in self.widths for h in self.periods if h >= 2 * w)
        return knocks + self.reinforcement_points()

    def reinforcement_points(self) -> tuple[tuple[float, int, int], ...]:
        """The constant reinforcement as `(amplitude factor, 1, 1)` points."""
        return tuple((a, 1, 1) for a in self.reinforcement)


class CompensateSettings(eqx.Module):
    """How [`jaxstiction.compensate`][] designs a knocker on the identified closed loop.

    - `grid`: the [`jaxstiction.KnockerGrid`][] searched (`method="grid"`, the default,
      and the starts of `method="gradient"`).
    - `travel_weight`: the design minimises
      $\\sigma_e / \\sigma_{e,\\text{as is}} + w\\,T / T_{\\text{as is}}$, with
      $\\sigma_e$ the standard deviation of SP − PV and $T$ the valve travel: each
      doubling of the travel costs as much as $w$ of the as-is variability (wear is
      the knocker's price). 0: variability alone.
    - `method`: `"grid"` (every grid point simulated with the Kano valve, in one
      vmapped closed-loop run) or `"gradient"` (gradient descent on amplitude and a
      continuous width, through a smoothed Kano valve, from `gradient_starts` periods
      spread over the grid's, at its median amplitude and width 1; `gradient_steps`
      Adam steps, `smooth` the smoothing width in % of
      span; the result is scored on the exact valve).
    - `robust_S`, `robust_J`: each knocker is scored by its worst objective over the
      fitted valve and four neighbours, S × (1 ± `robust_S`) and J ± `robust_J` × S
      (within [0, S]), each against its own run without a knocker; a knocker is
      chosen only when that worst case beats no knocker (1 + w), else none is. A
      knocker's effect hangs on the band to a few percent: on a concealed case whose
      fit has S within 1 % of the valve's, the best knocker for the fitted band makes
      the true loop's variability six times the as-is, and the best for a band 3 %
      narrower cuts it by a quarter. 0 and 0: the fitted valve alone.
    - `min_gain`: a knocker is chosen only when it lowers the standard deviation of
      SP − PV by at least this share of the as-is one on the fitted valve and on
      every neighbour: a knocker wears the valve, and a gain smaller than the
      model's own error is no reason to fit one. On the realistic fleet (seeds
      0–49) it withdraws 9 designs; on the true plants 6 of them bought nothing,
      one bought 6 %, and two made the loop worse (by 17 %, and three times over
      for a band fitted at 0.11 % for 8 %).
    """

    grid: KnockerGrid = KnockerGrid()
    travel_weight: float = eqx.field(static=True, default=0.05)
    method: str = eqx.field(static=True, default="grid")
    gradient_starts: int = eqx.field(static=True, default=4)
    gradient_steps: int = eqx.field(static=True, default=60)
    gradient_rate: float = eqx.field(static=True, default=0.05)
    smooth: float = eqx.field(static=True, default=0.05)
    robust_S: float = eqx.field(static=True, default=0.03)
    robust_J: float = eqx.field(static=True, default=0.1)
    min_gain: float = eqx.field(static=True, default=0.02)

    def __check_init__(self):
        check_counts(self, positive=("gradient_starts", "gradient_steps"))
        if not 0 <= self.min_gain < 1:
            raise ValueError(f"`CompensateSettings.min_gain` must be in [0, 1), got {self.min_gain!r}")
        if not (0 <= self.robust_S < 1 and 0 <= self.robust_J <= 1):
            raise ValueError("`CompensateSettings.robust_S` must be in [0, 1) and `robust_J` in [0, 1], got "
                             f"{self.robust_S!r} and {self.robust_J!r}")
        if self.method not in ("grid", "gradient"):
            raise ValueError(f"`CompensateSettings.method` must be 'grid' or 'gradient', got {self.method!r}")
        if not self.travel_weight >= 0:
            raise ValueError(f"`CompensateSettings.travel_weight` must be >= 0, got {self.travel_weight!r}")
        if not (self.smooth > 0 and self.gradient_rate > 0):
            raise ValueError("`CompensateSettings.smooth` and `gradient_rate` must be > 0, got "
                             f"{self.smooth!r} and {self.gradient_rate!r}")


class WhatIfSettings(eqx.Module):
    """Settings of [`jaxstiction.whatif`][] (static).

    - `draws`: models drawn to carry the uncertainty of S, J and the process into the
      intervals (S and J uniform on their intervals, the process coefficients from
      their asymptotic normal distribution; a draw the record rejects is dropped);
      0: no intervals.
    - `level`: the intervals' coverage (their ends are the quantiles of the kept
      draws and the fit), and the level of the test that keeps a draw.
    - `init_count`: candidate stopping points per direction of the Kano valve when
      the initial state of each model is estimated from the record. With too few, a
      valve whose hidden state at the start (where it stuck, which way it last
      moved) no candidate shares slips at the wrong time in the replay, which the
      disturbance then carries as a spurious step.
    - `reversal_threshold`: a valve reverses when it has moved more than this (% of
      span) against its previous direction of travel; smaller moves are not counted
      (as a positioner's reversal counter ignores its own resolution).
    - `min_controller_fit`: below this share of ΔOP explained, the identified
      controller gets a note (a historian may have compressed PV, or the
      controller is not a PI).
    - `min_samples`: fewest samples to read the numbers from: when the valve's
      unknown start and the repaired loop's settling leave fewer, the last
      `min_samples` samples after the valve's start are read (and the `whatif` note
      says so); when the valve's start alone leaves fewer, the numbers are null
      (see [`jaxstiction.WhatIf`][]).
    - `compensate`: [`jaxstiction.CompensateSettings`][] of the knocker design.
    - `seed`: of the draws.
    - `refine`: refit the fit's process for the replay by prediction error with a
      tenth-order AR noise model, on the fitted valve path (kept when it lowers that
      criterion and leaves a stable process stable).
      `whatif_model` replays the model it is given as it is.
    - `polish`: with `refine`, also polish S and J on a fine grid around the fit by a
      high-order ARX criterion, and refit the process on the polished valve's path at
      the fitted dead time and one sample either side; the least criterion is kept
      among the refits whose repaired replay does not run away. It makes a what-if
      about 4.5 times as costly: 1.1 s against 0.24 s for one 1500-sample loop,
      unbatched, on a 2-core CPU.
    """

    draws: int = eqx.field(static=True, default=24)
    level: float = eqx.field(static=True, default=0.9)
    init_count: int = eqx.field(static=True, default=32)
    reversal_threshold: float = eqx.field(static=True, default=0.1)
    min_controller_fit: float = eqx.field(static=True, default=0.8)
    min_samples: int = eqx.field(static=True, default=200)
    compensate: CompensateSettings = CompensateSettings()
    seed: int = eqx.field(static=True, default=0)
    refine: bool = eqx.field(static=True, default=True)
    polish: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        check_counts(self, positive=("init_count",), nonnegative=("draws", "seed", "min_samples"))
        if not 0.0 < self.level < 1.0:
            raise ValueError(f"`WhatIfSettings.level` must be in (0, 1), got {self.level!r}")
        if not self.reversal_threshold >= 0:
            raise ValueError(f"`WhatIfSettings.reversal_threshold` must be >= 0, got {self.reversal_threshold!r}")
