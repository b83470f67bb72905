"""The result of [`jaxstiction.estimate`][]: [`jaxstiction.LoopFit`][], its outcome
codes [`jaxstiction.RESULTS`][], and the notes a reader of a fit should see."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int

from .._criteria import simulate_scored
from .._models import InitialState, LoopModel
from .settings import Settings


class RESULTS(optx.RESULTS):  # pyright: ignore
    """Outcome codes of [`jaxstiction.estimate`][]: optimistix's solver codes plus
    data codes. `RESULTS[fit.result]` gives the message of an unbatched code."""

    too_short = "the record is too short for the chosen orders and delays"
    constant_op = "OP is constant: stiction cannot be identified without valve movement"
    constant_pv = "PV is constant: the process response cannot be identified"
    nonfinite_data = "the record has NaN or inf values"
    valve_never_moves = "the fitted valve never moves over the record"
    not_converged = "the estimator did not converge"


def delay_note(delay, kind, settings: Settings) -> str:
    """A note when the fitted `delay` of a model of `kind` (0 spline, 1 physical, 2 linear) is
    the longest its family tried (the process may have a longer dead time); else ""."""
    longest = settings.physical.max_delay if int(kind) >= 1 else settings.spline.max_delay
    if int(delay) < longest:
        return ""
    return (f"the fitted dead time is the longest tried ({longest} samples): the process may have a longer one "
            "(--max-delay, Settings.with_max_delay)")


def held_out_note(fitness, fitness_estimation, n_validation) -> str:
    """A note when the chosen model simulates the held-out part worse than the data's
    mean (a negative fitness) although it does not on the estimation part: it does
    not carry to new data. Else ""."""
    f, f_est = float(fitness), float(fitness_estimation)
    if int(n_validation) == 0 or not (f < 0.0 <= f_est):
        return ""
    return (f"held out, the chosen model simulates worse than the data's mean ({f:.1f} % against "
            f"{f_est:.1f} % on the estimation part): it does not carry to new data")


KINDS = ("spline", "physical", "linear")  # the chosen model's family, by `LoopFit.kind`


class LoopFit(eqx.Module):
    """Result of [`jaxstiction.estimate`][] (arrays; a leading axis when batched).

    - `model`: the chosen [`jaxstiction.LoopModel`][] in engineering units (OP in %,
      PV in its units); `kind` 0 = spline valve, 1 = physical (Kano) valve, 2 = the
      linear valve (no stiction model beat it).
    - `paper`: the paper's literal method (literal direction rule, no polish);
      `spline`, `physical`: the best model of each family; `linear`, `deadband`: a
      linear valve and a deadband (Kano with J = 0, its width searched around S),
      each with a Box–Jenkins linear part like the physical model's: the nulls
      against which stiction is judged (see [`jaxstiction.verdict`][]).
    - `fitness`: simulation fitness (34) on the validation part (on the estimation
      data when `validate == 0`), initial state estimated from its opening samples;
      `fitness_estimation`, `fitness_paper`, `fitness_spline`, `fitness_physical`,
      `fitness_linear`, `fitness_deadband`; the `*_estimation` fitnesses score the
      last four on the estimation samples.
    - `band_percent`: apparent stiction band (% of OP) of the chosen model: Kano's S
      for the physical model, the width of the spline loop at mid-height, 0 for the
      linear valve.
    - `S`, `J` (with 95 % profile-likelihood intervals): the physical fit.
    - `direction_rule` (0 literal, 1 robust), `num_knots`, `order`, `delay` of the
      chosen model; `foe`, `candidate_fitness`: every spline candidate (rule × knots);
      `foe_spline`, `foe_physical`, `foe_linear`: each family's FOE; `bic_spline`,
      `bic_physical`, `bic_linear`: its BIC, which makes the choice.
    - `n_estimation`, `n_validation`, `op_range`, `relax_steps`, `result`.
    """

    model: LoopModel
    paper: LoopModel
    spline: LoopModel
    physical: LoopModel
    linear: LoopModel
    deadband: LoopModel
    kind: Int[Array, ""]
    fitness: Float[Array, ""]
    fitness_estimation: Float[Array, ""]
    fitness_paper: Float[Array, ""]
    fitness_spline: Float[Array, ""]
    fitness_physical: Float[Array, ""]
    fitness_linear: Float[Array, ""]
    fitness_spline_estimation: Float[Array, ""]
    fitness_physical_estimation: Float[Array, ""]
    fitness_linear_estimation: Float[Array, ""]
    fitness_deadband: Float[Array, ""]
    fitness_deadband_estimation: Float[Array, ""]
    band_percent: Float[Array, ""]
    S: Float[Array, ""]
    J: Float[Array, ""]
    S_interval: Float[Array, " 2"]
    J_interval: Float[Array, " 2"]
    direction_rule: Int[Array, ""]
    num_knots: Int[Array, ""]
    order: Int[Array, ""]
    delay: Int[Array, ""]
    foe: Float[Array, "rules knots"]
    candidate_fitness: Float[Array, "rules knots"]
    foe_spline: Float[Array, ""]
    foe_physical: Float[Array, ""]
    foe_linear: Float[Array, ""]
    bic_spline: Float[Array, ""]
    bic_physical: Float[Array, ""]
    bic_linear: Float[Array, ""]
    n_estimation: Int[Array, ""]
    n_validation: Int[Array, ""]
    op_range: Float[Array, " 2"]
    relax_steps: Int[Array, ""]
    result: RESULTS

    @property
    def converged(self):
        """True where `result` is successful."""
        return self.result == RESULTS.successful

    def predict(self, op, pv=None, *, k: int | None = None, initial: InitialState | None = None):
        """Simulate or predict the chosen model on a record.

        - `pv=None`: simulation from `initial` (default: at rest at `op[0]`).
        - `pv` given, `k=None`: simulation from an initial state estimated on the
          opening samples of `pv` (as the fitness is scored).
        - `pv` and `k` given: `k`-step-ahead prediction with the noise model.
        """
        if pv is None:
            return self.model.simulate(op, initial)
        if k is None:
            w = jnp.ones_like(jnp.asarray(op))
            return simulate_scored(self.model, jnp.asarray(op), jnp.asarray(pv), w)[0]
        return self.model.predict(op, pv, k, initial)
