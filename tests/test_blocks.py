import jax


jax.config.update("jax_enable_x64", True)

import math

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

from jaxstiction._blocks import (
    actuator_lag,
    choudhury,
    dead_time,
    deadband,
    equal_percentage,
    he_stiction,
    kano,
    quantize,
    random_walk,
    rate_limit,
    sinusoid,
    travel_limits,
)


# --------------------------------------------------------------------------------------
# Slow, plain-Python references (one sample at a time, no vectorisation). Each returns
# the valve positions and, per sample, whether the valve is in its moving state.
# --------------------------------------------------------------------------------------


def kano_ref(u, S, J):
    """DESIGN §3 pseudo-code, line by line; starts stuck at u[0], direction +1."""
    u = [float(v) for v in u]
    y, us, stp, d, u_prev, du_prev = u[0], u[0], 1, 1.0, u[0], 0.0
    out, moving = [], []
    for ut in u:
        du = ut - u_prev
        if du * du_prev <= 0 and stp == 0:
            us = u_prev
            stp = 1
        if stp == 0:
            y = ut - d * (S - J) / 2
        elif -d * (ut - us) > S:
            d = -d
            y = ut - d * (S - J) / 2
            stp = 0
        elif d * (ut - us) > J:
            y = ut - d * (S - J) / 2
            stp = 0
        du_prev = du
        u_prev = ut
        out.append(y)
        moving.append(stp == 0)
    return np.array(out), np.array(moving)


def _sign(x):
    return (x > 0) - (x < 0)


def choudhury_ref(x, S, J):
    """Choudhury, Thornhill & Shah (2005) flow chart (direction = last travel)."""
    x = [float(v) for v in x]
    y, x_ss, stuck, v_old, direction, x_prev = x[0], x[0], True, 0.0, 0, x[0]
    out, moving = [], []
    for xt in x:
        v_new = xt - x_prev
        if not stuck and _sign(v_new) != _sign(v_old):  # velocity changes sign or is 0
            x_ss = x_prev
            stuck = True
        if stuck:
            disp = xt - x_ss
            if _sign(disp) == direction:  # same direction as the last travel
                slip = abs(disp) > J
            else:  # reversal (or unknown direction)
                slip = abs(disp) > S
            if slip:
                y = xt - _sign(v_new) * (S - J) / 2
                direction = _sign(v_new)
                stuck = False
        else:
            y = xt - _sign(v_new) * (S - J) / 2
            direction = _sign(v_new)
        v_old = v_new
        x_prev = xt
        out.append(y)
        moving.append(not stuck)
    return np.array(out), np.array(moving)


def he_ref(u, fs, fd):
    """He et al. (2007): accumulated residual force u_r against static friction fs."""
    u = [float(v) for v in u]
    y, u_prev, u_r = u[0], u[0], 0.0
    out, moving = [], []
    for ut in u:
        u_r = u_r + (ut - u_prev)
        if abs(u_r) > fs:
            s = _sign(u_r)
            y = y + u_r - s * fd
            u_r = s * fd
            moving.append(True)
        else:
            moving.append(False)
        u_prev = ut
        out.append(y)
    return np.array(out), np.array(moving)


def deadband_ref(u, w):
    """Backlash (play operator), starting centred on u[0]."""
    u = [float(v) for v in u]
    y = u[0]
    out, moving = [], []
    for ut in u:
        if ut - w / 2 > y:
            y = ut - w / 2
            moving.append(True)
        elif ut + w / 2 < y:
            y = ut + w / 2
            moving.append(True)
        else:
            moving.append(False)
        out.append(y)
    return np.array(out), np.array(moving)


# --------------------------------------------------------------------------------------
# Inputs: smooth, noisy random walk, staircase.
# --------------------------------------------------------------------------------------


def smooth_input(n=600):
    t = np.arange(n)
    return 50 + 30 * np.sin(2 * np.pi * t / 120) + 8 * np.sin(2 * np.pi * t / 37)


def noisy_walk_input(n=1500, seed=0):
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0.0, 1.0, n))
    return 50 + walk + rng.normal(0.0, 1.5, n)


def staircase_input(step=3.0, hold=7, levels=12, cycles=4):
    up = [50 + step * i for i in range(levels)]
    path = (up + up[::-1][1:-1]) * cycles
    return np.repeat(np.array(path, dtype=float), hold)


INPUTS = {
    "smooth": smooth_input(),
    "noisy": noisy_walk_input(),
    "staircase": staircase_input(),
}
# (S, J) per input; includes an overshoot case (J > S) and a pure-deadband case.
PARAMS = [(20.0, 2.0), (5.0, 1.5), (4.0, 6.0), (3.0, 0.0)]


