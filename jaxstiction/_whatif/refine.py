r"""The process refitted for the replay: prediction error with a high-order noise model.

The what-if replays the disturbance $v = PV - G(q)\,x$ through a loop whose valve is
repaired, so it needs $G$ right at the frequencies the repaired loop will use, not only
at the limit cycle's. The estimator fits $G$ with a first-order noise model
$C/D$ (and the screen's light profile from a fourth-order ARX start). A load that
wanders at the process input reaches PV coloured by $G$ itself, which a first-order
$C/D$ cannot whiten; the fit then trades $G$ against the noise and can settle far from
the process (on tight loops with a constant setpoint, $A$'s resonance is lost).

Here the free coefficients of $B$ and $A$ are refitted on the fitted valve path $x$
(the valve's S, J and initial state stay as fitted) by minimising the one-step
prediction error of an AR(`order`) noise model with a level, the AR coefficients
projected out at every step (variable projection: the residual is $v$'s least-squares
residual on its own past, by Householder QR), with optimistix's Levenberg–Marquardt.
The refit is kept when it lowers that criterion and leaves a stable process stable;
otherwise the fit's process stays.

Measured on `benchmarks/whatif.py` (docs/method/whatif.md).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx

from .._filters import lagged, steady_state
from .._linalg import apply_q, apply_qt, householder, HouseholderQR, is_stable
from .._models import InitialState, LoopModel
from .uncertainty import free_parameters, with_process


# AR order of the refit's noise model, and samples skipped at the start (the
# process's transient from its assumed rest)
AR_ORDER = 10
SKIP = 50


def ar_residual(v, weights, order: int = AR_ORDER):
    r"""The residual of $v_t$ regressed on a level and $v_{t-1}, \ldots, v_{t-order}$
    by least squares (Householder QR) over the samples whose `weights` are 1 and
    whose `order` predecessors are too; 0 elsewhere."""
    w = weights * jnp.prod(lagged(weights, order), axis=1)
    X = jnp.concatenate([jnp.ones_like(v)[:, None], lagged(v, order)], axis=1) * w[:, None]
    V, _ = householder(X)
    z = apply_qt(V, v * w)
    # Q^T (w v) with its first `order + 1` entries removed is the residual in the
    # reflected basis; reflecting back gives it sample by sample
    z = z.at[: order + 1].set(0.0)
    return apply_q(V, z) * w


def _simulate(model: LoopModel, op, initial: InitialState):
    """`model.simulate` from `initial`, its process filter restarted at rest for the
    first valve position (the refit changes the process, so the fit's filter state
    no longer applies)."""
    b, a = model.process.polynomials()
    x0 = model.valve(op[:1], initial.chain)[0]
    x0 = jnp.where(initial.held, initial.hold, x0)
    start = eqx.tree_at(lambda i: i.filter, initial, steady_state(b, a, x0 - model.op_offset))
    return model.simulate(op, start)


def refine_process(model: LoopModel, op, pv, mask, initial: InitialState, *, order: int = AR_ORDER,
                   max_steps: int = 40):
    """`(model, refined, result)`: `model` with its process refitted (see the module
    notes), whether the refit was kept, and the solver's result code. Pure and
    vmappable; a refit that fails leaves `model` as it was."""
    dtype = op.dtype
    b0, a0 = model.process.polynomials()
    nb = b0.shape[0]
    theta0 = jnp.concatenate([b0, a0[1:]])
    free = free_parameters(model)
    w = (mask > 0).astype(dtype) * (jnp.arange(op.shape[0]) >= SKIP)
    scale = jnp.where(free, jnp.maximum(jnp.abs(theta0), 1e-3), 1.0)

    def at(z):
        th = jnp.where(free, theta0 + z * scale, theta0)
        return with_process(model, th[:nb], jnp.concatenate([a0[:1], th[nb:]]))

    def resid(z, _):
        v = jnp.where(w > 0, pv - _simulate(at(z), op, initial), 0.0)
        return ar_residual(v, w, order)

    z0 = jnp.zeros_like(theta0)
    sol = optx.least_squares(
        resid, optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9, linear_solver=HouseholderQR()), z0,
        max_steps=max_steps, throw=False,
    )
    new = at(sol.value)
    loss0 = jnp.sum(resid(z0, None) ** 2)
    loss = jnp.sum(resid(sol.value, None) ** 2)
    b_new, a_new = new.process.polynomials()
    keep = (jnp.isfinite(loss) & (loss < loss0) & jnp.all(jnp.isfinite(sol.value))
            & (is_stable(a_new) | ~is_stable(a0)) & is_stable(a_new, margin=-1e-3))
    out = with_process(model, jnp.where(keep, b_new, b0), jnp.where(keep, a_new, a0))
    return out, keep, sol.result
