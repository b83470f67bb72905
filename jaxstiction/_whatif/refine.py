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
The residual's Jacobian is Golub and Pereyra's closed form (`_ar_residual_jvp`): the
valve path is computed once, and no derivative flows through the QR factorisation,
which would cost several times more. The refit is kept when it lowers that criterion and leaves a stable process stable;
otherwise the fit's process stays.

Before the refit the valve may be polished (`polish_valve`). On a slowly ramping OP
the sample at which the valve slips hangs on S's second decimal, and a fit whose S
is a tenth low slips a sample early and takes a dead time one sample too long to
match. S and J are searched on a fine grid around the fit, one coordinate at a time,
by the residual of a high-order ARX model of PV on its own past and the valve path
(no process model is assumed; PV's own regressors are factored once for the whole
grid, `arx_criteria`), and the process is then refitted at the fitted dead
time and one sample either side (`refit_for_replay`).

The refit is a local search, and a fit's process can sit in another basin: on
tight concealed loops, a static gain half the plant's with the valve right, while
the criterion is lower at the plant. So the process is also refitted from starts
that do not hang on the fit (`arx_starts`): a high-order ARX of PV on its past and
the polished valve path, simulated without noise, then the fit's structure fitted
to that output by equation error at its dead time and up to two samples either
side; each start gets its own initial valve state. One more start comes from a
fourth-order ARX of PV's and the valve path's first differences, at the fitted dead
time: a slow load makes the levels' ARX put a pole and a zero near 1 that do not
quite cancel, which spoils its low-frequency gain, and differencing leaves that
band out (on concealed seed 85 the differenced start reaches the plant's basin,
whose criterion is 15 % lower, and no other start does). Of all these refits and the one
without the polish, the least criterion is kept, among those whose repaired replay
(a cheap one, from the refit's own start, with the loop's PI) keeps its error within
`RUNAWAY_FACTOR` of the record's. A polished valve
without a slip can buy its fit with a process the repaired loop cannot carry (on the
plant record L47, a gain 2.6 times the fit's, and a repaired replay that bangs OP
between its limits).

Measured on `benchmarks/whatif.py` (docs/method/whatif.md).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .._control.closedloop import closed_loop, with_valve
from .._control.controller import Controller
from .._filters import lagged, lfilter, steady_state
from .._linalg import apply_q, apply_qt, householder, HouseholderQR, is_stable, lstsq, solve_upper
from .._misc import first_min, stack_trees
from .._models import InitialState, LoopModel
from .replay import initial_and_sync
from .uncertainty import free_parameters, with_process


# AR order of the refit's noise model, and samples skipped at the start (the
# process's transient from its assumed rest)
AR_ORDER = 10
SKIP = 50
# the valve polish: S within +-S_SPAN of the fit by S_STEP, J within +-J_SPAN by
# J_STEP (% of OP span), ROUNDS rounds of S then J
S_STEP, S_SPAN = 0.01, 0.4
J_STEP, J_SPAN = 0.05, 2.0
ROUNDS = 2


def _projected_out(X, y, weights, order: int):
    """The least-squares residual of `y` on the columns of `X` (Householder QR) over
    the samples whose `weights` are 1 and whose `order` predecessors are too; 0
    elsewhere."""
    w = _ar_weights(weights, order)
    X = X * w[:, None]
    V, _ = householder(X)
    z = apply_qt(V, y * w)
    # Q^T (w y) with its first entries removed is the residual in the reflected
    # basis; reflecting back gives it sample by sample
    z = z.at[: X.shape[1]].set(0.0)
    return apply_q(V, z) * w


def ar_residual(v, weights, order: int = AR_ORDER):
    r"""The residual of $v_t$ regressed on a level and $v_{t-1}, \ldots, v_{t-order}$
    by least squares (Householder QR) over the samples whose `weights` are 1 and
    whose `order` predecessors are too; 0 elsewhere.

    Differentiable in `v` by a closed-form derivative (`_ar_residual_jvp`), not
    through the QR factorisation: Levenberg–Marquardt on it costs several times
    less."""
    return _ar_residual(order, v, weights)


def _ar_regressors(v, order: int):
    return jnp.concatenate([jnp.ones_like(v)[:, None], lagged(v, order)], axis=1)


