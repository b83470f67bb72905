r"""Model criteria: FOE (22), BIC, and simulation fitness (34) scored the way
system-identification tools score it, with the initial state estimated first."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp

from ._checks import check_counts
from ._filters import fitness
from ._models import LoopModel


def foe(loss, count, dof):
    r"""Final output error (22): $\frac{N + d}{N - d} V$ for loss $V$ on $N$ samples
    with $d$ free parameters."""
    return (count + dof) / (count - dof) * loss


def bic(loss, count, dof):
    r"""Schwarz's Bayesian information criterion of a Gaussian fit: $N \ln V + d \ln N$
    for loss $V$ on $N$ samples with $d$ free parameters (lower is better). Its
    penalty grows with $N$, so between two model families it picks the true one as
    the record grows, where FOE (an AIC) keeps a fixed chance of the larger one."""
    return count * jnp.log(loss) + dof * jnp.log(count)


def family_criteria(loss, count, dof):
    """`(foe, bic)` of a model family's loss, both +inf where the fit failed (a
    non-finite loss or FOE), so that family is never chosen."""
    f = jnp.where(jnp.isfinite(loss), foe(loss, count, dof), jnp.inf)
    return f, jnp.where(jnp.isfinite(f), bic(loss, count, dof), jnp.inf)


class ScoreSettings(eqx.Module):
    """How a simulation is scored: the initial state is estimated from the opening
    `max(init_min, init_fraction × length)` samples of the scored record, over
    `init_count` candidate stopping points per direction of each valve block."""

    init_fraction: float = eqx.field(static=True, default=0.2)
    init_min: int = eqx.field(static=True, default=50)
    init_count: int = eqx.field(static=True, default=40)

    def __check_init__(self):
        check_counts(self, positive=("init_min", "init_count"))
        if not 0.0 < self.init_fraction <= 1.0:
            raise ValueError(f"`ScoreSettings.init_fraction` must be in (0, 1], got {self.init_fraction!r}")


def _rolled(model: LoopModel, op, pv, weights, settings: ScoreSettings):
    # The scored part (one contiguous run of weight-1 samples) rolled to the front, so
    # every shape stays static, and the model's initial state estimated on its opening
    # samples. Returns the rolled op, pv, weights, the state and the index map back.
    n = op.shape[0]
    t = jnp.arange(n)
    start = jnp.argmax(weights > 0)
    length = jnp.sum(weights)
    idx = (t + start) % n
    op_r, pv_r, w_r = op[idx], pv[idx], weights[idx]
    window = jnp.maximum(settings.init_min, settings.init_fraction * length)
    w_init = w_r * (t < window)
    # a static bound on the window (the scored length is at most `n`): the search for
    # the initial state runs on those samples only
    bound = min(n, math.ceil(max(settings.init_min, settings.init_fraction * n)))
    init = model.initial_state(op_r, pv_r, w_init, count=settings.init_count, window=bound)
    return op_r, pv_r, w_r, init, (t - start) % n


def simulate_scored(model: LoopModel, op, pv, weights, settings: ScoreSettings = ScoreSettings()):
    """Simulate `model` on the part of a record marked by `weights` (one contiguous
    run of samples, weight 1), from an initial state estimated on its opening samples.

    Returns `(pv_sim, fitness)`: the simulation over the whole array (meaningful on
    and after the scored part) and the fitness (34) over the scored part, in percent.
    """
    op_r, pv_r, w_r, init, back = _rolled(model, op, pv, weights, settings)
    sim_r = model.simulate(op_r, init)
    return sim_r[back], fitness(pv_r, sim_r, w_r)


def predicted(model: LoopModel, op, pv, weights, k: int, settings: ScoreSettings = ScoreSettings()):
    """The `k`-step-ahead prediction of `model` (its noise model included, see
    [`jaxstiction.LoopModel.predict`][]) over the whole array, from an initial state
    estimated on the opening samples of the part marked by `weights` (meaningful on and
    after that part). `k` is a static int."""
    op_r, pv_r, _, init, back = _rolled(model, op, pv, weights, settings)
    return model.predict(op_r, pv_r, k, init)[back]


def predict_scored(model: LoopModel, op, pv, weights, k: int, settings: ScoreSettings = ScoreSettings()):
    """Fitness (34), in percent, of the `k`-step-ahead prediction of `model` on the
    part of a record marked by `weights`, from an initial state estimated on its
    opening samples as in [`jaxstiction.simulate_scored`][]."""
    return fitness(pv, predicted(model, op, pv, weights, k, settings), weights)


def score(model: LoopModel, op, pv, weights, settings: ScoreSettings = ScoreSettings()):
    """Simulation fitness (34) of `model` on the samples marked by `weights`, with the
    initial state estimated first (see [`jaxstiction.simulate_scored`][])."""
    return simulate_scored(model, op, pv, weights, settings)[1]
