"""The model made ready for the replay (`jaxstiction._whatif.refine`): its two
criteria against plain least-squares references, the valve polish and the process
refit recovering a plant from wrong starts, the repaired replay that guards the
choice, and vmap against single calls."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from test_whatif import _plant_loop, KI, KP, reference_loop

from jaxstiction import Controller
from jaxstiction._filters import lagged
from jaxstiction._whatif.refine import _projected_out, _repaired_error, _start, arx_criteria, SKIP
from jaxstiction._whatif.replay import setpoints
from jaxstiction.internal import (
    ar_residual,
    arx_criterion,
    arx_starts,
    initial_and_sync,
    polish_valve,
    refine_process,
    refit_for_replay,
    with_process,
    with_valve,
)


def _reference_residual(v, weights, order):
    """The same regression, row by row with numpy's lstsq."""
    n = len(v)
    rows = [t for t in range(order, n) if all(weights[t - k] > 0 for k in range(order + 1))]
    X = np.array([[1.0] + [v[t - k] for k in range(1, order + 1)] for t in rows])
    y = v[rows]
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    out = np.zeros(n)
    out[rows] = y - X @ coef
    return out


def test_ar_residual_matches_a_plain_least_squares():
    rng = np.random.default_rng(0)
    n = 300
    v = np.cumsum(rng.standard_normal(n)) * 0.1 + 5.0 + rng.standard_normal(n)
    weights = np.ones(n)
    weights[:20] = 0.0
    weights[150:160] = 0.0  # a gap: rows whose lags fall in it are left out too
    weights[-30:] = 0.0  # padding
    got = np.asarray(ar_residual(jnp.asarray(v), jnp.asarray(weights), 4))
    np.testing.assert_allclose(got, _reference_residual(v, weights, 4), atol=1e-9)


def test_arx_criterion_matches_a_plain_least_squares():
    rng = np.random.default_rng(1)
    n, order = 300, 3
    x = np.cumsum(rng.standard_normal(n))
    pv = np.convolve(x, [0.0, 0.5, 0.3])[:n] + rng.standard_normal(n)
    weights = np.ones(n)
    weights[:10] = 0.0
    weights[-20:] = 0.0
    rows = [t for t in range(order, n) if all(weights[t - k] > 0 for k in range(order + 1))]
    X = np.array([[1.0] + [pv[t - k] for k in range(1, order + 1)] + [x[t - k] for k in range(1, order + 1)]
                  for t in rows])
    coef, *_ = np.linalg.lstsq(X, pv[rows], rcond=None)
    want = np.sum((pv[rows] - X @ coef) ** 2)
    got = float(arx_criterion(jnp.asarray(x), jnp.asarray(pv), jnp.asarray(weights), order))
    assert got == pytest.approx(want, rel=1e-9)


def test_arx_criteria_of_many_paths_match_the_full_regression():
    """The grid's form (PV's regressors factored once, vmapped over paths) against
    `arx_criterion`'s single regression on every regressor, path by path."""
    rng = np.random.default_rng(2)
    n, order = 400, 4
    pv = jnp.asarray(np.cumsum(rng.standard_normal(n)) * 0.2 + rng.standard_normal(n))
    weights = jnp.asarray(np.r_[np.zeros(15), np.ones(n - 40), np.zeros(25)])
    paths = jnp.asarray(np.round(np.cumsum(rng.standard_normal((5, n)), axis=1)))  # held, stepping valves
    got = jax.vmap(arx_criteria(pv, weights, order))(paths)
    for k in range(5):
        X = jnp.concatenate([jnp.ones((n, 1)), lagged(pv, order), lagged(paths[k], order)], axis=1)
        want = float(jnp.sum(_projected_out(X, pv, weights, order) ** 2))
        assert float(got[k]) == pytest.approx(want, rel=1e-9)


