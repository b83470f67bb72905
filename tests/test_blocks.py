import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

from jaxstiction import (
    AbstractBlock,
    ActuatorLag,
    block_name,
    BLOCKS,
    Choudhury,
    Deadband,
    DeadTime,
    Drift,
    EqualPercentage,
    He,
    Kano,
    make_block,
    NarrowBand,
    Quantiser,
    RateLimit,
    run_chain,
    Sinusoid,
    TravelLimits,
)
from jaxstiction.internal import levels


# --------------------------------------------------------------------------------------
# Slow, plain-Python references (one sample at a time, no vectorisation). Each returns
# the valve positions and, per sample, whether the valve is in its moving state.
# --------------------------------------------------------------------------------------


def kano_ref(u, S, J):
    """Kano's published pseudo-code, line by line; starts stuck at u[0], direction +1."""
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


def actuator_lag_ref(u, a):
    out, prev = np.empty(len(u)), float(u[0])
    for t in range(len(u)):
        prev = a * prev + (1 - a) * u[t]
        out[t] = prev
    return out


def rate_limit_ref(u, r):
    out, prev = np.empty(len(u)), float(u[0])
    for t in range(len(u)):
        prev = prev + np.clip(u[t] - prev, -r, r)
        out[t] = prev
    return out


def dead_time_ref(x, k):
    return np.array([x[t - k] if t - k >= 0 else x[0] for t in range(len(x))])


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
# He in Kano's terms: (S, J) <-> fs = (S + J)/2, fd = (S - J)/2. These are the former
# (fs, fd) = (11, 9), (3.25, 1.75), (1.5, 1.5); all exact in binary.
HE_PARAMS = [(20.0, 2.0), (5.0, 1.5), (3.0, 0.0)]


def _sync_index(*moving):
    """First sample at which every model is in its moving state."""
    both = np.logical_and.reduce(moving)
    assert both.any()
    return int(np.argmax(both))


@eqx.filter_jit
def _call(block, u):
    return block(u)


def run(block, u):
    """`block(u)` as NumPy; jitted once per block type and input shape (the parameters
    are traced leaves), which keeps the many parametrised cases fast."""
    return np.asarray(_call(block, jnp.asarray(u)))


