import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxstiction import make_scenario
from jaxstiction.internal import (
    ARXHammerstein,
    direction,
    hysteresis_regressors,
    lag_gram,
    relax,
    relax_init,
    relax_loss,
    relax_problem,
    relax_sweep,
    scale_input,
    spline_basis,
    uniform_knots,
)


try:
    from tests import reference as ref
except ImportError:  # pytest with tests/ on sys.path
    import reference as ref


N, ORDER, KNOTS = 600, 6, 4  # one shape for most tests, so compilations are shared
TIGHT = dict(rtol=1e-12, atol=1e-14, max_steps=2000)


def _regressors(op, m=KNOTS):
    op = np.asarray(op, float)
    u = scale_input(jnp.asarray(op), op.min(), op.max())
    return u, hysteresis_regressors(u, direction(u), uniform_knots(m, jnp.float64))


def _loop(rec, start):
    """A length-N window of a simulated record: scaled y and spline regressors."""
    op = np.asarray(rec.op)[start : start + N]
    pv = np.asarray(rec.pv)[start : start + N]
    y = (pv - pv.mean()) / pv.std()
    _, phi = _regressors(op)
    return jnp.asarray(y), phi


@pytest.fixture(scope="module")
def loops():
    """Three different noisy closed loops with Kano stiction (paper_sim windows)."""
    sc = make_scenario("paper_sim")
    return [
        _loop(sc.estimation, 0),
        _loop(sc.estimation, 900),
        _loop(sc.validation, 300),
    ]


@pytest.fixture(scope="module")
def loop(loops):
    return loops[0]