def _ar_weights(weights, order: int):
    return weights * jnp.prod(lagged(weights, order), axis=1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _ar_residual(order: int, v, weights):
    return _projected_out(_ar_regressors(v, order), v, weights, order)


def _guarded(R):
    """`R` with each row and column of a negligible pivot (a regressor with nothing
    left to fit) replaced by the identity's, and which pivots those are."""
    diag = jnp.abs(jnp.diag(R))
    full = diag > 1e-12 * jnp.maximum(jnp.max(diag), jnp.finfo(R.dtype).tiny)
    keep = full[:, None] & full[None, :]
    return jnp.where(keep, R, jnp.eye(R.shape[0], dtype=R.dtype)), full


@_ar_residual.defjvp
def _ar_residual_jvp(order, primals, tangents):
    r"""The derivative of the projected residual $r = \Pi^\perp W v$ with regressors
    $X = W[1, v_{t-1}, \ldots]$ that depend on $v$ too (Golub and Pereyra 1973):
    $\partial r = \Pi^\perp (W\partial v - \partial X\,\hat\beta)
    - Q_1 R^{-T} \partial X^T r$, with $X = Q_1 R$ and $\hat\beta = R^{-1} Q_1^T W v$."""
    v, weights = primals
    dv, _ = tangents
    w = _ar_weights(weights, order)
    V, R = householder(_ar_regressors(v, order) * w[:, None])
    n = R.shape[0]
    z = apply_qt(V, v * w)
    Rg, full = _guarded(R)
    beta = solve_upper(Rg, jnp.where(full, z[:n], 0.0))
    r = apply_q(V, z.at[:n].set(0.0)) * w
    dX = jnp.concatenate([jnp.zeros_like(dv)[:, None], lagged(dv, order)], axis=1) * w[:, None]
    first = apply_q(V, apply_qt(V, dv * w - dX @ beta).at[:n].set(0.0)) * w
    # R^{-T} c by back substitution on the reversed (upper-triangular) R^T
    c = jnp.where(full, dX.T @ r, 0.0)
    u = solve_upper(Rg.T[::-1, ::-1], c[::-1])[::-1]
    second = apply_q(V, jnp.zeros_like(v).at[:n].set(u)) * w
    return r, first - second


def arx_criterion(x, pv, weights, order: int = AR_ORDER):
    r"""The residual sum of squares of $PV_t$ regressed on a level, $PV_{t-1}, \ldots,
    PV_{t-order}$ and $x_{t-1}, \ldots, x_{t-order}$ (the valve path), over the
    samples `ar_residual` uses."""
    return arx_criteria(pv, weights, order)(x)


def arx_criteria(pv, weights, order: int = AR_ORDER):
    """`arx_criterion` as a function of the valve path alone, for many paths against
    one record: PV's own regressors (the level and PV's lags) are factored once, and
    each path's lags are projected off them and factored alone (half the work of
    factoring all the regressors again for every path)."""
    w = _ar_weights(weights, order)
    V1, _ = householder(_ar_regressors(pv, order) * w[:, None])
    n1 = order + 1

    def off(u):  # Q1^T u with the part in the span of PV's regressors removed
        return apply_qt(V1, u).at[:n1].set(0.0)

    y = off(pv * w)

    def criterion(x):
        Z = jax.vmap(off, in_axes=1, out_axes=1)(lagged(x, order) * w[:, None])
        V2, _ = householder(Z)
        return jnp.sum(apply_qt(V2, y)[order:] ** 2)

    return criterion


def polish_valve(model: LoopModel, op, pv, mask, initial: InitialState, *, order: int = AR_ORDER) -> LoopModel:
    """`model` with its Kano valve's S and J searched on a fine grid around the fit
    (see the module notes), by `arx_criterion` on the valve path from `initial`.
    The fit's own point is on the grid, so the criterion never rises. Pure and
    vmappable."""
    dtype = op.dtype
    w = (mask > 0).astype(dtype) * (jnp.arange(op.shape[0]) >= SKIP)
    kano = model.chain[0]
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)

    criterion = arx_criteria(pv, w, order)

    def crit(S, J):
        c = criterion(with_valve(model, S, J).valve_path(op, initial))
        return jnp.where((S > 0) & jnp.isfinite(c), c, big)

    crits = jax.vmap(crit)
    # the fit's own value first, so that a tie keeps it
    ds = jnp.concatenate([jnp.zeros((1,), dtype), S_STEP * jnp.arange(-round(S_SPAN / S_STEP),
                                                                      round(S_SPAN / S_STEP) + 1, dtype=dtype)])
    dj = jnp.concatenate([jnp.zeros((1,), dtype), J_STEP * jnp.arange(-round(J_SPAN / J_STEP),
                                                                      round(J_SPAN / J_STEP) + 1, dtype=dtype)])
    S, J = jnp.asarray(kano.S, dtype), jnp.asarray(kano.J, dtype)
    for _ in range(ROUNDS):
        Ss = S + ds
        S = Ss[first_min(crits(Ss, jnp.minimum(J, Ss)))]
        J = jnp.minimum(J, S)
        Js = jnp.clip(J + dj, 0.0, S)
        J = Js[first_min(crits(jnp.full_like(Js, S), Js))]
    return with_valve(model, S, J)


