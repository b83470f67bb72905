"""Held-out scoring: the held-out figures of a candidate model and its proof (gains
and the input cross-correlation test), the bootstrap records its significance is
judged against, the narrow-band statistic, and the `Finding` that carries the
evidence. (`proof` judges a gain against its run-to-run spread.)

Held-out simulation fitness starts from an initial state estimated on the opening
held-out samples; one-step and k-step prediction errors come from the model's noise
model. Bootstrap records are the fitted noise model driven by Gaussian innovations.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._blocks import Sinusoid
from .._criteria import simulate_scored
from .._filters import lfilter
from .._misc import json_number
from .._models import LoopModel
from .locate import ar_whiten, cross_correlation


K_STEP = 10


def _diff(a, b) -> float:
    """`a - b` for held-out figures that may be missing (None: not finite)."""
    if a is None:
        return -math.inf
    if b is None:
        return math.inf
    return a - b


def _normal_sf(zv: float) -> float:
    return 0.5 * math.erfc(zv / math.sqrt(2.0))


def _null_tail(obs: float, null) -> float:
    """P(statistic >= `obs`) under a normal approximation of the bootstrap values
    `null` (so the p-value is not limited to 1/(len(null)+1))."""
    null = np.asarray(null, float)
    return _normal_sf((obs - float(null.mean())) / max(float(null.std(ddof=1)), 1e-9))


class Finding(eqx.Module):
    """One named effect: its block's parameters (with an interval from the grid's
    likelihood profile), the evidence, and held-out figures before (refitted linear
    valve) and after (with the block)."""

    effect: str = eqx.field(static=True)
    parameters: dict
    evidence: dict
    heldout_before: dict
    heldout_after: dict
    accepted: bool = eqx.field(static=True)
    model: LoopModel | None = None

    def to_json(self) -> dict:
        return {"effect": self.effect, "parameters": self.parameters, "evidence": self.evidence,
                "heldout_before": self.heldout_before, "heldout_after": self.heldout_after,
                "accepted": self.accepted}


def _revised(finding: Finding, accepted: bool, **evidence) -> Finding:
    """`finding` with its acceptance decided again and `evidence` added (an accepted
    finding loses the `rejected_by` of an earlier decision)."""
    ev = {**finding.evidence, **evidence}
    if accepted:
        ev.pop("rejected_by", None)
    return dataclasses.replace(finding, evidence=ev, accepted=accepted)


def _add_output(model: LoopModel, block) -> LoopModel:
    """`model` with the output-side `block` added after its own output blocks."""
    return eqx.tree_at(lambda m: m.output, model, tuple(model.output) + (block,))


def _shift_phase(model: LoopModel, n: int) -> LoopModel:
    """The model seen from sample `n` on (output oscillations keep their phase)."""
    out = tuple(
        Sinusoid(b.amplitude, b.period, b.phase + 2 * jnp.pi * n / b.period) if isinstance(b, Sinusoid) else b
        for b in model.output
    )
    return eqx.tree_at(lambda m: m.output, model, out) if out else model


def _heldout(model: LoopModel, op, pv, n_est: int) -> dict:
    """Held-out figures: simulation fitness (initial state estimated on the opening
    held-out samples), one-step and k-step prediction RMS errors."""
    opj, pvj = jnp.asarray(op), jnp.asarray(pv)
    n = len(op)
    w = (jnp.arange(n) >= n_est).astype(opj.dtype)
    m_h = _shift_phase(model, n_est)
    # the held-out part alone: a scored simulation starts at its first scored sample,
    # so the samples before it change nothing (and cost a third of the time here)
    _, fit_h = _jit_scored(m_h, opj[n_est:], pvj[n_est:], w[n_est:]) if n_est < n else _jit_scored(m_h, opj, pvj, w)
    p1 = np.asarray(_jit_predict(model, opj, pvj, 1))
    pk = np.asarray(_jit_predict(model, opj, pvj, K_STEP))
    h = slice(n_est + 20, n)

    def rms(e):
        with np.errstate(all="ignore"):
            return json_number(np.sqrt(np.mean(e**2)), 5)

    return {"fitness": json_number(fit_h), "one_step_rms": rms(pv[h] - p1[h]),
            f"k{K_STEP}_step_rms": rms(pv[h] - pk[h])}


@eqx.filter_jit
def _jit_scored(model, op, pv, w):
    return simulate_scored(model, op, pv, w)


@eqx.filter_jit
def _jit_scores(model, op, pvs):
    """Fitness of `model` on each record of `pvs` (records, time), whole records scored."""
    w = jnp.ones_like(op)
    return jax.vmap(lambda p: simulate_scored(model, op, p, w)[1])(pvs)


@eqx.filter_jit
def _jit_kstep_rms(model, op, pvs, start: int):
    """RMS k-step prediction error of `model` on each record of `pvs` from sample `start` on."""
    return jax.vmap(lambda p: jnp.sqrt(jnp.mean((p - model.predict(op, p, K_STEP))[start:] ** 2)))(pvs)


@eqx.filter_jit
def _jit_predict(model, op, pv, k: int):
    return model.predict(op, pv, k)


def _bootstrap_noise(c, d, residual, n_est: int, key, count: int, n: int) -> list[np.ndarray]:
    """`count` noise records of length `n` from the noise model $C/D$: innovations of
    the standard deviation that whitening `residual` by $D/C$ leaves on the estimation
    samples (the first 20 skipped), filtered by $C/D$ after a 300-sample warm-up."""
    c, d = jnp.asarray(c), jnp.asarray(d)
    sig = float(np.std(np.asarray(lfilter(d, c, jnp.asarray(residual)))[20:n_est]))
    return list(np.asarray(_noise_records(c, d, key, sig, count, n)))


@functools.partial(jax.jit, static_argnums=(4, 5))
def _noise_records(c, d, key, sig, count: int, n: int):
    """(count, n) records of $C/D$ noise: record `b` from `fold_in(key, b)`, 300-sample warm-up dropped."""
    e = jax.vmap(lambda b: jr.normal(jr.fold_in(key, b), (n + 300,)))(jnp.arange(count)) * sig
    return jax.vmap(lambda x: lfilter(c, d, x))(e)[:, 300:]


@jax.jit
def _band_statistics(resid, c, d, w, f0):
    """Narrow-band statistic of each residual record in `resid` `(records, n)`:
    whitened by $D/C$ and weighted by `w` (0/1), the mean periodogram ordinate (8x
    zero-padded) within ±10 % of frequency `f0` over the median ordinate in
    [f0/2, 2 f0] outside that band. The band's mean power holds a line and a
    wandering narrow-band disturbance alike; a ratio to the band's neighbourhood, so
    a held-out part whose noise is louder or redder than the estimation part's does
    not read as a line."""
    n = resid.shape[1]
    m = 8 * n
    f = jnp.arange(m // 2 + 1) / m
    band = jnp.abs(f - f0) <= 0.1 * f0
    near = (f >= 0.5 * f0) & (f <= 2.0 * f0) & ~band

    def one(r):
        e = lfilter(d, c, r) * w
        e = (e - jnp.sum(e) / jnp.sum(w)) * w
        power = jnp.abs(jnp.fft.rfft(e, n=m)) ** 2
        return jnp.sum(jnp.where(band, power, 0.0)) / jnp.sum(band) / jnp.nanmedian(jnp.where(near, power, jnp.nan))

    return jax.vmap(one)(resid)


def _prove(model: LoopModel, op, pv, n_est: int, before: dict, other=None, innovations=False):
    """A candidate model's proof: its held-out figures, its held-out simulation and
    k-step gains over `before`, and the input cross-correlation test of its
    (AR(2)-whitened) estimation residual, with `other` (an effect found beside it,
    e.g. an external oscillation, in PV units) removed first; with `innovations`, a
    residual that fails is tested again on the model's innovations
    (`_residual_cross_correlation`)."""
    after = _heldout(model, op, pv, n_est)
    gain = _diff(after["fitness"], before["fitness"])
    kgain = _diff(before[f"k{K_STEP}_step_rms"], after[f"k{K_STEP}_step_rms"])
    return after, gain, kgain, _residual_cross_correlation(model, op, pv, n_est, other, innovations)


def _residual_cross_correlation(model: LoopModel, op, pv, n_est: int, other=None, innovations=False) -> dict:
    """The input cross-correlation test of `model`'s (AR(2)-whitened) estimation
    residual, with `other` (in PV units) removed first.

    With `innovations` (a drift's model), a residual that fails is tested again
    filtered first by the model's own noise model $D/C$, and passes if either passes:
    an AR(2) cannot whiten a large random walk, whose wander left in correlates with
    the OP that the controller moves against it (random draws 2181 and 5026), while
    the drift model, fitted on a grid with AR(1) noise, can leave two lags of 20 out
    of the band where the AR(2) left one, which is allowed (P8 seed 22)."""
    sim = np.asarray(_jit_scored(model, jnp.asarray(op), jnp.asarray(pv), jnp.ones(len(op)))[0])
    resid = pv - sim if other is None else pv - sim - other
    cc = cross_correlation(op[:n_est], ar_whiten(resid[:n_est], 2)[0])
    if innovations and not cc["passes"]:
        e = np.asarray(lfilter(model.noise.d, model.noise.c, jnp.asarray(resid - np.mean(resid[:n_est]))))
        cc = {**cross_correlation(op[:n_est], ar_whiten(e[:n_est], 2)[0]), "whitened_by": "the noise model"}
    return cc