def _synthetic(n_true=ORDER, seed=0):
    """Noise-free open-loop Hammerstein system that lies exactly in the model set:
    smooth OP, a two-branch spline valve in the same basis, an order-`n_true` ARX
    process. Returns (y, phi, x_true, a_true, b_true)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N)
    op = sum(
        rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * t / per + rng.uniform(0, 2 * np.pi))
        for per in (97.0, 61.0, 37.0, 23.0)
    )
    u, phi = _regressors(op)
    u = np.asarray(u)
    # ascent branch shifted right of the descent branch (a hysteresis loop)
    half = KNOTS + 2
    beta1 = np.zeros(half)
    beta2 = np.zeros(half)
    beta1[: KNOTS - 2] = [0.3, -0.2]
    beta1[KNOTS - 2 :] = [-0.2, 0.9, 0.1, 0.2]
    beta2[: KNOTS - 2] = [-0.1, 0.25]
    beta2[KNOTS - 2 :] = [0.2, 1.0, -0.1, 0.1]
    beta_true = np.concatenate([beta1, beta2])
    x = np.asarray(phi) @ beta_true
    poles = np.array([0.9, 0.7 + 0.2j, 0.7 - 0.2j, 0.5, -0.3, 0.2])[:n_true]
    A = np.real(np.poly(poles))  # [1, a_1..a_n]
    b_true = np.array([0.5, 0.3, -0.1, 0.05, 0.02, 0.01])[:n_true]
    y = np.zeros(N)
    for k in range(N):
        y[k] = sum(b_true[i - 1] * x[k - i] for i in range(1, n_true + 1) if k - i >= 0)
        y[k] -= sum(A[i] * y[k - i] for i in range(1, n_true + 1) if k - i >= 0)
    return jnp.asarray(y), phi, x, A[1:], b_true


# ----------------------------------------------------------------- spline layer


def test_spline_basis_matches_numpy():
    rng = np.random.default_rng(1)
    u = np.concatenate([rng.uniform(-1, 1, 50), [-1.0, 1.0, 0.0]])
    for m in (3, 4, 6):
        knots = uniform_knots(m, jnp.float64)
        np.testing.assert_allclose(knots, ref.uniform_knots(m), rtol=0, atol=1e-15)
        np.testing.assert_allclose(
            spline_basis(jnp.asarray(u), knots),
            ref.spline_basis(u, ref.uniform_knots(m)),
            rtol=1e-13,
            atol=1e-14,
        )


def test_direction_and_regressors_match_numpy():
    rng = np.random.default_rng(2)
    op = np.cumsum(rng.normal(size=300)) + 0.05 * rng.normal(size=300)
    op[10:15] = op[9]  # ties: the literal rule counts them as rising
    u = scale_input(jnp.asarray(op), op.min(), op.max())
    u_np = ref.scale_input(op, op.min(), op.max())
    np.testing.assert_allclose(u, u_np, rtol=0, atol=1e-14)
    assert float(u.min()) == -1.0 and float(u.max()) == 1.0
    np.testing.assert_array_equal(direction(u), ref.direction(u_np))
    for thr in (0.05, 0.2):
        np.testing.assert_array_equal(
            direction(u, threshold=thr), ref.direction(u_np, thr)
        )
    h = ref.direction(u_np)
    phi = hysteresis_regressors(u, jnp.asarray(h), uniform_knots(5, jnp.float64))
    np.testing.assert_allclose(
        phi,
        ref.hysteresis_regressors(u_np, h, ref.uniform_knots(5)),
        rtol=1e-13,
        atol=1e-14,
    )


# ----------------------------------------------------------------- relaxation


def _fit(y, phi):
    return relax(relax_problem(y, phi, ORDER), **TIGHT)


# The jitted fit every test shares. Its trace count is checked within one test
# (`test_no_retrace_for_new_data`), not across tests: between tests the suite may
# clear JAX's caches (conftest's `_release_compiled_programs`), which retraces it.
fit_tight = eqx.filter_jit(_fit)
problem = jax.jit(relax_problem, static_argnums=2)
loss_of = jax.jit(relax_loss)


@pytest.fixture(scope="module")
def reference_fit(loop):
    y, phi = loop
    r = ref.relax_reference(y, phi, ORDER, **TIGHT)
    assert r.converged
    return r


@eqx.filter_jit
def _fixed_point_no_ridge(y, phi):
    """The alternation of `relax`, with plain least squares in both steps, on the
    backward-stable (Householder QR) compression."""
    prob = relax_problem(y, phi, ORDER, method="qr")
    sweep = lambda m, pr: relax_sweep(m, pr, ridge=0.0)
    init = sweep(relax_init(prob), prob)
    sol = optx.fixed_point(
        sweep,
        optx.FixedPointIteration(rtol=TIGHT["rtol"], atol=TIGHT["atol"]),
        init,
        prob,
        max_steps=TIGHT["max_steps"],
        throw=False,
    )
    return sol.value, relax_loss(sol.value, prob), sol.stats["num_steps"], sol.result


def _assert_same_fit(model, loss, r, phi, *, xtol, ptol, losstol):
    np.testing.assert_allclose(float(loss), r.loss, rtol=losstol)
    np.testing.assert_allclose(
        np.asarray(phi) @ np.asarray(model.beta),
        np.asarray(phi) @ r.beta,
        rtol=0,
        atol=xtol,
    )
    np.testing.assert_allclose(model.a, r.a, rtol=0, atol=ptol)
    np.testing.assert_allclose(model.b, r.b, rtol=0, atol=ptol)


def _ok(result):
    return np.asarray(result == optx.RESULTS.successful)


def test_relaxation_algorithm_matches_reference(loop, reference_fit):
    """The compressed iteration (QR of [Z y], steps (15)/(16), normalisation, optx
    stopping rule) reproduces the full-data NumPy relaxation, once the Tikhonov rows
    are switched off. The sweep count may differ by one: the two QR factorisations
    (Householder in JAX, LAPACK in NumPy) round differently at 1e-16, which can move
    the stopping test across its threshold by one sweep."""
    y, phi = loop
    r = reference_fit
    model, loss, steps, result = _fixed_point_no_ridge(y, phi)
    assert _ok(result)
    assert abs(int(steps) - r.num_steps) <= 1
    _assert_same_fit(model, loss, r, phi, xtol=1e-9, ptol=1e-10, losstol=1e-12)
    # x_hat normalised: std 1 over the estimation samples, B(1) >= 0
    x = np.asarray(phi @ model.beta)[ORDER:]
    np.testing.assert_allclose(x.std(), 1.0, rtol=1e-10)
    assert float(jnp.sum(model.b)) >= 0


def test_relax_loss_matches_reference(loop, reference_fit):
    y, phi = loop
    sol = fit_tight(y, phi)
    assert _ok(sol.result)
    np.testing.assert_allclose(float(sol.loss), reference_fit.loss, rtol=1e-6)
    x = np.asarray(phi @ sol.model.beta)[ORDER:]
    np.testing.assert_allclose(x.std(), 1.0, rtol=1e-10)
    assert float(jnp.sum(sol.model.b)) >= 0


RIDGE_BUG = (
    "jaxstiction/_relax.py::_lstsq: the 1e-10 Tikhonov rows are scaled by max|R T| "
    "(~ column norm, grows like sqrt(N)), comparable to the smallest singular value of "
    "the step-(15) matrix, so the fixed point is biased (x_hat off by ~1e-3 here, O(1) "
    "at N=1500, n=10, m=6; wrong a, b on exact noise-free data). See the report."
)


def test_relax_matches_reference(loop, reference_fit):
    """Public `relax` vs the plain least-squares reference: same x_hat, a, b (unique
    thanks to the normalisation)."""
    y, phi = loop
    sol = fit_tight(y, phi)
    _assert_same_fit(
        sol.model, sol.loss, reference_fit, phi, xtol=1e-5, ptol=1e-5, losstol=1e-6
    )


def test_compressed_loss_equals_full_residual(loop):
    y, phi = loop
    prob = problem(y, phi, ORDER)
    rng = np.random.default_rng(3)
    p = phi.shape[1]
    models = [fit_tight(y, phi).model] + [
        ARXHammerstein(
            a=jnp.asarray(0.3 * rng.normal(size=ORDER)),
            b=jnp.asarray(rng.normal(size=ORDER)),
            beta=jnp.asarray(rng.normal(size=p)),
        )
        for _ in range(3)
    ]
    for mod in models:
        direct = ref.arx_loss(
            y, phi, np.asarray(mod.a), np.asarray(mod.b), np.asarray(mod.beta)
        )
        np.testing.assert_allclose(float(loss_of(mod, prob)), direct, rtol=1e-10)
    # zero weights drop samples from the criterion (lags still come from the data)
    w = jnp.ones(N).at[400:].set(0.0)
    probw = problem(y, phi, ORDER, w)
    np.testing.assert_allclose(float(probw.count), 400 - ORDER)
    for mod in models:
        e = ref.arx_residual(
            y, np.asarray(phi @ mod.beta), np.asarray(mod.a), np.asarray(mod.b)
        )
        np.testing.assert_allclose(
            float(loss_of(mod, probw)), np.mean(e[: 400 - ORDER] ** 2), rtol=1e-10
        )


def test_jit_matches_no_jit(loop):
    y, phi = loop
    a = relax(relax_problem(y, phi, ORDER), **TIGHT)
    b = fit_tight(y, phi)
    assert _ok(a.result) and _ok(b.result)
    # op-by-op and fused code round the Gram matrix differently at 1e-16, which can
    # move the tight stopping test across its threshold by one sweep
    assert abs(int(a.num_steps) - int(b.num_steps)) <= 1
    for u, v in zip(jax.tree.leaves(a.model), jax.tree.leaves(b.model)):
        np.testing.assert_allclose(u, v, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(a.loss, b.loss, rtol=1e-10)


def test_vmap_matches_loop_and_isolates_garbage(loops):
    ys = jnp.stack([y for y, _ in loops])
    phis = jnp.stack([phi for _, phi in loops])
    batched = eqx.filter_jit(jax.vmap(_fit))
    out = batched(ys, phis)
    assert np.all(_ok(out.result))
    for i, (y, phi) in enumerate(loops):
        s = fit_tight(y, phi)
        for u, v in zip(jax.tree.leaves(s.model), jax.tree.leaves(out.model)):
            np.testing.assert_allclose(v[i], u, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.loss[i], s.loss, rtol=1e-10)
        assert abs(int(out.num_steps[i]) - int(s.num_steps)) <= 1  # rounding at the stopping threshold
    # A degenerate member (constant OP: every regressor constant, std(x_hat) = 0; the
    # output a sparse pulse train) must not disturb the others.
    phi_const = hysteresis_regressors(
        jnp.zeros(N), jnp.ones(N), uniform_knots(KNOTS, jnp.float64)
    )
    bad = batched(
        ys.at[1].set(jnp.zeros(N).at[::7].set(1.0)), phis.at[1].set(phi_const)
    )
    ok = _ok(bad.result)
    assert ok[0] and ok[2]
    for i in (0, 2):
        for u, v in zip(jax.tree.leaves(out.model), jax.tree.leaves(bad.model)):
            np.testing.assert_allclose(v[i], u[i], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(bad.loss[i], out.loss[i], rtol=1e-10)


def test_no_retrace_for_new_data(loops):
    """New data of the same shape reuse the compiled fit: traced once for every loop."""
    once = eqx.filter_jit(eqx.debug.assert_max_traces(_fit, max_traces=1))
    for y, phi in loops:
        assert _ok(once(y, phi).result)
    y, phi, *_ = _synthetic()
    assert _ok(once(y, phi).result)


# ----------------------------------------------------------------- gradients


def test_grad_wrt_data_matches_finite_differences(loop):
    """Gradients w.r.t. the data flow through `optx.fixed_point`'s implicit adjoint
    (and through the QR of `relax_problem`)."""
    y, phi = loop
    rng = np.random.default_rng(4)
    v = jnp.asarray(rng.normal(size=N))  # direction in data space
    g_x = jnp.asarray(rng.normal(size=N))

    def parts(sol):
        x = phi @ sol.model.beta
        return jnp.stack([sol.loss, jnp.sum(sol.model.b), sol.model.a[0], g_x @ x / N])

    eps = 1e-5
    fd = (parts(fit_tight(y + eps * v, phi)) - parts(fit_tight(y - eps * v, phi))) / (
        2 * eps
    )
    fd = np.asarray(fd)
    assert np.all(np.abs(fd) > 1e-3)  # all four parts are sensitive to y
    # one scalar, weighted so that every part contributes about equally
    c = jnp.asarray(1.0 / np.abs(fd))
    grad = jax.jit(jax.grad(lambda y: c @ parts(_fit(y, phi))))(y)
    np.testing.assert_allclose(float(grad @ v), float(c @ fd), rtol=1e-4)
    assert np.all(np.isfinite(np.asarray(grad)))


# ----------------------------------------------------------------- recovery


def test_parameter_recovery_noise_free():
    """Exact data from a Hammerstein system inside the model set: x_hat is the true
    valve output up to gain and the ARX criterion vanishes."""
    y, phi, x_true, a_true, b_true = _synthetic()
    sol = fit_tight(y, phi)
    assert _ok(sol.result)
    x = np.asarray(phi @ sol.model.beta)
    assert np.corrcoef(x, x_true)[0, 1] > 0.999
    assert float(sol.loss) < 1e-8 * float(jnp.var(y))


def test_parameter_recovery_exact_without_ridge():
    """The same relaxation with plain least squares recovers everything exactly."""
    y, phi, x_true, a_true, b_true = _synthetic()
    model, loss, _, result = _fixed_point_no_ridge(y, phi)
    assert _ok(result)
    s = x_true[ORDER:].std()  # normalisation std(x_hat) = 1 moves the gain into b
    np.testing.assert_allclose(np.asarray(phi @ model.beta), x_true / s, atol=1e-8)
    np.testing.assert_allclose(model.a, a_true, atol=1e-8)
    np.testing.assert_allclose(model.b, b_true * s, atol=1e-8)
    assert float(loss) < 1e-20 * float(jnp.var(y))


def test_parameter_recovery_linear_part():
    y, phi, x_true, a_true, b_true = _synthetic()
    sol = fit_tight(y, phi)
    s = x_true[ORDER:].std()
    # The public solver keeps a 1e-14 Tikhonov term on the column-scaled problem (for
    # masked knots) and stops on rtol; on this ill-conditioned spline basis that
    # leaves ~1e-3 in a, b. The unregularised iteration recovers them to 1e-8 above.
    np.testing.assert_allclose(sol.model.a, a_true, atol=5e-3)
    np.testing.assert_allclose(sol.model.b, b_true * s, atol=5e-3)


# ------------------------------------------------------- faster schemes, same minimum


@eqx.filter_jit
def _fit_with(y, phi, compress, method):
    return relax(relax_problem(y, phi, ORDER, method=compress), method=method, **TIGHT)


def _lag_gram_reference(x, n, w):
    """sum_t w_t x_i(t-k) x_j(t-l), straight from the lagged matrix (NumPy)."""
    N, q = x.shape
    X = np.stack([np.concatenate([np.zeros((k, q)), x[: N - k]]) for k in range(n + 1)], axis=2)
    return np.einsum("t,tik,tjl->ikjl", w, X, X)


def test_lag_gram_matches_the_lagged_matrix():
    """The correlation route (one window of ones: a record, a padded record, an
    estimation window, a single sample) and the direct product (several runs) both
    equal the Gram matrix of the explicitly lagged signals; under `vmap` too."""
    rng = np.random.default_rng(3)
    N, q, n = 120, 3, 4
    x = rng.standard_normal((N, q))
    cases = [(n, N), (n, 90), (17, N), (30, 31), None]
    ws = []
    for case in cases:
        w = np.zeros(N)
        if case is None:
            w[10:40] = 1.0
            w[60:100] = 1.0
        else:
            w[case[0]:case[1]] = 1.0
        ws.append(w)
        want = _lag_gram_reference(x, n, w)
        got = lag_gram(jnp.asarray(x), n, jnp.asarray(w))
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12, atol=1e-12)
        if case is not None:
            fast = lag_gram(jnp.asarray(x), n, jnp.asarray(w), window=True)
            np.testing.assert_allclose(np.asarray(fast), want, rtol=1e-12, atol=1e-12)
    batched = jax.jit(jax.vmap(lambda w: lag_gram(jnp.asarray(x), n, w)))(jnp.asarray(np.stack(ws)))
    for w, got in zip(ws, batched):
        np.testing.assert_allclose(np.asarray(got), _lag_gram_reference(x, n, w), rtol=1e-12, atol=1e-12)


def test_gram_and_qr_compressions_give_the_same_minimum(loops):
    """The Gram/Cholesky compression (fast) and the Householder QR (backward
    stable) of [Z y] lead to the same minimum: same criterion, same valve output."""
    for y, phi in loops:
        g = _fit_with(y, phi, "gram", "alternation")
        q = _fit_with(y, phi, "qr", "alternation")
        assert _ok(g.result) and _ok(q.result)
        np.testing.assert_allclose(float(g.loss), float(q.loss), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(phi @ g.model.beta), np.asarray(phi @ q.model.beta), atol=1e-6)
        np.testing.assert_allclose(g.model.a, q.model.a, atol=1e-6)


@pytest.mark.parametrize("compress, method", [("gram", "anderson"), ("qr", "variable_projection")])
def test_accelerated_methods_reach_the_alternation_minimum(loops, reference_fit, compress, method):
    """Anderson-accelerated alternation (Gram route, as the kernel benchmark runs it)
    and variable projection then alternation (QR route) end at the alternation's
    fixed point (same criterion, b and valve output as the alternation alone, and the
    NumPy reference's criterion on the first loop) in fewer steps (their own steps
    counted)."""
    for i, (y, phi) in enumerate(loops):
        fast = _fit_with(y, phi, compress, method)
        alt = _fit_with(y, phi, compress, "alternation")
        assert _ok(fast.result) and _ok(alt.result)
        np.testing.assert_allclose(float(fast.loss), float(alt.loss), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(phi @ fast.model.beta), np.asarray(phi @ alt.model.beta), atol=1e-5)
        np.testing.assert_allclose(fast.model.b, alt.model.b, atol=1e-5)
        assert int(fast.num_steps) < int(alt.num_steps)
        if i == 0:
            np.testing.assert_allclose(float(fast.loss), reference_fit.loss, rtol=1e-8)


def test_anderson_vmapped_equals_single_calls(loops):
    """Anderson acceleration under `vmap` (members stopping at different steps) gives
    each member's single-call criterion."""
    ys = jnp.stack([y for y, _ in loops])
    phis = jnp.stack([phi for _, phi in loops])
    one = lambda y, phi: relax(relax_problem(y, phi, ORDER, method="gram"), method="anderson", **TIGHT)
    batched = jax.vmap(one)(ys, phis)
    for i, (y, phi) in enumerate(loops):
        np.testing.assert_allclose(float(batched.loss[i]), float(_fit_with(y, phi, "gram", "anderson").loss), rtol=1e-9)
