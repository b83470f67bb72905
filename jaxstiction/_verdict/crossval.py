r"""Blocked cross-validation of a sticky valve against a linear valve, in k-step
prediction.

A simulation from one initial state, scored on the last third of a record, says
little on plant data: the last third often sits in another regime, and a model
that simulates worse than the mean there can still win or lose by chance. Here the
record is cut into `folds` contiguous blocks; each block is predicted `horizon`
samples ahead by models fitted on the other blocks (with a guard band around the
held-out block, so no fitted sample sees it), and the valve that predicts the held
out blocks better wins them.

The models are cheap on purpose, so that every loop of a fleet can afford them: an
ARX model $A(q) y = B(q) q^{-d} x + c$ of PV (`ar_order`, `input_order`) driven by
the valve position $x$, with $x$ either OP itself (a linear valve) or OP through a
Kano valve on a grid of bands S (fractions of the OP range) and slips J/S. For each
fold, the Kano valve and the delay are chosen by the k-step error on the training
blocks, and the linear valve's delay the same way. An integrating process needs no
special case: an ARX model of order two holds an integrator when the data ask for
one.

`crossval_gain` returns, per fold, the share of the linear valve's held-out k-step
error that the Kano valve removes (in %; negative where it predicts worse).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._blocks import Kano
from .._linalg import lstsq
from .._misc import first_min


BANDS = (0.03, 0.08, 0.15, 0.3, 0.5, 0.7, 0.9)  # S as a fraction of the OP range (a limit cycle moves OP by about S)
SLIPS = (0.5, 1.0)  # J / S
DELAYS = (1, 2, 4, 8)


def _shift(x, k: int):
    """x(t - k), the first k samples repeating x[0]."""
    if k == 0:
        return x
    return jnp.concatenate([jnp.full((k,), x[0], x.dtype), x[:-k]])


def _regressors(y, x, na: int, nb: int, d: int):
    cols = [_shift(y, i) for i in range(1, na + 1)] + [_shift(x, d + j) for j in range(nb)] + [jnp.ones_like(y)]
    return jnp.stack(cols, axis=1)


def kstep_prediction(theta, y, x, na: int, nb: int, d: int, k: int):
    """The ARX model's `k`-step-ahead prediction of every sample of `y`: the model
    iterated `k` times from the measured outputs up to t − k."""
    a, b, c = theta[:na], theta[na : na + nb], theta[-1]
    forced = sum(b[j] * _shift(x, d + j) for j in range(nb)) + c
    past = [y]  # past[s]: each sample predicted s steps ahead
    for s in range(1, k + 1):
        acc = forced
        for i in range(1, na + 1):
            acc = acc + a[i - 1] * _shift(past[s - i] if s >= i else y, i)
        past.append(acc)
    return past[k]


def _fit_and_score(y, x, train, test, na, nb, d, k):
    A = _regressors(y, x, na, nb, d)
    sw = jnp.sqrt(train)
    theta = lstsq(A * sw[:, None], y * sw)
    err = (y - kstep_prediction(theta, y, x, na, nb, d, k)) ** 2
    return (jnp.sum(train * err) / jnp.maximum(jnp.sum(train), 1.0),
            jnp.sum(test * err) / jnp.maximum(jnp.sum(test), 1.0))


def crossval_gain(op, pv, mask, *, folds: int = 4, horizon: int = 5, ar_order: int = 2, input_order: int = 2,
                  delays=DELAYS, bands=BANDS, slips=SLIPS):
    """Per fold, 100 (1 − e_Kano / e_linear): the share of the linear valve's
    held-out `horizon`-step prediction error (mean square) that the best Kano valve
    removes (see the module notes). Pure and vmappable; shape `(folds,)`."""
    w = (mask > 0).astype(op.dtype)
    n = op.shape[0]
    count = jnp.maximum(jnp.sum(w), 1.0)
    t = jnp.arange(n)
    fold = jnp.minimum(jnp.floor(t / count * folds), folds - 1).astype(jnp.int32)
    big = jnp.finfo(op.dtype).max
    span = jnp.max(jnp.where(w > 0, op, -big)) - jnp.min(jnp.where(w > 0, op, big))
    S = jnp.asarray([0.0] + [s for s in bands for _ in slips], op.dtype) * span
    J = jnp.asarray([0.0] + [s * j for s in bands for j in slips], op.dtype) * span
    paths = jax.vmap(lambda s, j: Kano(s, j)(op))(S, J)  # (1 + grid, n); the first is OP itself
    guard = max(delays) + input_order + ar_order + horizon
    gains = []
    for f in range(folds):
        held = w * (fold == f)
        first = jnp.min(jnp.where(held > 0, t, n))
        near = jnp.convolve(held, jnp.ones((2 * guard + 1,), op.dtype), mode="same") > 0
        train = w * ~near * (t >= guard)  # the record's first samples have no known past
        test = held * (t >= first + guard)  # the block's first samples predict from the training data

        def one(x):
            scores = [_fit_and_score(pv, x, train, test, ar_order, input_order, d, horizon) for d in delays]
            tr = jnp.stack([s[0] for s in scores])
            te = jnp.stack([s[1] for s in scores])
            i = first_min(tr)
            return tr[i], te[i]

        tr, te = jax.vmap(one)(paths)
        best = first_min(tr[1:]) + 1
        gains.append(100.0 * (1.0 - te[best] / jnp.maximum(te[0], 1e-300)))
    return jnp.stack(gains)