def test_ar_residual_derivative_is_autodiff_through_the_factorisation():
    """`ar_residual`'s closed-form derivative against JAX differentiating the QR
    itself (the plain regression), against central differences, and under vmap; on
    a record with gaps, and finite where no lag is left to fit."""
    rng = np.random.default_rng(3)
    n, order = 300, 4
    v = jnp.asarray(np.cumsum(rng.standard_normal(n)) * 0.1 + 5.0 + rng.standard_normal(n))
    w = np.ones(n)
    w[:20], w[150:160], w[-30:] = 0.0, 0.0, 0.0
    w = jnp.asarray(w)
    dv = jnp.asarray(rng.standard_normal(n))

    def plain(u):
        X = jnp.concatenate([jnp.ones((n, 1)), lagged(u, order)], axis=1)
        return _projected_out(X, u, w, order)

    value, tangent = jax.jvp(lambda u: ar_residual(u, w, order), (v,), (dv,))
    ref_value, ref_tangent = jax.jvp(plain, (v,), (dv,))
    np.testing.assert_allclose(np.asarray(value), np.asarray(ref_value), atol=1e-12)
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(ref_tangent), atol=1e-10)
    eps = 1e-6
    central = (ar_residual(v + eps * dv, w, order) - ar_residual(v - eps * dv, w, order)) / (2 * eps)
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(central), atol=1e-6)
    grad = jax.grad(lambda u: jnp.sum(ar_residual(u, w, order) ** 2))(v)
    ref_grad = jax.grad(lambda u: jnp.sum(plain(u) ** 2))(v)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(ref_grad), atol=1e-10)
    batched = jax.vmap(lambda a, b: jax.jvp(lambda u: ar_residual(u, w, order), (a,), (b,))[1])(
        jnp.stack([v, 2 * v + 1]), jnp.stack([dv, -dv]))
    np.testing.assert_allclose(np.asarray(batched[0]), np.asarray(tangent), atol=1e-12)
    flat = jax.jvp(lambda u: ar_residual(u, w, order), (jnp.zeros(n),), (dv,))[1]
    assert bool(jnp.all(jnp.isfinite(flat)))


def _prepared(model, loop):
    op, pv = jnp.asarray(loop.op), jnp.asarray(loop.pv)
    w = (jnp.asarray(loop.mask) > 0).astype(op.dtype)
    initial, _ = initial_and_sync(model, op, pv, w, 8)
    return op, pv, w, initial


def test_polish_finds_the_band_a_fit_missed_by_a_tenth():
    """A valve whose S is a tenth low and J half a percent off slips samples early;
    the polish finds S to its grid step and never raises its criterion."""
    plant, loop, _, _ = _plant_loop(3, S=4.0, J=1.5)
    off = with_valve(plant, jnp.asarray(3.88), jnp.asarray(2.0))
    op, pv, w, initial = _prepared(off, loop)
    polished = polish_valve(off, op, pv, w, initial)
    assert float(polished.chain[0].S) == pytest.approx(4.0, abs=0.021)
    assert abs(float(polished.chain[0].J) - 1.5) < abs(2.0 - 1.5)
    ws = w * (jnp.arange(op.shape[0]) >= SKIP)

    def crit(m):
        return float(arx_criterion(m.valve_path(op, initial), pv, ws))

    assert crit(polished) <= crit(off)


PI = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))


def _ready(model, loop, ctrl, polish=True):
    op, pv, w, _ = _prepared(model, loop)
    sp_sim, sp_stat, _ = setpoints(loop, ctrl)
    return refit_for_replay(model, op, pv, w, ctrl, sp_sim, sp_stat, 8, polish=polish)