def _shifted(model: LoopModel, k: int):
    """`(model, valid)`: the process with its dead time changed by `k` samples (its
    B moved along; valid while B stays strictly proper and inside its array)."""
    b, a = model.process.polynomials()
    nz = b != 0
    if k < 0:
        valid = ~jnp.any(nz[: 1 - k])
    elif k > 0:
        valid = ~jnp.any(nz[b.shape[0] - k:])
    else:
        valid = jnp.asarray(True)
    return with_process(model, jnp.roll(b, k), a), valid


def arx_starts(model: LoopModel, x, pv, weights, shifts=(-2, -1, 0, 1, 2), *, order: int = AR_ORDER,
               difference: bool = False):
    """`(models, valid)`: starts for `refine_process` that do not hang on the fit's
    process. A high-order ARX of PV on its own past and the valve path `x` (order
    `order`, a level, by QR over `weights`; with `difference`, of their first
    differences, the same transfer function) is simulated without noise from `x`;
    the fit's process structure, its dead time moved by each of `shifts`, is fitted
    to that noise-free output by equation error (least squares, QR). `valid`: the
    shifted structure fits in B's array, and the ARX and the start are stable. Pure
    and vmappable; stacked along a leading axis of `len(shifts)`."""
    dtype = pv.dtype
    b0, a0 = model.process.polynomials()
    nb, na = b0.shape[0], a0.shape[0] - 1
    w = _ar_weights(weights, order + 1 if difference else order)
    yy, xx = (jnp.diff(pv, prepend=pv[:1]), jnp.diff(x, prepend=x[:1])) if difference else (pv, x)
    X = jnp.concatenate([jnp.ones_like(pv)[:, None], lagged(yy, order), lagged(xx, order)], axis=1)
    th = lstsq(X * w[:, None], yy * w)
    A = jnp.concatenate([jnp.ones((1,), dtype), -th[1:order + 1]])
    B = jnp.concatenate([jnp.zeros((1,), dtype), th[order + 1:]])
    u = x - x[0]
    y = lfilter(B, A, u)
    arx_ok = is_stable(A, margin=-1e-3) & jnp.all(jnp.isfinite(y))
    y = jnp.where(arx_ok, y, 0.0)
    ww = _ar_weights(weights, max(nb, na))
    ys = lagged(y, na) * (a0[1:] != 0)[None, :]
    xs = jnp.concatenate([u[:, None], lagged(u, nb - 1)], axis=1)
    starts, valid = [], []
    for k in shifts:
        shifted, fits = _shifted(model, k)
        support = shifted.process.polynomials()[0] != 0
        Z = jnp.concatenate([jnp.ones_like(y)[:, None], -ys, xs * support[None, :]], axis=1)
        c = lstsq(Z * ww[:, None], y * ww)
        a = jnp.concatenate([jnp.ones((1,), dtype), c[1:na + 1]])
        b = c[na + 1:] * support
        ok = fits & arx_ok & is_stable(a, margin=-1e-3) & jnp.all(jnp.isfinite(c))
        starts.append(with_process(model, jnp.where(ok, b, b0), jnp.where(ok, a, a0)))
        valid.append(ok)
    return stack_trees(*starts), jnp.stack(valid)


def refine_process(model: LoopModel, op, pv, mask, initial: InitialState, *, order: int = AR_ORDER,
                   max_steps: int = 40):
    """`(model, refined, result, loss)`: `model` with its process refitted (see the
    module notes), whether the refit was kept, the solver's result code and the
    criterion of the model returned. Pure and vmappable; a refit that fails leaves
    `model` as it was."""
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

    # the valve is not refitted: its path is computed once
    x = model.valve_path(op, initial)

    def resid(z, _):
        m = at(z)
        v = jnp.where(w > 0, pv - m.process_output(x, _restarted(m, x, initial)), 0.0)
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
    return out, keep, sol.result, jnp.where(keep, loss, loss0)


# a candidate whose repaired replay's error exceeds the record's by this factor has
# run away (an OP that bangs between its limits), and is not kept
RUNAWAY_FACTOR = 3.0


def _start(model: LoopModel, op, initial: InitialState) -> InitialState:
    """`initial` with the process filter at rest for the first valve position (as
    `refine_process` restarts it: it changes the process, so the fit's filter state
    no longer applies)."""
    return _restarted(model, model.valve_path(op[:1], initial), initial)


def _restarted(model: LoopModel, x, initial: InitialState) -> InitialState:
    """`initial` with the process filter at rest for the valve path `x`'s first
    position."""
    b, a = model.process.polynomials()
    return eqx.tree_at(lambda i: i.filter, initial, steady_state(b, a, x[0] - model.op_offset))


