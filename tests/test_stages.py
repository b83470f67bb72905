"""The estimator's stages one by one: reduction (19)-(21), the spline candidates, the
physical (Kano) fit, the mask-aware spectra, and gradients through the smooth parts
(relaxation -> reduction -> output-error polish) against finite differences."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxstiction as js
from jaxstiction import freq_response, lfilter, min_length
from jaxstiction.internal import (
    arx_design,
    arx_loss,
    candidate_knots,
    direction,
    FIT_BYTES_PER_SAMPLE,
    fit_candidate,
    fit_noise_model,
    fit_physical,
    fit_spline_candidates,
    is_stable,
    LowOrder,
    nominal_model,
    p_experiment,
    paper_experiment,
    reduce_model,
    scale_input,
    valve_from,
    welch,
)


SPL = js.SplineSettings(arx_order=5, knot_counts=(3, 5), max_order=2, max_delay=2, welch_segment=64, relax_steps=150,
                        polish_steps=15)


@pytest.fixture(scope="module")
def sticky():
    """A short noisy closed loop with Kano stiction S = 10, J = 2, scaled as the
    estimator scales it."""
    plant = nominal_model(chain=(js.Kano(10.0, 2.0),))
    rec = js.simulate_loop(plant, paper_experiment(), jr.PRNGKey(4), 600)
    op, pv = rec.op, rec.pv
    y = (pv - pv.mean()) / pv.std()
    u = scale_input(op, op.min(), op.max())
    return op, y, u


def test_reduction_recovers_an_exact_low_order_model():
    """Fed the exact frequency response of a second-order model with delay 1, the
    reduction recovers it (to solver tolerance) and ASYC picks order 2, delay 1."""
    w = jnp.linspace(0.02, jnp.pi, 64)
    truth = LowOrder(a=jnp.array([-1.5, 0.7]), b=jnp.array([1.0, 0.5]), delay=1, mask=jnp.ones(2))
    b, a = truth.polynomials(2)
    G = freq_response(b, a, w)
    variance = jnp.full(w.shape, 1e-6)
    sol = reduce_model(G, jnp.ones_like(w), w, variance, max_order=2, max_delay=2)
    best = jax.tree.map(lambda t: t[sol.best], sol.models)
    assert int(best.delay) == 1 and float(jnp.sum(best.mask)) == 2
    np.testing.assert_allclose(best.a, truth.a, atol=1e-6)
    np.testing.assert_allclose(best.b, truth.b, atol=1e-6)


def test_noise_model_is_always_invertible():
    """On a residual close to white, C and D nearly cancel and Gauss-Newton can wander
    along that ridge out of the unit circle; the noise model returned must still be
    stable and inversely stable (its result code flags the fallback). A genuine
    ARMA(1, 1) residual is still recovered, with a successful code."""
    import optimistix as optx

    fell_back = 0
    for seed in range(12):
        e = jr.normal(jr.key(seed), (600,))
        nm = fit_noise_model(e, jnp.ones(600))
        assert bool(is_stable(jnp.concatenate([jnp.ones(1), nm.c])))
        assert bool(is_stable(jnp.concatenate([jnp.ones(1), nm.d])))
        assert np.isfinite(float(nm.variance)) and float(nm.variance) < 1.5
        fell_back += int(nm.result != optx.RESULTS.successful and not np.any(np.asarray(nm.c)))
    assert fell_back > 0  # the white residuals do reach the fallback
    e = jr.normal(jr.key(99), (4000,))
    v = lfilter(jnp.array([1.0, 0.5]), jnp.array([1.0, -0.8]), e)
    nm = fit_noise_model(v, jnp.ones(4000))
    assert nm.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(nm.c), [0.5], atol=0.05)
    np.testing.assert_allclose(np.asarray(nm.d), [-0.8], atol=0.03)


def test_welch_ignores_masked_samples():
    """Spectra over a record padded with garbage but masked equal the spectra of the
    record alone (only wholly unmasked segments are averaged)."""
    x = jr.normal(jr.PRNGKey(0), (512,))
    e = jr.normal(jr.PRNGKey(1), (512,))
    ref = welch(x, e, 64)
    xp = jnp.concatenate([x, 50.0 * jnp.ones(200)])
    ep = jnp.concatenate([e, -7.0 * jnp.ones(200)])
    mask = jnp.concatenate([jnp.ones(512), jnp.zeros(200)])
    got = welch(xp, ep, 64, mask)
    for r, g in zip(ref, got):
        np.testing.assert_allclose(g, r, rtol=1e-12, atol=1e-14)


def test_spline_candidates_equal_single_candidate_calls(sticky):
    """The batched candidate grid (rule x knots, one lax.map) equals one call per
    candidate."""
    op, y, u = sticky
    w = jnp.ones_like(y)
    H = jnp.stack([direction(u), direction(u, threshold=0.05)])
    grid = jax.jit(lambda y, u, H, w: fit_spline_candidates(y, u, H, w, w, SPL))(y, u, H, w)
    knots, masks, counts = candidate_knots(SPL, y.dtype)
    one = jax.jit(lambda y, u, h, k, m, w, c: fit_candidate(y, u, h, k, m, w, w, SPL, c))
    for r in range(2):
        for k in range(len(SPL.knot_counts)):
            c = one(y, u, H[r], knots[k], masks[k], w, counts[k])
            np.testing.assert_allclose(grid.foe[r, k], c.foe, rtol=1e-9)
            np.testing.assert_allclose(grid.model.beta[r, k], c.model.beta, rtol=1e-7, atol=1e-9)
    assert bool(jnp.all(jnp.isfinite(grid.foe)))


def _physical_fits(sticky, variants):
    op, y, u = sticky
    w = jnp.ones_like(y)
    fits = []
    for span, budget in variants:
        pset = js.PhysicalSettings(num_S=31, num_J=6, starts=3, refine=7, refine_S=21, final=3, line=11, rounds=1,
                                   polish_starts=2, init_count=3, oe_steps=20, interval_span=span,
                                   memory_budget=budget)
        fitted = jax.jit(lambda op, y, w, lo, hi: fit_physical(op, y, w, lo, hi, pset))
        fits.append(fitted(op, y, w, op.min(), op.max()))
    return fits


def test_physical_fit_finds_s_and_j(sticky):
    """Kano S, J recovered near the truth (10, 2) on a 600-sample noisy loop. The
    wider interval grid (`interval_span`) changes only the intervals: the same point
    and loss as without it, intervals that contain the narrow ones, and here the truth."""
    fit, narrow = _physical_fits(sticky, ((4.0, 10**8), (0.0, 10**8)))
    assert abs(float(fit.S) - 10.0) < 0.6
    assert abs(float(fit.J) - 2.0) < 0.8
    for name in ("S", "J", "v_oe"):
        assert float(getattr(fit, name)) == float(getattr(narrow, name))
    for name in ("S_interval", "J_interval"):
        wide, nar = np.asarray(getattr(fit, name)), np.asarray(getattr(narrow, name))
        assert wide[0] <= nar[0] and nar[1] <= wide[1]
    assert float(fit.S_interval[0]) <= float(fit.S) <= float(fit.S_interval[1])
    assert float(fit.S_interval[0]) <= 10.0 <= float(fit.S_interval[1])
    assert float(fit.J_interval[0]) <= 2.0 <= float(fit.J_interval[1])


@pytest.mark.slow
def test_physical_fit_memory_budget_changes_nothing(sticky):
    """A memory budget that splits the grid and the final output-error fits into
    chunks (as on a long record) changes nothing."""
    fit, chunked = _physical_fits(sticky, ((4.0, 10**8), (4.0, 4 * 600 * FIT_BYTES_PER_SAMPLE)))
    for name in ("S", "J", "v_oe", "S_interval", "J_interval"):
        np.testing.assert_allclose(getattr(chunked, name), getattr(fit, name), rtol=1e-12)


def test_physical_fit_tries_longer_dead_times():
    """A sticky loop whose process has a dead time of 6 samples: with the default
    delays (1-3) the fit ends at the longest tried, which is what the report flags;
    with `Settings.with_max_delay(8)` it finds a longer delay and fits better. A
    delay below 1 is refused."""
    plant = js.LoopModel(chain=(js.Kano(10.0, 2.0),),
                         process=js.LinearProcess(b=(0.0,) * 6 + (1.0, 0.5), a=(1.0, -1.5, 0.7)),
                         noise=js.NoiseModel(c=(1.0,), d=(1.0, -0.9)), op_offset=50.0)
    rec = js.simulate_loop(plant, p_experiment(), jr.PRNGKey(4), 600)
    op, pv = rec.op, rec.pv
    y = (pv - pv.mean()) / pv.std()
    w = jnp.ones_like(y)
    small = js.PhysicalSettings(num_S=31, num_J=6, starts=3, refine=7, refine_S=21, final=3, line=11, rounds=1,
                                polish_starts=2, init_count=3, oe_steps=20)
    fits = []
    for settings in (js.Settings(physical=small), js.Settings(physical=small).with_max_delay(8)):
        assert settings.spline.max_delay == settings.physical.max_delay
        pset = settings.physical
        fits.append(jax.jit(lambda op, y, w, lo, hi: fit_physical(op, y, w, lo, hi, pset))(op, y, w, op.min(),
                                                                                           op.max()))
    assert int(fits[0].delay) == 3
    assert 5 <= int(fits[1].delay) <= 7
    assert float(fits[1].v_oe) < 0.95 * float(fits[0].v_oe)
    assert abs(float(fits[1].S) - 10.0) < 1.0
    for bad in (0, -2, 2.5, True):
        with pytest.raises(ValueError, match="max_delay"):
            js.Settings().with_max_delay(bad)
    # a delay is resolved only from a record many times longer
    assert min_length(js.Settings().with_max_delay(60)) == 1200
    assert min_length(js.Settings().with_max_delay(8)) == min_length(js.Settings())


def test_arx_criterion_equals_numpy_lstsq(sticky):
    """The grid's ARX criterion, read off a Gram-matrix Cholesky factor, equals the
    residual of NumPy's `lstsq` (SVD) on the same weighted regression to 1e-9
    relative, over (S, J) points from no stiction to a band of a quarter of the OP range,
    and every delay: the normal matrix is safe here. The sample window given as a
    `start` index (as the grid passes it: output columns from suffix sums) or inside
    the weights (with gaps too) gives the same criterion, under `vmap` as well."""
    op, y, u = sticky
    N = y.shape[0]
    w = jnp.ones_like(y)
    gaps = w.at[300:420].set(0.0).at[N - 50 :].set(0.0)  # an excluded stretch and padding
    lo, hi = op.min(), op.max()
    for base in (w, gaps):
        for s, j in [(0.0, 0.0), (3.0, 1.0), (10.0, 2.0), (20.0, 20.0), (25.0, 5.0)]:
            x, wb, first = valve_from(op, s, j, base, 10, -1, 3)
            x = scale_input(x, lo, hi)
            assert float(jnp.sum(wb)) > 100
            for order in (4, 8):
                # every delay from one shared Gram matrix, each against its own lstsq
                got = np.asarray(arx_loss(x, y, base, order, jnp.arange(1, 4), 3, first))
                inside = np.asarray(arx_loss(x, y, wb, order, jnp.arange(1, 4), 3))
                np.testing.assert_allclose(inside, got, rtol=1e-9)
                for d in (1, 2, 3):
                    X = np.asarray(arx_design(x, y, order, d))
                    m = np.asarray(wb) * (np.arange(N) >= order + 3)
                    th = np.linalg.lstsq(X * m[:, None], np.asarray(y) * m, rcond=None)[0]
                    want = np.sum((m * (np.asarray(y) - X @ th)) ** 2) / m.sum()
                    np.testing.assert_allclose(got[d - 1], want, rtol=1e-9)
    # a grid of valve paths under vmap, the output block shared, equals point by point
    S = jnp.array([0.0, 3.0, 10.0, 25.0])
    J = jnp.array([0.0, 1.0, 2.0, 5.0])

    def at(s, j):
        x, wb, first = valve_from(op, s, j, gaps, 10, -1, 3)
        return arx_loss(scale_input(x, lo, hi), y, gaps, 4, jnp.arange(1, 4), 3, first)

    batched = np.asarray(jax.jit(jax.vmap(at))(S, J))
    for i in range(S.shape[0]):
        np.testing.assert_allclose(batched[i], np.asarray(at(S[i], J[i])), rtol=1e-12)


def test_grad_through_relaxation_reduction_and_polish(sticky):
    """d(static gain of the polished model)/d(data) by implicit differentiation equals
    central finite differences (the candidate's discrete choices held fixed)."""
    op, y, u = sticky
    w = jnp.ones_like(y)
    h = direction(u)
    knots, masks, counts = candidate_knots(SPL, y.dtype)

    def gain(y):
        c = fit_candidate(y, u, h, knots[0], masks[0], w, w, SPL, counts[0])
        b, a = c.model.linear.polynomials(SPL.max_delay)
        return jnp.sum(b) / jnp.sum(a)

    g = jax.jit(jax.grad(gain))(y)
    f = jax.jit(gain)
    rng = np.random.default_rng(0)
    for _ in range(2):
        v = jnp.asarray(rng.standard_normal(y.shape[0]))
        eps = 1e-5
        fd = (f(y + eps * v) - f(y - eps * v)) / (2 * eps)
        np.testing.assert_allclose(float(g @ v), float(fd), rtol=2e-3, atol=1e-6)