def test_repaired_error_is_the_linear_plant_s():
    """The cheap repaired replay of the plant's own model is the plant run with a
    linear valve under the same noise and setpoint; under a PI ten times too tight
    it runs away."""
    plant, loop, sp, v = _plant_loop(3, S=4.0, J=1.5)
    op, pv, w, initial = _prepared(plant, loop)
    sp_sim, sp_stat, _ = setpoints(loop, PI)
    ws = w * (jnp.arange(op.shape[0]) >= SKIP)
    got = float(_repaired_error(plant, op, pv, ws, sp_sim, sp_stat, PI, initial))
    _, _, _, pv_lin = reference_loop(0.0, 0.0, KP, KI, sp, v)
    want = float(np.std((sp - pv_lin)[SKIP:]))
    assert got == pytest.approx(want, rel=0.05)
    tight = Controller(kp=jnp.asarray(10 * KP), ki=jnp.asarray(10 * KI))
    assert not float(_repaired_error(plant, op, pv, ws, sp_sim, sp_stat, tight, initial)) < 10 * want


def test_refit_for_replay_undoes_a_dead_time_traded_for_a_low_band():
    """A fit that took a dead time of 2 for 1 with S a tenth low: the valve polish
    and the dead-time choice give the plant's dead time back; without the polish the
    dead time stays."""
    plant, loop, _, _ = _plant_loop(3, S=4.0, J=1.5)
    b, a = (jnp.concatenate([p, jnp.zeros(2)]) for p in plant.process.polynomials())
    traded = with_valve(with_process(plant, jnp.roll(b, 1), a), jnp.asarray(3.88), jnp.asarray(1.5))
    op, pv, w, _ = _prepared(traded, loop)
    ready = _ready(traded, loop, PI)
    b_ready = np.asarray(ready.process.polynomials()[0])
    assert b_ready[0] == 0 and abs(b_ready[1]) > 0.5
    # every S whose slips fall on the same samples ties; on 500 samples that spans
    # a few hundredths here
    assert float(ready.chain[0].S) == pytest.approx(4.0, abs=0.06)
    plain = _ready(traded, loop, PI, polish=False)
    assert float(plain.chain[0].S) == pytest.approx(3.88) and np.asarray(plain.process.polynomials()[0])[1] == 0


def _wrong(plant):
    """The plant with the kind of process a light fit finds on a tight loop: the
    resonance of A lost (a = [1, -0.8, 0.1] for [1, -1.5, 0.7]), B rescaled."""
    b, a = plant.process.polynomials()
    return with_process(plant, b * 0.4, jnp.asarray([1.0, -0.8, 0.1]))


def _refit(model, loop):
    op, pv = jnp.asarray(loop.op), jnp.asarray(loop.pv)
    w = (jnp.asarray(loop.mask) > 0).astype(op.dtype)
    initial, _ = initial_and_sync(model, op, pv, w, 8)
    return refine_process(model, op, pv, w, initial)[:3]


def _criterion(model, loop, initial_from):
    """The refit's criterion for `model`'s process, on the valve path of
    `initial_from`'s best initial state."""
    op, pv = jnp.asarray(loop.op), jnp.asarray(loop.pv)
    w = (jnp.asarray(loop.mask) > 0).astype(op.dtype)
    initial, _ = initial_and_sync(initial_from, op, pv, w, 8)
    ws = w * (jnp.arange(op.shape[0]) >= SKIP)
    v = jnp.where(ws > 0, pv - model.simulate(op, _start(model, op, initial)), 0.0)
    return float(jnp.sum(ar_residual(v, ws) ** 2))