def _repaired_error(model: LoopModel, op, pv, weights, sp_sim, sp_stat, controller: Controller,
                    initial: InitialState):
    """The standard deviation of SP − PV over `weights` in the loop repaired (a linear
    valve) under `controller`, driven by `model`'s disturbance on the record: a
    cheap replay from `initial`, to catch a model whose repaired loop runs away."""
    dtype = op.dtype
    sp_sim, sp_stat = jnp.asarray(sp_sim, dtype), jnp.asarray(sp_stat, dtype)
    start = _start(model, op, initial)
    v = jnp.where(weights > 0, pv - model.simulate(op, start), 0.0)
    run = closed_loop(with_valve(model, jnp.zeros((), dtype), jnp.zeros((), dtype)), controller, sp_sim, v, start,
                      op[0])
    return _error_std(run.pv, sp_stat, weights)


def _error_std(pv, sp, weights):
    """The standard deviation of `sp − pv` over `weights`."""
    count = jnp.maximum(jnp.sum(weights), 1.0)
    e = sp - pv
    return jnp.sqrt(jnp.sum(weights * (e - jnp.sum(weights * e) / count) ** 2) / count)


def refit_for_replay(model: LoopModel, op, pv, mask, controller: Controller, sp_sim, sp_stat, init_count: int, *,
                     polish: bool = True) -> LoopModel:
    """`model` made ready for the replay (see the module notes): its process refitted
    on the fit's valve path and, with `polish`, also on the polished valve's path,
    from the fit's process at the fitted dead time and one sample either side and
    from `arx_starts` (of the levels at five dead times, of the first differences at
    the fitted one). With `polish`, the least
    criterion is kept (the earlier candidate on a tie) among the refits whose loop
    repaired under `controller` (setpoint `sp_sim`, error read against `sp_stat`: see
    `setpoints`) does not run away; without it, the one refit is. Pure and
    vmappable."""
    initial, _ = initial_and_sync(model, op, pv, mask, init_count)
    fitted = with_process(model, *model.process.polynomials())
    plain, _, _, loss = refine_process(fitted, op, pv, mask, initial)
    if not polish:  # one candidate: nothing to choose between
        return plain
    polished = polish_valve(model, op, pv, mask, initial)
    start, _ = initial_and_sync(polished, op, pv, mask, init_count)
    shifted = [_shifted(polished, k) for k in (0, -1, 1)]
    w = (mask > 0).astype(op.dtype) * (jnp.arange(op.shape[0]) >= SKIP)
    x_pol = polished.valve_path(op, start)
    from_arx, arx_valid = arx_starts(polished, x_pol, pv, w)
    from_d, d_valid = arx_starts(polished, x_pol, pv, w, shifts=(0,), order=4, difference=True)
    from_arx = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), from_arx, from_d)
    arx_valid = jnp.concatenate([arx_valid, d_valid])
    # an ARX start can be far from the polished process, whose best initial valve
    # state need not be its own
    arx_initial = jax.vmap(lambda m: initial_and_sync(m, op, pv, mask, init_count)[0])(from_arx)
    candidates = jax.tree.map(lambda s, a: jnp.concatenate([s, a]), stack_trees(*[m for m, _ in shifted]), from_arx)
    n_shifted = len(shifted)
    starts = jax.tree.map(lambda i, s, a: jnp.concatenate([i[None], jnp.broadcast_to(s, (n_shifted,) + s.shape), a]),
                          initial, start, arx_initial)
    # one candidate at a time: Levenberg–Marquardt takes from 5 to 40 steps by
    # candidate, and a vmapped solve runs every member to the slowest one's count
    # (0.76 s against 0.48 s for eight candidates, one 1500-sample loop)
    outs, _, _, losses = jax.lax.map(lambda mi: refine_process(mi[0], op, pv, mask, mi[1]),
                                     (candidates, jax.tree.map(lambda t: t[1:], starts)))
    # the candidates: the fit's valve, then the polished one at three dead times
    # from the fit's process, at five from the levels' ARX and at one from the
    # differences'
    models = jax.tree.map(lambda p, o: jnp.concatenate([p[None], o]), plain, outs)
    losses = jnp.concatenate([loss[None], losses])
    valid = jnp.concatenate([jnp.stack([jnp.asarray(True)] + [v for _, v in shifted]), arx_valid])
    recorded = _error_std(pv, sp_stat, w)
    repaired = jax.vmap(lambda m, i0: _repaired_error(m, op, pv, w, sp_sim, sp_stat, controller, i0))(models, starts)
    ok = valid & jnp.isfinite(losses) & ~(repaired > RUNAWAY_FACTOR * recorded)
    losses = jnp.where(ok, losses, jnp.inf)
    chosen = jax.tree.map(lambda t: t[first_min(losses)], models)
    # no candidate qualifies: the fit as it is
    return jax.tree.map(lambda c, m: jnp.where(jnp.any(jnp.isfinite(losses)), c, m), chosen, fitted)
