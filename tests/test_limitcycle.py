"""The verdict's limit-cycle check: the fitted loop closed again around the
identified controller. Its oscillation reading and closed-loop stability test
against plain references; the reproduction on loops whose truth is known (a sticky
valve's own cycle, an external oscillation a band was fitted to); the cases it
cannot judge; jit, vmap; and the probability's handling of a missing feature."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_verdict as R
from jaxtyping import Array

import jaxstiction as js
from jaxstiction import Controller, Kano, LoopModel, SplineValve
from jaxstiction.internal import (
    Calibration,
    chain_gain,
    closed_loop,
    closed_loop_stable,
    cycle,
    fit_calibration,
    limit_cycle,
    loop_stats,
    nominal_model,
    with_process,
)


N = 1500
_closed_loop, _limit_cycle = eqx.filter_jit(closed_loop), eqx.filter_jit(limit_cycle)  # compiled once here
KP, KI = 0.05, 0.01  # the concealed cases' detuned PI


class _Fit(eqx.Module):
    """The three fields of a `LoopFit` that `limit_cycle` reads."""

    physical: LoopModel
    S: Array
    J: Array


def _fit(S, J):
    return _Fit(nominal_model(chain=(Kano(S, J),)), jnp.asarray(float(S)), jnp.asarray(float(J)))


def _record(S, J, seed=0, sine=0.0, period=37, noise=0.05, kp=KP, ki=KI):
    """The concealed-case plant with a Kano valve `S`, `J` under a PI at a constant
    setpoint 0, with white noise and an optional sinusoid of amplitude `sine` at the
    output: `(op, pv, sp, mask)`, the first 300 samples of run-in dropped."""
    rng = np.random.default_rng(seed)
    n = N + 300
    v = noise * rng.standard_normal(n) + sine * np.sin(2 * np.pi * np.arange(n) / period)
    plant = nominal_model(chain=(Kano(S, J),))
    ctrl = Controller(kp=jnp.asarray(kp), ki=jnp.asarray(ki))
    init = plant.rest_state(jnp.full((4,), 52.0))
    run = _closed_loop(plant, ctrl, jnp.zeros(n), jnp.asarray(v), init, 50.0)
    cut = slice(300, None)
    nan = jnp.full((N,), jnp.nan)
    return run.op[cut], run.pv[cut], nan, jnp.ones(N)


def test_cycle_reads_a_sine():
    t = jnp.arange(1200.0)
    for amplitude, period in ((2.0, 40.0), (0.5, 111.0)):
        e = amplitude * jnp.sin(2 * jnp.pi * t / period) + 0.01 * jnp.cos(2 * jnp.pi * t / 7.0)
        a, p = cycle(e, jnp.ones_like(t))
        assert abs(float(a) - amplitude) < 0.05 * amplitude
        assert abs(float(p) - period) < 0.05 * period


def _swing_and_cycle(n=7200, seed=1):
    """A fast cycle (period 20, amplitude 0.5) under a slow swing (period 1400,
    amplitude 3) and a little noise: over a long record the swing holds more power."""
    t = np.arange(float(n))
    noise = 0.02 * np.random.default_rng(seed).normal(size=n)
    return 0.5 * np.sin(2 * np.pi * t / 20.0) + 3.0 * np.sin(2 * np.pi * t / 1400.0) + noise


@pytest.mark.parametrize("min_periods", [3.0, 2.0])
def test_cycle_reads_a_long_record_in_segments(min_periods):
    """Over more than `segment` samples the oscillation is read in segments: whole,
    the record shows the slow swing; in segments, the fast cycle, as the plain
    reference computes it piece by piece, and the same cycle from a window that
    starts later in the record. No longer than `segment`, it is read whole."""
    e = _swing_and_cycle()
    ones = jnp.ones(e.size)
    a_whole, p_whole = cycle(jnp.asarray(e), ones, min_periods)
    assert float(p_whole) > 200
    a, p = cycle(jnp.asarray(e), ones, min_periods, segment=2400)
    a_ref, p_ref = R.cycle_segmented(e, 2400, min_periods)
    assert float(p) == pytest.approx(p_ref, rel=1e-9) and float(a) == pytest.approx(a_ref, rel=1e-6)
    assert float(p) == pytest.approx(20.0, rel=0.02) and float(a) == pytest.approx(0.5, rel=0.1)
    late = jnp.asarray((np.arange(e.size) >= 1000).astype(float))
    a_late, p_late = cycle(jnp.asarray(e), late, min_periods, segment=2400)
    assert float(p_late) == pytest.approx(20.0, rel=0.02) and float(a_late) == pytest.approx(0.5, rel=0.1)
    for segment in (None, e.size, e.size + 1):
        got = cycle(jnp.asarray(e), ones, min_periods, segment=segment)
        assert [float(x) for x in got] == [float(a_whole), float(p_whole)]


def test_loop_stats_read_a_long_run_as_the_verdict_does():
    """What-if numbers of a long run: the oscillation of a fast cycle under a slow
    swing is the cycle's, with the default segment the verdict's; a short run's
    is read whole, vmapped as in a loop."""
    from jaxstiction._whatif.stats import SEGMENT

    assert SEGMENT == js.VerdictSettings().segment
    e = _swing_and_cycle()
    pv = jnp.asarray(-e)
    valve = jnp.asarray(np.cumsum(e) * 0.01)
    st = loop_stats(pv, 0.0, valve, jnp.ones(e.size), 1.0, 0.1)
    assert float(st.period) == pytest.approx(20.0, rel=0.02) and float(st.amplitude) == pytest.approx(0.5, rel=0.1)
    short = jnp.stack([pv[:1500], pv[1500:3000]])
    batched = jax.vmap(lambda y: loop_stats(y, 0.0, y, jnp.ones(1500), 1.0, 0.1))(short)
    for i in range(2):
        one = cycle(-short[i], jnp.ones(1500))
        assert float(batched.amplitude[i]) == pytest.approx(float(one[0]), rel=1e-9)
        assert float(batched.period[i]) == pytest.approx(float(one[1]), rel=1e-9)


def _stable_by_roots(b, a, kp, ki, lag=0):
    """Whether every root (NumPy) of A(1 - q^-1) + q^-lag B (kp + ki - kp q^-1) lies
    inside the unit circle."""
    char = np.convolve(a, [1.0, -1.0])
    right = np.concatenate([np.zeros(lag), np.convolve(b, [kp + ki, -kp])])
    n = max(char.size, right.size)
    char = np.pad(char, (0, n - char.size)) + np.pad(right, (0, n - right.size))
    return bool(np.max(np.abs(np.roots(np.trim_zeros(char, "b")))) < 1.0)


@pytest.mark.parametrize("lag", [0, 1])
def test_closed_loop_stable_matches_the_roots(lag):
    """Against the roots (NumPy) of A(1 - q^-1) + q^-lag B (kp + ki - kp q^-1), on
    random gains around the edge of stability."""
    model = nominal_model(chain=(Kano(0.0, 0.0),))
    b, a = (np.asarray(x) for x in model.process.polynomials())
    rng = np.random.default_rng(lag)
    seen = set()
    for _ in range(40):
        kp, ki = rng.uniform(-0.2, 1.0), rng.uniform(0.0, 0.6)
        want = _stable_by_roots(b, a, kp, ki, lag)
        c = Controller(kp=jnp.asarray(kp), ki=jnp.asarray(ki), lag=jnp.asarray(lag))
        assert bool(closed_loop_stable(model, c, 40.0, 60.0)) == want, (kp, ki)
        seen.add(want)
    assert seen == {True, False}


def test_closed_loop_stable_counts_the_chain_after_the_valve():
    """A fitted model's chain carries the estimator's spline after the valve, which
    scales OP to [-1, 1]: the loop gain is the process's times the spline's slope.
    Checked against the roots (NumPy) with B scaled by that slope, and the slope
    against the spline's own, 2 / (hi - lo)."""
    lo, hi = 45.0, 55.0
    spline = SplineValve.linear(lo, hi, 8, jnp.float64)
    model = nominal_model(chain=(Kano(0.0, 0.0), spline))
    assert abs(float(chain_gain(model, 47.0, 52.0)) - 2.0 / (hi - lo)) < 1e-9
    assert abs(float(chain_gain(nominal_model(chain=(Kano(0.0, 0.0),)), 47.0, 52.0)) - 1.0) < 1e-12
    b, a = (np.asarray(x) for x in model.process.polynomials())
    g = 2.0 / (hi - lo)
    seen = set()
    for kp in np.linspace(0.05, 8.0, 40):
        want = _stable_by_roots(g * b, a, kp, 0.01)
        c = Controller(kp=jnp.asarray(kp), ki=jnp.asarray(0.01))
        assert bool(closed_loop_stable(model, c, 47.0, 52.0)) == want, kp
        seen.add(want)
    assert seen == {True, False}


