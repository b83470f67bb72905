r"""Model criteria: FOE (22), and simulation fitness (34) scored the way
system-identification tools score it, with the initial state estimated first."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp

from ._filters import fitness
from ._models import LoopModel


def foe(loss, count, dof):
    r"""Final output error (22): $\frac{N + d}{N - d} V$ for loss $V$ on $N$ samples
    with $d$ free parameters."""
    return (count + dof) / (count - dof) * loss


class ScoreSettings(eqx.Module):
    """How a simulation is scored: the initial state is estimated from the opening
    `max(init_min, init_fraction × length)` samples of the scored record, over
    `init_count` candidate stopping points per direction of each valve block."""

    init_fraction: float = eqx.field(static=True, default=0.2)
    init_min: int = eqx.field(static=True, default=50)
    init_count: int = eqx.field(static=True, default=40)


def simulate_scored(model: LoopModel, op, pv, weights, settings: ScoreSettings = ScoreSettings()):
    """Simulate `model` on the part of a record marked by `weights` (one contiguous
    run of samples, weight 1), from an initial state estimated on its opening samples.

    Returns `(pv_sim, fitness)`: the simulation over the whole array (meaningful on
    and after the scored part) and the fitness (34) over the scored part, in percent.
    """
    n = op.shape[0]
    t = jnp.arange(n)
    start = jnp.argmax(weights > 0)
    length = jnp.sum(weights)
    # Roll the scored part to the front, so every shape stays static.
    idx = (t + start) % n
    op_r, pv_r, w_r = op[idx], pv[idx], weights[idx]
    window = jnp.maximum(settings.init_min, settings.init_fraction * length)
    w_init = w_r * (t < window)
    # a static bound on the window (the scored length is at most `n`): the search for
    # the initial state runs on those samples only
    bound = min(n, math.ceil(max(settings.init_min, settings.init_fraction * n)))
    init = model.initial_state(op_r, pv_r, w_init, count=settings.init_count, window=bound)
    sim_r = model.simulate(op_r, init)
    fit = fitness(pv_r, sim_r, w_r)
    sim = sim_r[(t - start) % n]
    return sim, fit


def score(model: LoopModel, op, pv, weights, settings: ScoreSettings = ScoreSettings()):
    """Simulation fitness (34) of `model` on the samples marked by `weights`, with the
    initial state estimated first (see [`jaxstiction.simulate_scored`][])."""
    return simulate_scored(model, op, pv, weights, settings)[1]