def test_refine_recovers_the_process_from_a_wrong_start():
    """Under a load that wanders at the process input, the refit finds the plant's
    A and B again (to the precision 500 samples allow), starting from a process that
    lost A's resonance, at a criterion within a few percent of the plant's own (a
    local search: here it stops 4 % above it); a start at the plant itself stays
    near it."""
    plant, loop, _, _ = _plant_loop(3)
    wrong = _wrong(plant)
    refined, kept, result = _refit(wrong, loop)
    assert bool(kept) and result == optx.RESULTS.successful
    b, a = refined.process.polynomials()
    np.testing.assert_allclose(np.asarray(a)[:3], [1.0, -1.5, 0.7], atol=0.1)
    np.testing.assert_allclose(np.asarray(b)[1:3], [1.0, 0.5], atol=0.2)
    start = _criterion(wrong, loop, wrong)
    assert _criterion(refined, loop, wrong) <= 1.1 * _criterion(plant, loop, wrong) < 0.5 * start
    at_plant, _, _ = _refit(plant, loop)
    for got, want in zip(at_plant.process.polynomials(), plant.process.polynomials()):
        np.testing.assert_allclose(np.asarray(got)[:3], np.asarray(want)[:3], atol=0.1)


def _reference_starts(x, pv, weights, b0, a0, shifts, order, levels=None, level_weights=None):
    """`arx_starts` row by row with numpy's lstsq and scipy's lfilter (the ARX on
    `x` and `pv` over `weights`, simulated on `levels` and the structure fitted over
    `level_weights`, by default `x` and `weights`)."""
    from scipy.signal import lfilter as sp_lfilter

    n, nb, na = len(pv), len(b0), len(a0) - 1

    def rows(lags):
        return [t for t in range(lags, n) if all(weights[t - k] > 0 for k in range(lags + 1))]

    r = rows(order)
    X = np.array([[1.0] + [pv[t - k] for k in range(1, order + 1)] + [x[t - k] for k in range(1, order + 1)]
                  for t in r])
    th, *_ = np.linalg.lstsq(X, pv[r], rcond=None)
    levels = x if levels is None else levels
    u = levels - levels[0]
    y = sp_lfilter(np.r_[0.0, th[order + 1:]], np.r_[1.0, -th[1:order + 1]], u)
    if level_weights is not None:
        weights = level_weights
    r = rows(max(nb, na))
    out = []
    for k in shifts:
        support = np.roll(b0 != 0, k)
        lags = [j for j in range(nb) if support[j]]
        Z = np.array([[1.0] + [-y[t - i] for i in range(1, na + 1)] + [u[t - j] for j in lags] for t in r])
        c, *_ = np.linalg.lstsq(Z, y[r], rcond=None)
        b = np.zeros(nb)
        b[lags] = c[na + 1:]
        out.append((b, np.r_[1.0, c[1:na + 1]]))
    return out