def test_a_sticky_valve_reproduces_its_own_cycle():
    """The true model of a sticky loop makes the recorded cycle; its repaired
    valve does not."""
    op, pv, sp, mask = _record(4.0, 1.5)
    lc = _limit_cycle(_fit(4.0, 1.5), op, pv, sp, mask)
    assert bool(lc.stable)
    assert float(lc.controller_fit) > 0.9
    assert float(lc.reproduction) > 0.7
    assert float(lc.amplitude_repaired) < 0.1 * float(lc.amplitude_kano)


def test_a_band_fitted_to_an_external_oscillation_does_not():
    """A healthy valve and a sinusoid from elsewhere: a band fitted to it (wrongly)
    cycles at the loop's own period, not the sinusoid's, and the reproduction is low."""
    op, pv, sp, mask = _record(0.0, 0.0, sine=1.0, period=23)
    lc = _limit_cycle(_fit(4.0, 1.5), op, pv, sp, mask)
    assert abs(float(lc.period_recorded) - 23.0) < 2.0
    assert float(lc.reproduction) < 0.3


def test_what_cannot_be_judged_is_nan():
    op, pv, sp, mask = _record(4.0, 1.5)
    # an OP that is not the controller's law (random moves): the PI is not identified
    rng = np.random.default_rng(3)
    wild = 50.0 + jnp.cumsum(jnp.asarray(rng.standard_normal(N)))
    lc = _limit_cycle(_fit(4.0, 1.5), wild, pv, sp, mask)
    assert float(lc.controller_fit) < 0.2 and np.isnan(float(lc.reproduction))
    # a fitted process that the identified PI makes unstable (its gain 20 times the
    # plant's)
    fit = _fit(4.0, 1.5)
    b, a = fit.physical.process.polynomials()
    fit = eqx.tree_at(lambda f: f.physical, fit, with_process(fit.physical, 20.0 * b, a))
    lc = _limit_cycle(fit, op, pv, sp, mask)
    assert not bool(lc.stable) and np.isnan(float(lc.reproduction))
    assert float(lc.amplitude_repaired) > 10 * float(lc.amplitude_recorded)  # it ran away