def _sync_index(*moving):
    """First sample at which every model is in its moving state."""
    both = np.logical_and.reduce(moving)
    assert both.any()
    return int(np.argmax(both))


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S,J", PARAMS)
def test_kano_matches_reference(name, S, J):
    u = INPUTS[name]
    ref, _ = kano_ref(u, S, J)
    np.testing.assert_allclose(
        np.asarray(kano(jnp.asarray(u), S, J)), ref, rtol=0, atol=1e-12
    )


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S,J", PARAMS)
def test_choudhury_matches_reference(name, S, J):
    u = INPUTS[name]
    ref, _ = choudhury_ref(u, S, J)
    out = np.asarray(choudhury(jnp.asarray(u), S, J))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("fs,fd", [(11.0, 9.0), (3.25, 1.75), (1.5, 1.5)])
def test_he_matches_reference(name, fs, fd):
    u = INPUTS[name]
    ref, _ = he_ref(u, fs, fd)
    out = np.asarray(he_stiction(jnp.asarray(u), fs, fd))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("w", [0.0, 3.0, 20.0])
def test_deadband_matches_reference(name, w):
    u = INPUTS[name]
    ref, _ = deadband_ref(u, w)
    np.testing.assert_allclose(
        np.asarray(deadband(jnp.asarray(u), w)), ref, rtol=0, atol=1e-12
    )


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S,J", [p for p in PARAMS if p[1] <= p[0]])
def test_choudhury_equals_kano_after_first_stick(name, S, J):
    # (With an overshoot J > S the first break-away differs -- Kano assumes upward
    # travel, Choudhury an unknown direction -- and on a staircase with steps < J the
    # two stay one step apart, so the equality is checked for J <= S.)
    u = INPUTS[name]
    _, mk = kano_ref(u, S, J)
    _, mc = choudhury_ref(u, S, J)
    t0 = _sync_index(mk, mc)
    assert t0 < len(u) // 4
    k = np.asarray(kano(jnp.asarray(u), S, J))
    c = np.asarray(choudhury(jnp.asarray(u), S, J))
    np.testing.assert_allclose(c[t0:], k[t0:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S", [3.0, 20.0])
def test_he_equals_kano_without_slip_jump(name, S):
    # fs = fd = S/2  <=>  S = fs + fd, J = fs - fd = 0: equal on every input.
    u = INPUTS[name]
    fs = fd = S / 2
    _, mk = kano_ref(u, S, 0.0)
    _, mh = he_ref(u, fs, fd)
    t0 = _sync_index(mk, mh)
    assert t0 < len(u) // 4
    k = np.asarray(kano(jnp.asarray(u), fs + fd, fs - fd))
    h = np.asarray(he_stiction(jnp.asarray(u), fs, fd))
    np.testing.assert_allclose(h[t0:], k[t0:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("fs,fd", [(11.0, 9.0), (2.0, 1.0)])
def test_he_equals_kano_on_staircase(fs, fd):
    # With J = fs - fd > 0 the models agree whenever each move exceeds J (step 3 > J).
    u = INPUTS["staircase"]
    S, J = fs + fd, fs - fd
    _, mk = kano_ref(u, S, J)
    _, mh = he_ref(u, fs, fd)
    t0 = _sync_index(mk, mh)
    assert t0 < len(u) // 4
    k = np.asarray(kano(jnp.asarray(u), S, J))
    h = np.asarray(he_stiction(jnp.asarray(u), fs, fd))
    np.testing.assert_allclose(h[t0:], k[t0:], rtol=0, atol=1e-12)


def test_he_stick_slips_where_kano_keeps_moving():
    # Documented difference: slow input, J > 0 -> He re-sticks (moves in jumps > J).
    u = INPUTS["smooth"]
    fs, fd = 11.0, 9.0
    h = np.asarray(he_stiction(jnp.asarray(u), fs, fd))
    k = np.asarray(kano(jnp.asarray(u), fs + fd, fs - fd))
    assert np.max(np.abs(h - k)[200:]) > 0.5
    jumps = np.abs(np.diff(h))
    assert np.all((jumps == 0) | (jumps > fs - fd - 1e-12))


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("w", [3.0, 20.0])
def test_deadband_equals_kano_with_zero_jump(name, w):
    u = INPUTS[name]
    _, mk = kano_ref(u, w, 0.0)
    _, md = deadband_ref(u, w)
    t0 = _sync_index(mk, md)
    assert t0 < len(u) // 4
    k = np.asarray(kano(jnp.asarray(u), w, 0.0))
    d = np.asarray(deadband(jnp.asarray(u), w))
    np.testing.assert_allclose(d[t0:], k[t0:], rtol=0, atol=1e-12)


def test_stiction_blocks_jit_vmap_over_parameters():
    u = jnp.asarray(INPUTS["noisy"][:400])
    S = jnp.array([1.0, 4.0, 9.0])
    J = jnp.array([0.5, 1.0, 0.0])
    for fn in (kano, choudhury, he_stiction):
        batched = jax.jit(jax.vmap(fn, in_axes=(None, 0, 0)))(u, S, J)
        for i in range(3):
            np.testing.assert_array_equal(
                np.asarray(batched[i]), np.asarray(fn(u, S[i], J[i]))
            )
    batched = jax.jit(jax.vmap(deadband, in_axes=(None, 0)))(u, S)
    for i in range(3):
        np.testing.assert_array_equal(
            np.asarray(batched[i]), np.asarray(deadband(u, S[i]))
        )


def test_integer_input_does_not_truncate_parameters():
    u_int = jnp.asarray(staircase_input().astype(np.int64))
    u_float = u_int.astype(jnp.float64)
    for fn in (kano, choudhury, he_stiction):
        out = fn(u_int, 2.5, 0.75)
        assert jnp.issubdtype(out.dtype, jnp.floating)
        np.testing.assert_array_equal(
            np.asarray(out), np.asarray(fn(u_float, 2.5, 0.75))
        )


def test_float32_respected():
    u = jnp.asarray(INPUTS["smooth"], jnp.float32)
    for out in (
        kano(u, 2.0, 1.0),
        choudhury(u, 2.0, 1.0),
        he_stiction(u, 2.0, 1.0),
        deadband(u, 2.0),
        actuator_lag(u, 0.5),
        rate_limit(u, 1.0),
        equal_percentage(u, 30.0),
        quantize(u, 2.0),
        dead_time(u, 3),
    ):
        assert out.dtype == jnp.float32


# --------------------------------------------------------------------------------------
# The other blocks against NumPy references.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("k", [0, 1, 5, 700])
def test_dead_time(k):
    x = INPUTS["smooth"]
    ref = np.empty_like(x)
    for t in range(len(x)):
        ref[t] = x[t - k] if t - k >= 0 else x[0]
    np.testing.assert_array_equal(np.asarray(dead_time(jnp.asarray(x), k)), ref)


@pytest.mark.parametrize("k", [-1, 1.0, True])
def test_dead_time_rejects_bad_k(k):
    with pytest.raises(ValueError, match="`k`"):
        dead_time(jnp.arange(5.0), k)


@pytest.mark.parametrize("R", [20.0, 30.0, 50.0, 1.0])
def test_equal_percentage(R):
    x = np.linspace(0, 100, 101)
    ref = x if R == 1.0 else (np.power(R, x / 100) - 1) / (R - 1) * 100
    out = np.asarray(equal_percentage(jnp.asarray(x), R))
    np.testing.assert_allclose(out, ref, rtol=1e-13, atol=1e-12)
    assert out[0] == pytest.approx(0.0) and out[-1] == pytest.approx(100.0)


def test_travel_limits():
    x = INPUTS["noisy"]
    np.testing.assert_array_equal(
        np.asarray(travel_limits(jnp.asarray(x), 45.0, 52.5)), np.clip(x, 45.0, 52.5)
    )


@pytest.mark.parametrize("a", [0.0, 0.5, 0.8, 0.99])
def test_actuator_lag(a):
    u = INPUTS["staircase"]
    ref = np.empty_like(u)
    prev = u[0]
    for t in range(len(u)):
        prev = a * prev + (1 - a) * u[t]
        ref[t] = prev
    out = np.asarray(actuator_lag(jnp.asarray(u), a))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)
    if a == 0.0:
        np.testing.assert_array_equal(out, u)


@pytest.mark.parametrize("r", [0.5, 2.0, 1e9])
def test_rate_limit(r):
    u = INPUTS["noisy"]
    ref = np.empty_like(u)
    prev = u[0]
    for t in range(len(u)):
        prev = prev + np.clip(u[t] - prev, -r, r)
        ref[t] = prev
    out = np.asarray(rate_limit(jnp.asarray(u), r))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)
    assert np.all(np.abs(np.diff(out)) <= r + 1e-12)
    if r == 1e9:
        np.testing.assert_array_equal(out, u)


@pytest.mark.parametrize("q", [0.1, 2.0])
def test_quantize(q):
    y = INPUTS["noisy"] - 50
    out = np.asarray(quantize(jnp.asarray(y), q))
    np.testing.assert_allclose(out, q * np.round(y / q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(out / q, np.round(out / q), rtol=0, atol=1e-9)


def test_sinusoid():
    n, A, P, ph = 200, 5.0, 50.0, 0.3
    t = np.arange(n)
    out = np.asarray(sinusoid(n, A, P, ph))
    np.testing.assert_allclose(
        out, A * np.sin(2 * np.pi * t / P + ph), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(sinusoid(n, A, P)), A * np.sin(2 * np.pi * t / P), atol=1e-12
    )
    assert sinusoid(n, A, P).dtype == jnp.float64


def test_random_walk():
    key = jr.PRNGKey(3)
    n, std = 5000, 0.3
    out = np.asarray(random_walk(key, n, std))
    eps = np.array(jr.normal(key, (n,)))
    eps[0] = 0.0
    np.testing.assert_allclose(out, np.cumsum(std * eps), rtol=0, atol=1e-12)
    assert out[0] == 0.0
    assert np.std(np.diff(out)) == pytest.approx(std, rel=0.05)
    assert math.isclose(float(random_walk(key, n, 0.0)[-1]), 0.0)