def test_arx_starts_match_a_plain_least_squares():
    """The ARX and the equation-error fits of each shifted structure, against numpy
    and scipy row by row; a shift that pushes B out of its array is not valid."""
    plant, loop, _, _ = _plant_loop(3)
    b, a = plant.process.polynomials()
    model = with_process(plant, jnp.concatenate([b, jnp.zeros(2)]), a)  # b = [0, 1, 0.5, 0, 0]
    op, pv, w, initial = _prepared(model, loop)
    w = w.at[200:210].set(0.0)  # a gap: rows whose lags fall in it are left out too
    x = model.valve_path(op, initial)
    shifts = (-2, -1, 0, 1, 2)
    starts, valid = arx_starts(model, x, pv, w, shifts, order=6)
    assert np.asarray(valid).tolist() == [False, False, True, True, True]  # B stays strictly proper
    want = _reference_starts(np.asarray(x), np.asarray(pv), np.asarray(w), np.asarray(model.process.polynomials()[0]),
                             np.asarray(a), shifts, 6)
    got_b, got_a = (np.asarray(p) for p in jax.vmap(lambda m: m.process.polynomials())(starts))
    for i in range(2, 5):
        np.testing.assert_allclose(got_b[i], want[i][0], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(got_a[i][:3], want[i][1], rtol=1e-6, atol=1e-9)
        assert not np.any(got_a[i][3:])  # A's padding stays fixed at 0
    # at the plant's dead time the start is the plant, to the precision the noisy
    # closed-loop record allows
    np.testing.assert_allclose(got_a[2][:3], [1.0, -1.5, 0.7], atol=0.1)
    np.testing.assert_allclose(got_b[2][1:3], [1.0, 0.5], atol=0.25)


def test_refit_for_replay_recovers_a_gain_the_fit_lost():
    """A fit whose process lost A's resonance and 70 % of its gain, with a dead time
    a sample too long besides: the refits started from it stay near its gain (2.1
    for the plant's 7.5); the start from the ARX, with its own initial valve state,
    gives the replay a model within a quarter of the plant's gain (500 samples, and
    the polished J 2.1 for the valve's 1.5: the plant's process refitted at that
    valve has 5.4)."""
    plant, loop, _, _ = _plant_loop(3, S=4.0, J=1.5)
    b, a = plant.process.polynomials()
    b = jnp.concatenate([b, jnp.zeros(2)])
    wrong = with_process(plant, jnp.roll(b, 1) * 0.3, jnp.asarray([1.0, -0.8, 0.1]))
    gain = float(jnp.sum(b) / jnp.sum(a))
    ready = _ready(wrong, loop, PI)
    b_r, a_r = ready.process.polynomials()
    assert float(jnp.sum(b_r) / jnp.sum(a_r)) == pytest.approx(gain, rel=0.3)
    assert np.asarray(b_r)[0] == 0 and abs(float(b_r[1])) > 0.5


def test_refine_vmap_equals_single_calls():
    models, loops = [], []
    for seed in (4, 5):
        plant, loop, _, _ = _plant_loop(seed)
        models.append(_wrong(plant))
        loops.append(loop)
    stacked = jax.tree.map(lambda *t: jnp.stack(t), *models)
    lstack = jax.tree.map(lambda *t: jnp.stack(t), *loops)
    batched = eqx.filter_vmap(_refit)(stacked, lstack)
    for i, (m, lp) in enumerate(zip(models, loops)):
        one = _refit(m, lp)
        got = jax.tree.map(lambda t: t[i], batched)
        assert bool(got[1]) == bool(one[1])
        for g, o in zip(got[0].process.polynomials(), one[0].process.polynomials()):
            np.testing.assert_allclose(np.asarray(g), np.asarray(o), rtol=1e-7, atol=1e-9)


def test_differenced_arx_start_matches_a_plain_least_squares():
    """With `difference`, the ARX is fitted to PV's and the valve path's first
    differences (the same transfer function) and simulated on the levels, against
    numpy and scipy row by row; on the plant's loop it is near the plant."""
    plant, loop, _, _ = _plant_loop(3)
    b, a = plant.process.polynomials()
    model = with_process(plant, jnp.concatenate([b, jnp.zeros(2)]), a)
    op, pv, w, initial = _prepared(model, loop)
    w = w.at[200:210].set(0.0)
    x = model.valve_path(op, initial)
    starts, valid = arx_starts(model, x, pv, w, (0,), order=4, difference=True)
    assert np.asarray(valid).tolist() == [True]
    xn, pvn, wn = np.asarray(x), np.asarray(pv), np.asarray(w)
    # differences of samples next to a gap are left out: one more lag of weights
    wd = wn * np.r_[0.0, wn[:-1]]
    dx, dpv = np.diff(xn, prepend=xn[0]), np.diff(pvn, prepend=pvn[0])
    want = _reference_starts(dx, dpv, wd, np.asarray(model.process.polynomials()[0]), np.asarray(a), (0,), 4,
                             levels=xn, level_weights=wn)
    got_b, got_a = (np.asarray(p)[0] for p in jax.vmap(lambda m: m.process.polynomials())(starts))
    np.testing.assert_allclose(got_b, want[0][0], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(got_a[:3], want[0][1], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(got_a[:3], [1.0, -1.5, 0.7], atol=0.1)
    np.testing.assert_allclose(got_b[1:3], [1.0, 0.5], atol=0.25)
