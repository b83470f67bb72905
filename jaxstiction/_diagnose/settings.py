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
# Why a finding is not accepted: `Finding.evidence["rejected_by"]` names one of these.
# The first four are the acceptance test itself (significant, a held-out gain beyond
# the spread, residuals that pass); the others reject a finding that passed it.
REJECTION_RULES = {
    "significance": "not significant against the bootstrap's null (family-wise)",
    "heldout_gain": "its held-out simulation gain does not exceed the run-to-run spread (nor, for an "
                    "oscillation, does its band persist held out)",
    "output_cross_correlation": "an output-side effect whose residual still correlates with past OP",
    "drift_k_step_gain": "a drift model that predicts k steps ahead no better than stationary noise held out",
    "gain_over_level": "an input block whose held-out gain is the refitted PV level's (`_gain_from_the_block`)",
    "gain_over_linear_under_drift": "with a drift significant, an input block that beats the linear valve refitted "
                                    "the same way by nothing held out (`_gain_from_the_block`)",
    "k_step_gain_under_drift": "with a drift significant, an input block that predicts k steps ahead no better "
                               "than the refitted linear valve, both under the drift's noise model held out "
                               "(`_gain_from_the_block`)",
    "stiction_vs_deadband": "stiction and deadband both proven: the slip J decides which one stands",
    "alternative": "proven on its own, but an alternative to the verdict's block (never fitted together with it)",
    "joint_gain_over_linear": "joint fit (no nominal): no held-out gain over its own linear valve",
    "joint_rank_score": "joint fit (no nominal): penalised likelihood ratio against the linear valve not positive",
    "joint_slip": "joint fit (no nominal): J not significantly above 0, so the band is a deadband",
    "stiction_verdict": "no nominal model: the stiction verdict (the screen's) does not call the valve sticky",
    "unnamed": "rejected by a step that named no rule (a defect: every rejection should name its rule)",
}
ACCEPTANCE_RULES = ("significance", "heldout_gain", "output_cross_correlation", "drift_k_step_gain")


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
