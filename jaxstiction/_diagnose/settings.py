"""Settings of [`jaxstiction.diagnose`][] and the diagnosis's vocabularies (a leaf:
every step of the diagnosis imports its settings from here)."""

from __future__ import annotations

import dataclasses

import equinox as eqx

from .._checks import check_counts, is_count
from .._estimate.settings import SCREEN_ESTIMATE, Settings


VERDICTS = ("none", "stiction", "deadband", "dead_time", "valve_characteristic", "saturation", "actuator_lag",
            "external_oscillation", "drift", "quantization")
OUTPUT_FAMILIES = ("external_oscillation", "drift")
INPUT_FAMILIES = ("stiction", "deadband", "dead_time", "valve_characteristic", "saturation", "actuator_lag")


# The joint stiction fit: the screen's profile, with the S and J intervals also read
# off the wider Box-Jenkins grid (`PhysicalSettings.interval_span`), which moves no
# point estimate. On P1 (S 3, J 1) diagnosed without a nominal model, seeds 0-19, the
# intervals held the truth on 8 (S) and 14 (J) of 20 seeds without it, 14 and 17 with
# it (S on 14 of the 15 seeds named stiction; the others' fits found another band),
# for 1-3 s more per diagnosis.
JOINT_ESTIMATE = dataclasses.replace(
    SCREEN_ESTIMATE, physical=dataclasses.replace(SCREEN_ESTIMATE.physical, interval_span=4.0))


class DiagnoseSettings(eqx.Module):
    """Settings of [`jaxstiction.diagnose`][] (static).

    `holdout`: fraction of the record held out at its end, in (0, 1); `bootstrap`:
    parametric bootstrap replicates, at least 2 (each family's null is a normal
    approximation of their statistics, so its p-values are not limited to
    1/(bootstrap+1); 19 or more are advised); `alpha`:
    family-wise significance level; `order`: linear order when no nominal model is
    given; `max_delay`: delays tried then; `grid`: points per axis of the stiction and
    deadband grids; `periods`: periods tried for an external oscillation; `seed`: of
    the random numbers (the bootstrap's noise, the segment tests' circular shifts).

    Without a nominal model, stiction is also refitted jointly with the linear part
    (poles free) by [`jaxstiction.estimate`][] with settings `joint` (default:
    `JOINT_ESTIMATE`), its significance from `joint_bootstrap` replicates of that
    whole fit (0 turns the joint fit off)."""

    holdout: float = eqx.field(static=True, default=1 / 3)
    bootstrap: int = eqx.field(static=True, default=39)
    alpha: float = eqx.field(static=True, default=0.05)
    order: int = eqx.field(static=True, default=2)
    max_delay: int = eqx.field(static=True, default=4)
    grid: int = eqx.field(static=True, default=36)
    periods: int = eqx.field(static=True, default=48)
    seed: int = eqx.field(static=True, default=0)
    joint: Settings = eqx.field(static=True, default=JOINT_ESTIMATE)
    joint_bootstrap: int = eqx.field(static=True, default=9)

    def __check_init__(self):
        if not (isinstance(self.holdout, (int, float)) and 0.0 < self.holdout < 1.0):
            raise ValueError(f"`holdout` must be a fraction between 0 and 1 (the held-out part), got {self.holdout!r}")
        if not is_count(self.bootstrap, 2):
            raise ValueError(f"`bootstrap` must be a whole number of replicates, at least 2, got {self.bootstrap!r}")
        check_counts(self, nonnegative=("joint_bootstrap",))
        if not (isinstance(self.alpha, (int, float)) and 0.0 < self.alpha < 1.0):
            raise ValueError(f"`alpha` must be a significance level between 0 and 1, got {self.alpha!r}")