# --------------------------------------------------------------------------------------
# Stiction blocks against the references (exact: the same operations in the same
# order; 1e-12 only leaves room for a last-bit difference in XLA's fused kernels).
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S,J", PARAMS)
def test_kano_matches_reference(name, S, J):
    u = INPUTS[name]
    ref, _ = kano_ref(u, S, J)
    np.testing.assert_allclose(run(Kano(S, J), u), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S,J", PARAMS)
def test_choudhury_matches_reference(name, S, J):
    u = INPUTS[name]
    ref, _ = choudhury_ref(u, S, J)
    np.testing.assert_allclose(run(Choudhury(S, J), u), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S,J", HE_PARAMS)
def test_he_matches_reference(name, S, J):
    u = INPUTS[name]
    ref, _ = he_ref(u, (S + J) / 2, (S - J) / 2)
    np.testing.assert_allclose(run(He(S, J), u), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("w", [0.0, 3.0, 20.0])
def test_deadband_matches_reference(name, w):
    u = INPUTS[name]
    ref, _ = deadband_ref(u, w)
    np.testing.assert_allclose(run(Deadband(w), u), ref, rtol=0, atol=1e-12)


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
    k, c = run(Kano(S, J), u), run(Choudhury(S, J), u)
    np.testing.assert_allclose(c[t0:], k[t0:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("S", [3.0, 20.0])
def test_he_equals_kano_without_slip_jump(name, S):
    # J = 0  <=>  fs = fd = S/2: equal on every input after the first slip.
    u = INPUTS[name]
    _, mk = kano_ref(u, S, 0.0)
    _, mh = he_ref(u, S / 2, S / 2)
    t0 = _sync_index(mk, mh)
    assert t0 < len(u) // 4
    k, h = run(Kano(S, 0.0), u), run(He(S, 0.0), u)
    np.testing.assert_allclose(h[t0:], k[t0:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("S,J", [(20.0, 2.0), (3.0, 1.0)])
def test_he_equals_kano_on_staircase(S, J):
    # With J > 0 the models agree whenever each move exceeds J (step 3 > J).
    u = INPUTS["staircase"]
    _, mk = kano_ref(u, S, J)
    _, mh = he_ref(u, (S + J) / 2, (S - J) / 2)
    t0 = _sync_index(mk, mh)
    assert t0 < len(u) // 4
    k, h = run(Kano(S, J), u), run(He(S, J), u)
    np.testing.assert_allclose(h[t0:], k[t0:], rtol=0, atol=1e-12)


def test_he_stick_slips_where_kano_keeps_moving():
    # Documented difference: slow input, J > 0 -> He re-sticks (moves in jumps > J).
    u = INPUTS["smooth"]
    S, J = 20.0, 2.0
    h, k = run(He(S, J), u), run(Kano(S, J), u)
    assert np.max(np.abs(h - k)[200:]) > 0.5
    jumps = np.abs(np.diff(h))
    assert np.all((jumps == 0) | (jumps > J - 1e-12))


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("w", [3.0, 20.0])
def test_deadband_equals_kano_with_zero_jump(name, w):
    u = INPUTS[name]
    _, mk = kano_ref(u, w, 0.0)
    _, md = deadband_ref(u, w)
    t0 = _sync_index(mk, md)
    assert t0 < len(u) // 4
    k, d = run(Kano(w, 0.0), u), run(Deadband(w), u)
    np.testing.assert_allclose(d[t0:], k[t0:], rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------
# jit, vmap, dtypes.
# --------------------------------------------------------------------------------------


# One instance of every block; Drift's key is fixed so that runs are comparable.
DRIFT_KEY = jr.key_data(jr.key(3))
EXAMPLE_PARAMS = {
    "kano": dict(S=4.0, J=1.0),
    "choudhury": dict(S=4.0, J=1.0),
    "he": dict(S=4.0, J=1.0),
    "deadband": dict(width=3.0),
    "actuator_lag": dict(a=0.7),
    "rate_limit": dict(max_rate=0.8),
    "travel_limits": dict(lo=45.0, hi=55.0),
    "equal_percentage": dict(R=30.0),
    "dead_time": dict(k=3),
    "sinusoid": dict(amplitude=2.0, period=25.0, phase=0.4),
    "drift": dict(step_std=0.2, key=DRIFT_KEY),
    "narrow_band": dict(rms=1.5, period=30.0, r=0.98, key=DRIFT_KEY),
    "quantiser": dict(step_size=0.5),
}
OUTPUT_SIDE = {"sinusoid", "drift", "narrow_band", "quantiser"}


def test_example_params_cover_the_registry():
    assert set(EXAMPLE_PARAMS) == set(BLOCKS)


@pytest.mark.parametrize("name", list(EXAMPLE_PARAMS))
def test_jit_matches_no_jit(name):
    blk = make_block(name, **EXAMPLE_PARAMS[name])
    u = jnp.asarray(INPUTS["noisy"][:60])  # short: the eager run dispatches op by op
    jitted = eqx.filter_jit(lambda b, x: b(x))(blk, u)
    with jax.disable_jit():
        eager = blk(u)
    # Same operations; XLA's fused kernels may round the last bit differently.
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=1e-14, atol=1e-12)


@pytest.mark.parametrize("cls", [Kano, Choudhury, He])
def test_stiction_blocks_jit_vmap_over_parameters(cls):
    u = jnp.asarray(INPUTS["noisy"][:400])
    S = jnp.array([1.0, 4.0, 9.0])
    J = jnp.array([0.5, 1.0, 0.0])
    batched = jax.jit(jax.vmap(lambda s, j: cls(s, j)(u)))(S, J)
    for i in range(3):
        np.testing.assert_array_equal(np.asarray(batched[i]), run(cls(float(S[i]), float(J[i])), u))


def test_deadband_and_lag_vmap_over_parameters():
    u = jnp.asarray(INPUTS["noisy"][:400])
    w = jnp.array([1.0, 4.0, 9.0])
    batched = jax.jit(jax.vmap(lambda v: Deadband(v)(u)))(w)
    for i in range(3):
        np.testing.assert_array_equal(np.asarray(batched[i]), run(Deadband(float(w[i])), u))
    a = jnp.array([0.0, 0.5, 0.9])
    batched = jax.jit(jax.vmap(lambda v: ActuatorLag(v)(u)))(a)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(batched[i]), run(ActuatorLag(float(a[i])), u), rtol=0, atol=1e-12)


def test_vmap_over_a_batched_module():
    # A block whose fields carry a batch axis, vmapped as a pytree.
    u = jnp.asarray(INPUTS["smooth"])
    blocks = eqx.filter_vmap(lambda s: Kano(s, 1.0))(jnp.array([2.0, 6.0]))
    out = eqx.filter_vmap(lambda b: b(u))(blocks)
    for i, s in enumerate((2.0, 6.0)):
        np.testing.assert_array_equal(np.asarray(out[i]), run(Kano(s, 1.0), u))


def test_integer_input_does_not_truncate_parameters():
    u_int = jnp.asarray(staircase_input().astype(np.int64))
    u_float = u_int.astype(jnp.float64)
    for cls in (Kano, Choudhury, He):
        out = cls(2.5, 0.75)(u_int)
        assert jnp.issubdtype(out.dtype, jnp.floating)
        np.testing.assert_array_equal(np.asarray(out), np.asarray(cls(2.5, 0.75)(u_float)))
    # Integer parameters become floats: (S - J)/2 = 1.5 is not truncated to 1.
    for blk in (Kano(5, 2), make_block("kano", S=5, J=2)):
        assert jnp.issubdtype(blk.S.dtype, jnp.inexact) and jnp.issubdtype(blk.J.dtype, jnp.inexact)
        np.testing.assert_array_equal(np.asarray(blk(u_int)), run(Kano(5.0, 2.0), u_float))
    for blk in (Deadband(3), ActuatorLag(0), RateLimit(1), EqualPercentage(30), Quantiser(2), Sinusoid(2, 40)):
        for leaf in jax.tree.leaves(blk):
            assert jnp.issubdtype(leaf.dtype, jnp.inexact), blk


@pytest.mark.parametrize("name", list(EXAMPLE_PARAMS))
def test_float32_respected(name):
    u = jnp.asarray(INPUTS["smooth"], jnp.float32)
    out = make_block(name, **EXAMPLE_PARAMS[name])(u)
    assert out.dtype == jnp.float32


# --------------------------------------------------------------------------------------
# The other blocks against NumPy references.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("k", [0, 1, 5, 700])
def test_dead_time(k):
    x = INPUTS["smooth"]
    np.testing.assert_array_equal(run(DeadTime(k), x), dead_time_ref(x, k))


@pytest.mark.parametrize("k", [-1, 1.0, True])
def test_dead_time_rejects_bad_k(k):
    with pytest.raises(ValueError, match="`k`"):
        DeadTime(k)


@pytest.mark.parametrize("R", [20.0, 30.0, 50.0, 1.0])
def test_equal_percentage(R):
    x = np.linspace(0, 100, 101)
    ref = x if R == 1.0 else (np.power(R, x / 100) - 1) / (R - 1) * 100
    out = run(EqualPercentage(R), x)
    # jnp.power and np.power may differ in the last bits: relative 1e-13.
    np.testing.assert_allclose(out, ref, rtol=1e-13, atol=1e-12)
    assert out[0] == pytest.approx(0.0) and out[-1] == pytest.approx(100.0)


def test_travel_limits():
    x = INPUTS["noisy"]
    np.testing.assert_array_equal(run(TravelLimits(45.0, 52.5), x), np.clip(x, 45.0, 52.5))
    np.testing.assert_array_equal(run(TravelLimits(hi=52.5), x), np.minimum(x, 52.5))
    np.testing.assert_array_equal(run(TravelLimits(), x), x)


@pytest.mark.parametrize("a", [0.0, 0.5, 0.8, 0.99])
def test_actuator_lag(a):
    u = INPUTS["staircase"]
    out = run(ActuatorLag(a), u)
    np.testing.assert_allclose(out, actuator_lag_ref(u, a), rtol=0, atol=1e-12)
    if a == 0.0:
        np.testing.assert_array_equal(out, u)


@pytest.mark.parametrize("r", [0.5, 2.0, 1e9])
def test_rate_limit(r):
    u = INPUTS["noisy"]
    out = run(RateLimit(r), u)
    np.testing.assert_allclose(out, rate_limit_ref(u, r), rtol=0, atol=1e-12)
    assert np.all(np.abs(np.diff(out)) <= r + 1e-12)
    if r == 1e9:
        np.testing.assert_array_equal(out, u)


# --------------------------------------------------------------------------------------
# Output-side blocks.
# --------------------------------------------------------------------------------------


def test_block_sides():
    for name, cls in BLOCKS.items():
        assert cls.side == ("output" if name in OUTPUT_SIDE else "input"), name


@pytest.mark.parametrize("q", [0.1, 2.0])
def test_quantiser(q):
    y = INPUTS["noisy"] - 50
    out = run(Quantiser(q), y)
    np.testing.assert_allclose(out, q * np.round(y / q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(out / q, np.round(out / q), rtol=0, atol=1e-9)
    # Ties go to even, as np.round.
    np.testing.assert_array_equal(run(Quantiser(1.0), np.array([0.5, 1.5, 2.5, -0.5, -1.5])), [0, 2, 2, 0, -2])


def test_sinusoid():
    y = INPUTS["noisy"][:300]
    t = np.arange(len(y))
    A, P, ph = 5.0, 50.0, 0.3
    np.testing.assert_allclose(run(Sinusoid(A, P, ph), y), y + A * np.sin(2 * np.pi * t / P + ph), rtol=0, atol=1e-12)
    np.testing.assert_allclose(run(Sinusoid(A, P), np.zeros(300)), A * np.sin(2 * np.pi * t / P), rtol=0, atol=1e-12)
    assert Sinusoid(A, P)(jnp.zeros(10)).dtype == jnp.float64


def test_drift_is_a_random_walk():
    n, std = 5000, 0.3
    w = run(Drift(std, DRIFT_KEY), np.zeros(n))
    assert w[0] == 0.0
    inc = np.diff(w)
    # Statistical checks on 4999 iid N(0, std^2) increments: the sample std has a
    # relative spread of 1/sqrt(2 * 4999) = 1 %, so 5 % is a 5-sigma bound; the mean
    # has spread std/sqrt(n) = 0.004 (bound 0.025 = 6 sigma); the lag-1 autocorrelation
    # has spread 1/sqrt(n) = 0.014 (bound 0.08 = 5.6 sigma). The key is fixed, so the
    # test is deterministic; the bounds only guard against a change of key or seed.
    assert np.std(inc) == pytest.approx(std, rel=0.05)
    assert abs(np.mean(inc)) < 0.025
    assert abs(np.corrcoef(inc[1:], inc[:-1])[0, 1]) < 0.08
    # Additive at the output; deterministic for a fixed key; the key matters.
    y = INPUTS["noisy"][:n]
    np.testing.assert_allclose(run(Drift(std, DRIFT_KEY), y), y + w[: len(y)], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(run(Drift(std, DRIFT_KEY), np.zeros(n)), w)
    other = run(Drift(std, jr.key_data(jr.key(4))), np.zeros(n))
    assert not np.allclose(other, w)
    np.testing.assert_array_equal(run(Drift(0.0, DRIFT_KEY), np.zeros(n)), 0.0)
    # Scale: the same draws times step_std.
    np.testing.assert_allclose(run(Drift(2 * std, DRIFT_KEY), np.zeros(n)), 2 * w, rtol=1e-12, atol=1e-12)


def test_narrow_band_is_a_resonator_driven_by_white_noise():
    n, rms, P, r = 20000, 2.0, 40.0, 0.98
    w = run(NarrowBand(rms, P, r, DRIFT_KEY), np.zeros(n))
    # NumPy reference: the same draws through the AR(2) recursion, from rest
    eps = np.asarray(jax.vmap(lambda t: jr.normal(jr.fold_in(jr.wrap_key_data(DRIFT_KEY), t), ()))(jnp.arange(n)))
    c, r2 = np.cos(2 * np.pi / P), r * r
    sigma = rms / np.sqrt((1 + r2) / ((1 - r2) * ((1 + r2) ** 2 - 4 * r2 * c * c)))
    ref = np.zeros(n)
    w1 = w2 = 0.0
    for t in range(n):
        ref[t] = 2 * r * c * w1 - r2 * w2 + sigma * eps[t]
        w1, w2 = ref[t], w1
    np.testing.assert_allclose(w, ref, rtol=1e-9, atol=1e-9)
    # stationary std `rms` (20000 samples, correlation time ~50: ~400 effective
    # samples, a relative spread of ~4 %; 15 % is a 4-sigma bound)
    assert np.std(w[500:]) == pytest.approx(rms, rel=0.15)
    # its power sits at the period: the periodogram's peak within 5 % of 1/P
    f = np.fft.rfftfreq(n)
    peak = f[np.argmax(np.abs(np.fft.rfft(w)) ** 2)]
    assert peak == pytest.approx(1 / P, rel=0.05)
    # additive at the output, and the key matters
    y = INPUTS["noisy"][:300]
    np.testing.assert_allclose(run(NarrowBand(rms, P, r, DRIFT_KEY), y), y + w[:300], rtol=0, atol=1e-12)
    assert not np.allclose(run(NarrowBand(rms, P, r, jr.key_data(jr.key(4))), np.zeros(300)), w[:300])


# --------------------------------------------------------------------------------------
# Registry.
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(EXAMPLE_PARAMS))
def test_make_block_builds_the_registered_class(name):
    params = EXAMPLE_PARAMS[name]
    blk = make_block(name, **params)
    assert type(blk) is BLOCKS[name]
    assert isinstance(blk, AbstractBlock)
    assert block_name(blk) == name
    for field, value in params.items():
        np.testing.assert_array_equal(np.asarray(getattr(blk, field)), np.asarray(value))
    again = make_block(block_name(blk), **params)
    assert eqx.tree_equal(again, blk)
    assert eqx.tree_equal(BLOCKS[name](**params), blk)


def test_registry_names():
    assert BLOCKS == {
        "kano": Kano,
        "choudhury": Choudhury,
        "he": He,
        "deadband": Deadband,
        "actuator_lag": ActuatorLag,
        "rate_limit": RateLimit,
        "travel_limits": TravelLimits,
        "equal_percentage": EqualPercentage,
        "dead_time": DeadTime,
        "sinusoid": Sinusoid,
        "drift": Drift,
        "narrow_band": NarrowBand,
        "quantiser": Quantiser,
    }


def test_make_block_unknown_name():
    with pytest.raises(ValueError, match="unknown block 'karnopp'") as err:
        make_block("karnopp", S=1.0)
    for name in BLOCKS:
        assert name in str(err.value)


def test_make_block_wrong_parameters():
    with pytest.raises(ValueError, match="block 'kano'"):
        make_block("kano", S=1.0)  # J missing
    with pytest.raises(ValueError, match="block 'deadband'"):
        make_block("deadband", width=1.0, J=2.0)  # unexpected parameter
    with pytest.raises(ValueError, match="`k`"):
        make_block("dead_time", k=-2)


def test_block_name_of_an_unregistered_block():
    class MyValve(AbstractBlock):
        def init(self, u0):
            return ()

        def step(self, state, u):
            return state, u

    assert block_name(MyValve()) == "myvalve"
    assert block_name(Kano(1.0, 0.5)) == "kano"


# --------------------------------------------------------------------------------------
# run_chain.
# --------------------------------------------------------------------------------------


CHAIN = (ActuatorLag(0.6), Kano(4.0, 1.0), TravelLimits(40.0, 58.0), EqualPercentage(30.0), DeadTime(3))


@pytest.mark.parametrize("name", list(INPUTS))
def test_run_chain_equals_blocks_in_sequence(name):
    u = INPUTS[name]
    x = jnp.asarray(u)
    for blk in CHAIN:
        x = blk(x)
    out = np.asarray(run_chain(CHAIN, jnp.asarray(u)))
    # Same per-sample operations inside one scan instead of five: exact up to XLA's
    # last-bit rounding.
    np.testing.assert_allclose(out, np.asarray(x), rtol=1e-14, atol=1e-12)


def test_run_chain_with_given_states():
    u = jnp.asarray(INPUTS["noisy"])
    states = (
        jnp.asarray(55.0),  # actuator lag
        tuple(jnp.asarray(v) for v in (53.0, 51.0, 1.0, -1.0, 55.0, 0.0)),  # Kano, stuck at 53 after falling
        (),
        (),
        jnp.array([60.0, 61.0, 62.0]),  # dead time: a filled delay line
    )
    x = u
    for blk, s in zip(CHAIN, states):
        x = blk(x, s)
    np.testing.assert_allclose(np.asarray(run_chain(CHAIN, u, states)), np.asarray(x), rtol=1e-14, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(x[:3]), [60.0, 61.0, 62.0])
    # The default states are each block at rest at its own first input.
    np.testing.assert_array_equal(np.asarray(run_chain(CHAIN, u)), np.asarray(run_chain(CHAIN, u, None)))


def test_run_chain_empty_and_integer_input():
    u = staircase_input().astype(np.int64)
    out = run_chain((), jnp.asarray(u))
    assert jnp.issubdtype(out.dtype, jnp.floating)
    np.testing.assert_array_equal(np.asarray(out), u)
    np.testing.assert_array_equal(
        np.asarray(run_chain((Kano(2.5, 0.75),), jnp.asarray(u))), run(Kano(2.5, 0.75), u.astype(float))
    )


# --------------------------------------------------------------------------------------
# Candidate initial states: `initial_states(u_open, count)` from the opening samples.
# --------------------------------------------------------------------------------------


def _member(states, i):
    return jax.tree.map(lambda t: t[i], states)


def _assert_state_equal(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _first_change(y):
    """First sample after which the output differs from its first value: up to there
    `LoopModel` replaces it by a free level (the held position of a stuck valve)."""
    idx = np.nonzero(y != y[0])[0]
    return int(idx[0]) if len(idx) else len(y)


@eqx.filter_jit
def _final_state(blk, history):
    """The block's state after running it from rest over `history` (a reachable state)."""
    return jax.lax.scan(lambda s, x: blk.step(s, x), blk.init(history[0]), history)[0]


OPEN = 12  # opening samples handed to initial_states (count = OPEN: every level)


@eqx.filter_jit
def _call_from(block, u, state):
    return block(u, state)


def run_from(block, u, state):
    return np.asarray(_call_from(block, jnp.asarray(u), state))


@eqx.filter_jit
def _candidate_outputs(blk, u):
    cands = blk.initial_states(u[:OPEN], OPEN)
    return jax.vmap(lambda c: blk(u, c))(cands)


def _stuck_starts(blk, is_stuck, trials=40, seed=0):
    """Reachable stuck states with their continuation input: histories of a random walk
    run through the block; kept when the valve is stuck at the end of the history and
    first slips at a sample 1..OPEN-1 of the continuation."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(trials):
        walk = 50 + np.cumsum(rng.normal(0.0, 0.8, 80))
        h, u = jnp.asarray(walk[:40]), jnp.asarray(walk[40:])
        state = _final_state(blk, h)
        t = _first_change(run_from(blk, u, state))
        if is_stuck(state) and 1 <= t < OPEN:
            out.append((state, u))
    return out


def _realised(blk, state, u):
    """Some candidate from the opening samples gives the same output as `state` from
    the first change on (before it, both are constant: the held level is free)."""
    y = run_from(blk, u, state)
    t = _first_change(y)
    for yc in np.asarray(_candidate_outputs(blk, jnp.asarray(u))):
        if _first_change(yc) == t and np.array_equal(yc[t:], y[t:]):
            return True
    return False


STUCK_CASES = {
    "kano": (Kano(4.0, 1.0), lambda s: float(s[2]) == 1.0),
    "kano_overshoot": (Kano(2.0, 3.0), lambda s: float(s[2]) == 1.0),
    # (A Choudhury valve that never moved has direction 0, "unknown": excluded, as for
    # the rest start below.)
    "choudhury": (Choudhury(4.0, 1.0), lambda s: float(s[2]) == 1.0 and float(s[4]) != 0.0),
    "deadband": (Deadband(3.0), lambda s: True),
    "he": (He(4.0, 1.0), lambda s: True),
}


@pytest.mark.parametrize(
    "case",
    [
        "kano",
        "kano_overshoot",
        "choudhury",
        "deadband",
        "he",
    ],
)
def test_initial_states_realise_every_first_slip(case):
    """The documented guarantee: a stopped valve whose first slip falls within the
    opening samples is reproduced exactly, to the sample, by one of the candidates
    built from those samples (count = their number)."""
    blk, is_stuck = STUCK_CASES[case]
    starts = _stuck_starts(blk, is_stuck)
    assert len(starts) >= 12
    missed = [i for i, (state, u) in enumerate(starts) if not _realised(blk, state, u)]
    assert not missed, f"{len(missed)} of {len(starts)} reachable stuck starts not realised"


@pytest.mark.parametrize("cls", [Kano, Deadband])
def test_initial_states_realise_the_rest_start(cls):
    # The default start (at rest at u[0]) is one of the stuck starts covered. (Not for
    # Choudhury: its rest state has an unknown direction, slipping only after S either
    # way, which no candidate -- all with a direction -- represents.)
    blk = cls(4.0, 1.0) if cls is not Deadband else cls(3.0)
    for seed in range(3):
        u = jnp.asarray(noisy_walk_input(60, seed))
        assert _first_change(run(blk, u)) < OPEN
        assert _realised(blk, blk.init(u[0]), u)


def _levels_reference(u, count):
    """The running extremes at the samples where each is new: all of them (the last
    repeated) when at most `count`, else `count` spread evenly over them."""
    out = []
    for run in (np.maximum.accumulate(u), np.minimum.accumulate(u)):
        pos = [0] + [t for t in range(1, len(u)) if run[t] != run[t - 1]]
        k = len(pos)
        if k <= count:
            idx = [pos[min(i, k - 1)] for i in range(count)]
        else:
            idx = [pos[int(np.round(i * (k - 1) / max(count - 1, 1)))] for i in range(count)]
        out.append(run[idx])
    return out


@pytest.mark.parametrize("count", [1, 4, 12, 80])
def test_levels_are_the_distinct_running_extremes(count):
    """`levels` against a loop over the samples: the candidate slip levels are the
    running extremes where they change (one per distinct first slip), wherever in the
    opening samples they fall, not the first `count` samples."""
    for seed in range(3):
        u = np.asarray(noisy_walk_input(120, seed))
        up, dn = (np.asarray(v) for v in jax.jit(levels, static_argnums=1)(jnp.asarray(u), count))
        ref_up, ref_dn = _levels_reference(u, count)
        np.testing.assert_array_equal(up, ref_up)
        np.testing.assert_array_equal(dn, ref_dn)


@pytest.mark.parametrize("count", [1, 5, 12])
def test_kano_initial_states(count):
    blk = Kano(6.0, 1.0)
    u_open = jnp.asarray(noisy_walk_input(12, 2))
    u0 = float(u_open[0])
    states = blk.initial_states(u_open, count)
    leaves = jax.tree.leaves(states)
    assert len(leaves) == len(jax.tree.leaves(blk.init(u_open[0])))
    for leaf in leaves:
        assert leaf.shape == (4 * count + 2,)
    y, us, stp, d, u_prev, du_prev = (np.asarray(v) for v in states)
    # 4*count stopped states (after rising, then after falling), then the two moving.
    np.testing.assert_array_equal(stp, [1.0] * (4 * count) + [0.0, 0.0])
    np.testing.assert_array_equal(d, [1.0] * (2 * count) + [-1.0] * (2 * count) + [1.0, -1.0])
    stuck = stp == 1
    np.testing.assert_array_equal(y[stuck], u0)
    np.testing.assert_array_equal(u_prev[stuck], u0)
    np.testing.assert_array_equal(du_prev[stuck], 0.0)
    # Moving states sit at u0 -/+ (S - J)/2, as a valve travelling up/down.
    np.testing.assert_allclose(y[~stuck], [u0 - 2.5, u0 + 2.5], rtol=0, atol=1e-12)
    # Stop points: within S + J of the range of the opening samples.
    lo, hi = float(jnp.min(u_open)), float(jnp.max(u_open))
    assert np.all(us >= lo - 7.0) and np.all(us <= hi + 7.0)


@pytest.mark.parametrize("count", [3, 8])
def test_other_initial_states(count):
    u_open = jnp.asarray(noisy_walk_input(10, 1))
    sizes = [(Choudhury(6.0, 1.0), 4 * count), (He(6.0, 1.0), 2 * count), (Deadband(3.0), 2 * count)]
    for name, params in EXAMPLE_PARAMS.items():
        if name not in ("kano", "choudhury", "he", "deadband"):
            sizes.append((make_block(name, **params), 1))
    for blk, size in sizes:
        states = blk.initial_states(u_open, count)
        for leaf in jax.tree.leaves(states):
            assert leaf.shape[0] == size, blk
        if size == 1:  # the default: init(u_open[0]) with a leading axis
            _assert_state_equal(_member(states, 0), blk.init(u_open[0]))
    # He's residual force lies in [-fs, fs]; deadband's position within w/2 of the range.
    ur = np.asarray(He(6.0, 1.0).initial_states(u_open, count)[2])
    assert np.all(np.abs(ur) <= 3.5)
    pos = np.asarray(Deadband(3.0).initial_states(u_open, count)[0])
    assert np.all(pos >= float(jnp.min(u_open)) - 1.5) and np.all(pos <= float(jnp.max(u_open)) + 1.5)


@pytest.mark.parametrize("cls", [Kano, Choudhury, He])
def test_slips_do_not_depend_on_the_units_of_op(cls):
    """OP in other units (a scale and a zero that round differently): the valve, from
    each candidate initial state, slips at the same samples and its position follows
    the units. The candidates are built to slip just past a level the input reaches,
    an exact tie that rounding must not decide."""
    rng = np.random.default_rng(3)
    u = 50 + np.cumsum(rng.normal(0.0, 0.8, 120))
    S, J = 4.0, 1.0
    y = np.asarray(_candidate_outputs(cls(S, J), jnp.asarray(u)))
    for a, c in [(1.1, 0.0), (1.0, 64.0), (0.013, -0.7)]:
        ya = np.asarray(_candidate_outputs(cls(a * S, a * J), jnp.asarray(a * u + c)))
        np.testing.assert_array_equal(np.diff(ya, axis=1) != 0, np.diff(y, axis=1) != 0)
        np.testing.assert_allclose((ya - c) / a, y, rtol=1e-9, atol=1e-9)