def test_jit_equals_no_jit_and_vmap_equals_a_loop():
    """To 1 %: a slip is a threshold crossing, so the last bits of rounding (which XLA
    fuses differently jitted, batched or not) move a slip by a sample now and then."""
    records = [_record(4.0, 1.5, seed=1), _record(0.0, 0.0, seed=2, sine=1.0, period=23)]
    fits = [_fit(4.0, 1.5), _fit(2.0, 0.5)]
    singles = [_limit_cycle(f, *r) for f, r in zip(fits, records)]
    with jax.disable_jit():
        plain = limit_cycle(fits[0], *records[0])
    assert eqx.tree_equal(singles[0], plain, rtol=1e-2, atol=1e-6)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *fits), [jnp.stack(x) for x in zip(*records)]
    batched = eqx.filter_vmap(limit_cycle)(stacked[0], *stacked[1])
    for i, one in enumerate(singles):
        assert eqx.tree_equal(jax.tree.map(lambda x, i=i: x[i], batched), one, rtol=1e-2, atol=1e-6)


def test_a_missing_feature_is_taken_at_its_mean():
    cal = Calibration(names=("a", "b"), mean=jnp.array([1.0, 2.0]), scale=jnp.array([2.0, 0.5]),
                      weights=jnp.array([0.7, -1.3]), bias=jnp.array(0.2))
    assert float(cal.logit(jnp.array([3.0, jnp.nan]))) == pytest.approx(float(cal.logit(jnp.array([3.0, 2.0]))))
    # the fit imputes the same way: NaN entries fit as the column's (weighted) mean
    rng = np.random.default_rng(0)
    X = rng.standard_normal((200, 2))
    y = (X[:, 0] + 0.5 * rng.standard_normal(200) > 0).astype(float)
    w = rng.uniform(0.5, 2.0, 200)
    missing = X.copy()
    missing[::7, 1] = np.nan
    filled = missing.copy()
    seen = ~np.isnan(missing[:, 1])
    filled[~seen, 1] = np.sum(w[seen] * missing[seen, 1]) / np.sum(w[seen])
    got, want = fit_calibration(missing, y, w), fit_calibration(filled, y, w)
    for field in ("mean", "scale", "weights", "bias"):
        np.testing.assert_allclose(np.asarray(getattr(got, field)), np.asarray(getattr(want, field)), rtol=1e-10)
