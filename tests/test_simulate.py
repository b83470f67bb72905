import jax


jax.config.update("jax_enable_x64", True)

import functools as ft

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

from jaxstiction import (
    ActuatorLag,
    Choudhury,
    Deadband,
    DeadTime,
    Drift,
    EqualPercentage,
    Experiment,
    fitness,
    He,
    InitialState,
    Kano,
    LinearProcess,
    LoopModel,
    LoopRecord,
    make_scenario,
    NoiseModel,
    Quantiser,
    RateLimit,
    run_chain,
    SCENARIOS,
    simulate_loop,
    Sinusoid,
    TravelLimits,
)
from jaxstiction.internal import nominal_model, p_experiment, paper_experiment


B, A = (0.0, 1.0, 0.5), (1.0, -1.5, 0.7)
N = 1000  # one length for most tests, so that compilations are shared
P_EXP = p_experiment()


def experiment(base=P_EXP, **changes):
    """`base` with some fields changed (`nsr_iterations` is static: no `eqx.tree_at`)."""
    fields = dict(kc=base.kc, op_limits=base.op_limits, sp_amplitude=base.sp_amplitude,
                  sp_switch_prob=base.sp_switch_prob, nsr=base.nsr, nsr_iterations=base.nsr_iterations)
    return Experiment(**(fields | changes))


def np_lfilter(b, a, x, x_pre=0.0, delay=0):
    """Plain NumPy difference equation, one sample at a time:
    y(t) = sum_i b_i x(t - delay - i) - sum_{j>=1} a_j y(t - j)  (a_0 = 1),
    with the input equal to `x_pre` before t = 0 and the output at its steady state
    B(1)/A(1) * x_pre there."""
    x = np.asarray(x, float)
    y_pre = sum(b) / sum(a) * x_pre if x_pre else 0.0
    y = np.zeros_like(x)
    for t in range(len(x)):
        acc = sum(b[i] * (x[t - delay - i] if t - delay - i >= 0 else x_pre) for i in range(len(b)))
        acc -= sum(a[j] * (y[t - j] if t - j >= 0 else y_pre) for j in range(1, len(a)))
        y[t] = acc / a[0]
    return y


def with_history(x, value=50.0):
    """Prepend the pre-t=0 value (OP and every block rest at op_offset before t = 0)."""
    return jnp.concatenate([jnp.array([value]), jnp.asarray(x)])


def g_response(valve, rest=50.0, delay=0, op_offset=50.0):
    """Noise-free response of the paper's process to the recorded process input
    `valve`, which rested at `rest` before t = 0 (the loop starts at steady state)."""
    return np_lfilter(B, A, np.asarray(valve) - op_offset, rest - op_offset, delay)


def rest_output(chain, op0=50.0):
    """The chain's output at rest at OP = op0 (what the process sees before t = 0)."""
    return float(run_chain(tuple(chain), jnp.array([op0]))[0])


# --------------------------------------------------------------------------------------
# Closed-loop simulator
# --------------------------------------------------------------------------------------


# XLA's CPU code generation (vectorised loops under vmap, fused kernels under jit) can
# round the last bit differently from op-by-op execution, so "identical" is checked to
# 1e-12 relative; the loops below are long enough for a stick-slip valve to amplify any
# real discrepancy (different stick decisions or noise gain) far beyond that.
RTOL, ATOL = 1e-12, 1e-10
FIELDS = ("op", "pv", "pv_clean", "sp", "valve", "t", "noise_gain", "nsr")


def assert_records_close(a, b, index=None):
    for name in FIELDS:
        x = getattr(a, name) if index is None else getattr(a, name)[index]
        np.testing.assert_allclose(np.asarray(x), np.asarray(getattr(b, name)), rtol=RTOL, atol=ATOL, err_msg=name)


def test_jit_matches_no_jit():
    plant = nominal_model(chain=(Kano(3.0, 1.0),))
    exp = experiment(nsr_iterations=2)
    key = jr.PRNGKey(7)
    rec = simulate_loop(plant, exp, key, 20)  # short: the eager run dispatches op by op
    with jax.disable_jit():
        rec_nojit = simulate_loop(plant, exp, key, 20)
    assert float(rec.noise_gain) > 0 and np.any(np.diff(np.asarray(rec.valve)) == 0)
    assert_records_close(rec, rec_nojit)


def test_vmap_over_keys_matches_loop():
    plant = nominal_model(chain=(He(4.0, 1.0),), output=(Sinusoid(2.0, 50.0), Drift(0.1, jr.key_data(jr.key(11)))))
    keys = jr.split(jr.PRNGKey(0), 3)
    batched = jax.vmap(lambda k: simulate_loop(plant, P_EXP, k, N))(keys)
    assert batched.op.shape == (3, N)
    for i, k in enumerate(keys):
        assert_records_close(batched, simulate_loop(plant, P_EXP, k, N), index=i)


def test_vmap_over_plant_parameters():
    S = jnp.array([2.0, 4.0])
    key = jr.PRNGKey(1)
    batched = jax.vmap(lambda s: simulate_loop(nominal_model(chain=(Choudhury(s, 1.0),)), P_EXP, key, N))(S)
    for i in range(2):
        single = simulate_loop(nominal_model(chain=(Choudhury(float(S[i]), 1.0),)), P_EXP, key, N)
        assert_records_close(batched, single, index=i)


@pytest.mark.parametrize(
    "chain,output",
    [
        ((), ()),
        ((Kano(3.0, 1.0),), ()),
        ((), (Sinusoid(5.0, 50.0),)),
        ((ActuatorLag(0.8), DeadTime(2)), ()),
    ],
    ids=["nominal", "kano", "sinusoid", "lag_dead_time"],
)
def test_achieved_nsr(chain, output):
    plant = nominal_model(chain=chain, output=output)
    for seed in range(3):
        rec = simulate_loop(plant, P_EXP, jr.PRNGKey(seed), N)
        noise = np.asarray(rec.pv - rec.pv_clean)
        ratio = np.var(noise) / np.var(np.asarray(rec.pv_clean))
        assert ratio == pytest.approx(float(rec.nsr), rel=1e-9)
        assert abs(ratio / 0.05 - 1) < 0.1


def test_achieved_nsr_paper_loop():
    # Stick-slip makes var(pv_clean) jump with the noise gain, so the ratio cannot
    # always be hit exactly: typically within 1-3 %, rarely ~15 % (a jump is bracketed).
    plant = nominal_model(chain=(Kano(20.0, 2.0),))
    keys = jr.split(jr.PRNGKey(0), 16)
    nsr = np.asarray(jax.vmap(lambda k: simulate_loop(plant, paper_experiment(), k, 1500))(keys).nsr)
    err = np.abs(nsr / 0.05 - 1)
    assert np.median(err) < 0.03 and np.mean(err < 0.1) >= 0.9 and err.max() < 0.2, nsr


def test_zero_nsr_is_noise_free():
    exp = experiment(nsr=0.0)
    rec = simulate_loop(nominal_model(), exp, jr.PRNGKey(0), N)
    np.testing.assert_array_equal(np.asarray(rec.pv), np.asarray(rec.pv_clean))
    assert float(rec.noise_gain) == 0.0


def test_op_within_limits():
    exp = Experiment(op_limits=(45.0, 55.0), sp_amplitude=40.0)
    rec = simulate_loop(nominal_model(chain=(Kano(5.0, 1.0),)), exp, jr.PRNGKey(2), N)
    op = np.asarray(rec.op)
    assert op.min() >= 45.0 and op.max() <= 55.0
    assert np.isclose(op, 45.0).any() and np.isclose(op, 55.0).any()


@pytest.mark.parametrize("k", [0, 2])
def test_numpy_resimulation_of_g_reproduces_pv_clean(k):
    # The dead time in the chain is part of the recorded process input `valve`.
    rec = simulate_loop(nominal_model(chain=(Kano(3.0, 1.0), DeadTime(k))), P_EXP, jr.PRNGKey(4), N)
    # Scan (direct form II transposed) vs. direct form: the same sums in another order.
    np.testing.assert_allclose(np.asarray(rec.pv_clean), g_response(rec.valve), rtol=0, atol=1e-9)
    # Noise present in pv, not in pv_clean.
    assert np.std(np.asarray(rec.pv - rec.pv_clean)) > 0.1


def test_dead_time_block_equals_process_delay():
    """q^-2 in the chain (DeadTime) or in the process (delay=2): the same loop."""
    in_chain = nominal_model(chain=(Kano(3.0, 1.0), DeadTime(2)))
    in_process = eqx.tree_at(lambda m: m.process, nominal_model(chain=(Kano(3.0, 1.0),)),
                             LinearProcess(b=B, a=A, delay=2))
    key = jr.PRNGKey(4)
    a, b = simulate_loop(in_chain, P_EXP, key, N), simulate_loop(in_process, P_EXP, key, N)
    for name in ("op", "pv", "pv_clean", "sp", "noise_gain", "nsr"):
        np.testing.assert_allclose(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), rtol=RTOL, atol=ATOL,
                                   err_msg=name)
    # `valve` is the chain's output: delayed in the first plant only.
    np.testing.assert_allclose(np.asarray(a.valve)[2:], np.asarray(b.valve)[:-2], rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(np.asarray(b.pv_clean), g_response(b.valve, delay=2), rtol=0, atol=1e-9)


def test_chain_order():
    """OP -> lag -> rate limit -> stiction -> travel limits -> characteristic -> dead
    time -> G -> + sinusoid -> (+ noise) -> quantisation -> PV: the chain runs in the
    order of the tuple, the output blocks too."""
    chain = (ActuatorLag(0.5), RateLimit(1.5), Kano(3.0, 1.0), TravelLimits(46.0, 82.0), EqualPercentage(30.0),
             DeadTime(1))
    plant = nominal_model(chain=chain, output=(Sinusoid(2.0, 40.0), Quantiser(0.5)))
    rec = simulate_loop(plant, paper_experiment(), jr.PRNGKey(5), N)
    x = with_history(rec.op)
    stages = []
    for blk in chain:
        x = blk(x)
        stages.append(np.asarray(x))
    np.testing.assert_allclose(np.asarray(rec.valve), stages[-1][1:], rtol=0, atol=1e-10)
    # Every block does something here: the rate limit is active, the valve sticks, the
    # stem reaches the travel limit.
    assert np.mean(np.abs(np.diff(stages[0])) > 1.5) > 0.1
    assert np.mean(np.diff(stages[2]) == 0) > 0.1
    assert np.mean(stages[2] > 82.0) > 0.01
    # The process saw the chain's output (which rested at EP(50) before t = 0).
    dist = np.asarray(rec.pv_clean) - g_response(rec.valve, rest=rest_output(chain))
    np.testing.assert_allclose(dist, 2.0 * np.sin(2 * np.pi * np.arange(N) / 40.0), rtol=0, atol=1e-9)
    pv = np.asarray(rec.pv)
    np.testing.assert_allclose(pv / 0.5, np.round(pv / 0.5), rtol=0, atol=1e-9)
    assert np.max(np.abs(pv - np.asarray(rec.pv_clean))) > 0.25


def test_controller_sees_measured_pv():
    rec = simulate_loop(nominal_model(output=(Quantiser(2.0),)), P_EXP, jr.PRNGKey(6), N)
    op, pv, sp = (np.asarray(v) for v in (rec.op, rec.pv, rec.sp))
    err = sp - pv
    op_prev = np.concatenate([[50.0], op[:-1]])
    err_prev = np.concatenate([[0.0], err[:-1]])
    expect = np.clip(op_prev + 0.06 * err - 0.05 * err_prev, 0, 100)
    np.testing.assert_allclose(op, expect, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(np.fmod(pv, 2.0), 0.0)


def test_setpoint_is_gbn():
    keys = jr.split(jr.PRNGKey(8), 3)
    plant = eqx.tree_at(lambda m: m.pv_offset, nominal_model(), jnp.asarray(10.0))
    sp = np.asarray(jax.vmap(lambda k: simulate_loop(plant, P_EXP, k, N))(keys).sp)
    assert set(np.unique(sp)) == {-30.0, 50.0}  # +-40 around pv_offset
    # 3 x 999 Bernoulli(0.03) switches: mean 0.03, sd 0.003.
    switches = np.mean(sp[:, 1:] != sp[:, :-1])
    assert 0.02 < switches < 0.04


def test_algebraic_loop_rejected():
    # Documented: "Raises ValueError ... if the process is not strictly proper".
    with pytest.raises(ValueError, match="b\\[0\\]"):
        simulate_loop(LoopModel(chain=(), process=LinearProcess(b=(1.0, 0.5), a=A)), P_EXP, jr.PRNGKey(0), 10)


def test_algebraic_loop_rejected_without_jit():
    with jax.disable_jit(), pytest.raises(ValueError, match="b\\[0\\]"):
        simulate_loop(LoopModel(chain=(), process=LinearProcess(b=(1.0, 0.5), a=A)), P_EXP, jr.PRNGKey(0), 10)


def test_errors():
    simulate_loop(LoopModel(chain=(), process=LinearProcess(b=(1.0, 0.5), a=A, delay=1)), P_EXP, jr.PRNGKey(0), 10)
    with pytest.raises(ValueError, match="`k`"):
        DeadTime(-1)
    for n in (0, 1, 10.0, True):
        with pytest.raises(ValueError, match="`n`"):
            simulate_loop(nominal_model(), P_EXP, jr.PRNGKey(0), n)
    with pytest.raises(ValueError, match="AbstractBlock"):
        LoopModel(chain=(lambda u: u,), process=LinearProcess(b=B, a=A))
    with pytest.raises(ValueError, match="AbstractBlock"):
        LoopModel(chain=(), process=LinearProcess(b=B, a=A), output=("quantiser",))


def test_float32_respected():
    with jax.enable_x64(False):
        plant = nominal_model(chain=(Kano(3.0, 1.0),))
        exp = experiment(paper_experiment(), nsr_iterations=4)
        rec = simulate_loop(plant, exp, jr.PRNGKey(0), 100)
        assert rec.pv.dtype == jnp.float32 and rec.op.dtype == jnp.float32
        assert np.all(np.isfinite(np.asarray(rec.pv)))


# --------------------------------------------------------------------------------------
# LoopModel: simulate, initial_state, predict
# --------------------------------------------------------------------------------------


def walk_op(n=600, seed=1):
    rng = np.random.default_rng(seed)
    return 55.0 + np.cumsum(rng.normal(0.0, 1.0, n))


@pytest.mark.parametrize(
    "b,a,delay",
    [
        (B, A, 0),
        ((0.4, 0.2), (1.0, -0.8), 2),  # pure delay of two samples, b shorter than a
        ((1.0,), (1.0, -0.5, 0.1, -0.02), 0),  # b0 != 0: direct feed-through
        ((0.2, 0.3, -0.1, 0.05), (1.0, -0.6), 1),  # b longer than a
    ],
)
@pytest.mark.parametrize("op_offset,pv_offset", [(0.0, 0.0), (50.0, -3.0)])
def test_simulate_matches_difference_equation(b, a, delay, op_offset, pv_offset):
    op = walk_op()
    model = LoopModel(chain=(), process=LinearProcess(b=b, a=a, delay=delay), op_offset=op_offset,
                      pv_offset=pv_offset)
    out = np.asarray(model.simulate(jnp.asarray(op)))
    # At rest at op[0] before t = 0: the output starts at its steady state.
    ref = pv_offset + np_lfilter(b, a, op - op_offset, op[0] - op_offset, delay)
    # DF-II transposed vs. direct form round differently; values are O(100-1000), so
    # 1e-12 relative (plus 1e-10 absolute) is a few hundred ulps.
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(np.asarray(model.simulate(jnp.asarray(op), model.rest_state(jnp.asarray(op)))), out,
                               rtol=0, atol=0)
    if delay:
        np.testing.assert_allclose(out[:delay], ref[0], rtol=1e-12)  # still at rest


def test_integrating_process():
    """A level loop (A(1) = 0) starts from rest at OP = op_offset and runs in closed loop."""
    b, a = (0.0, 0.05), (1.0, -1.0)
    op = walk_op()
    model = LoopModel(chain=(), process=LinearProcess(b=b, a=a), op_offset=float(op[0]), pv_offset=10.0)
    ref = 10.0 + np_lfilter(b, a, op - op[0])
    np.testing.assert_allclose(np.asarray(model.simulate(jnp.asarray(op))), ref, rtol=1e-12, atol=1e-10)
    plant = LoopModel(chain=(Kano(4.0, 1.0),), process=LinearProcess(b=b, a=a), noise=NoiseModel(d=(1.0, -0.5)),
                      op_offset=50.0, pv_offset=100.0)
    rec = simulate_loop(plant, experiment(kc=(2.05, -2.0, 0.0), sp_amplitude=5.0), jr.PRNGKey(0), N)
    assert np.all(np.isfinite(np.asarray(rec.pv))) and np.std(np.asarray(rec.op)) > 1.0
    assert abs(float(rec.nsr) - 0.05) < 1e-3


def test_simulate_with_chain_and_output_blocks():
    op = jnp.asarray(walk_op())
    chain, output = (ActuatorLag(0.6), Deadband(2.0)), (Sinusoid(1.5, 30.0), Quantiser(0.25))
    model = nominal_model(chain=chain, output=output)
    x = np.asarray(run_chain(chain, op))
    y = g_response(x, rest=float(x[0]))
    y = y + 1.5 * np.sin(2 * np.pi * np.arange(len(y)) / 30.0)
    np.testing.assert_allclose(np.asarray(model.simulate(op)), 0.25 * np.round(y / 0.25), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(model.valve(op)), x)


@ft.cache
def paper_op():
    return make_scenario("paper_sim", seed=0).estimation.op


def test_initial_state_recovers_a_non_rest_start():
    op = paper_op()
    plant = nominal_model(chain=(Kano(20.0, 2.0),))
    op0 = op[0]
    one = jnp.ones((), op.dtype)
    # Stuck at op0 + 7 after travelling down, stopped at us = op0 + 0.5; the process
    # not at steady state. This valve first slips (down, once op < us - J) at a sample
    # inside the opening samples that `initial_state` searches (count = 16), where the
    # candidates realise every first slip to the sample: the fit is then exact. (A
    # later first slip is matched only approximately.)
    kano_state = (op0 + 7.0, op0 + 0.5, one, -one, op0, 0.0 * one)
    start = InitialState(chain=(kano_state,), hold=0.0 * one, held=jnp.asarray(False),
                         filter=plant.rest_state(op).filter + jnp.array([3.0, -1.5]), output=())
    pv = plant.simulate(op, start)
    valve = np.asarray(plant.valve(op, (kano_state,)))
    first_slip = int(np.argmax(valve != valve[0]))
    assert valve[0] == pytest.approx(float(op0) + 7.0) and 3 <= first_slip < 16
    est = plant.initial_state(op, pv, jnp.ones_like(op))
    assert bool(est.held)
    fit_est = float(fitness(pv, plant.simulate(op, est)))
    fit_rest = float(fitness(pv, plant.simulate(op)))
    assert fit_est > 99.9
    assert fit_rest < 90.0
    # The held level is the stuck position; afterwards the two valves are identical.
    assert float(est.hold) == pytest.approx(float(op0) + 7.0, abs=1e-6)
    np.testing.assert_allclose(np.asarray(plant.valve(op, est.chain))[first_slip:], valve[first_slip:], rtol=0,
                               atol=1e-12)


def test_initial_state_finds_a_first_slip_late_in_the_window():
    """A valve at rest whose first slip comes after `count` samples (OP wanders inside
    the slip jump for 60 samples, then ramps): the candidates come from the whole
    searched window, so one slips at the same sample and the fit is exact. (They
    used to come from the first `count` samples only: on `paper_sim` seed 34's
    validation record the true plant, its valve stuck for 49 samples, scored 69 %.)"""
    t = np.arange(400)
    op = np.where(t < 60, 50 + 1.5 * np.sin(2 * np.pi * t / 30), 50 + 0.2 * (t - 60))
    op = np.where(t < 90, op, 56 + np.cumsum(np.random.default_rng(4).normal(0, 1.5, 400)))
    op = jnp.asarray(op)
    plant = nominal_model(chain=(Kano(20.0, 2.0),))
    pv = plant.simulate(op)  # from rest at op[0] = 50: first slips when OP passes 52
    valve = np.asarray(plant.valve(op))
    first_slip = int(np.argmax(valve != valve[0]))
    assert first_slip == 71
    est = plant.initial_state(op, pv, (jnp.arange(400) < 100).astype(op.dtype), count=16, window=100)
    assert float(fitness(pv, plant.simulate(op, est))) > 99.99
    np.testing.assert_allclose(np.asarray(plant.valve(op, est.chain))[first_slip:], valve[first_slip:], rtol=0,
                               atol=1e-12)


@pytest.mark.parametrize("window", [60, 200])
def test_initial_state_window_changes_nothing(window):
    """`window` only skips samples of zero weight: the same state as the whole record
    (a noisy record, so the least squares are not exact and ties are unlikely)."""
    op = paper_op()
    plant = nominal_model(chain=(Kano(20.0, 2.0),), output=(Sinusoid(0.5, 40.0, 0.3),))
    pv = plant.simulate(op) + 0.3 * jr.normal(jr.PRNGKey(3), op.shape, op.dtype)
    w = (jnp.arange(op.shape[0]) < 50).astype(op.dtype)
    whole = plant.initial_state(op, pv, w, count=16)
    cut = plant.initial_state(op, pv, w, count=16, window=window)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(cut)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-10, atol=1e-10)


def test_initial_state_without_chain_is_the_filter_state():
    # No chain: the free levels are the hold level (chain output held until it first
    # changes, here never for a non-constant op after sample 0) and the filter state,
    # so a start off steady state is recovered exactly.
    op = jnp.asarray(walk_op())
    model = LoopModel(chain=(), process=LinearProcess(b=B, a=A), op_offset=50.0, pv_offset=2.0)
    start = InitialState(chain=(), hold=jnp.asarray(0.0), held=jnp.asarray(False),
                         filter=jnp.array([12.0, -4.0]), output=())
    pv = model.simulate(op, start)
    est = model.initial_state(op, pv, jnp.ones_like(op))
    # Least squares on an exact fit: agreement to rounding of the QR solve.
    np.testing.assert_allclose(np.asarray(model.simulate(op, est)), np.asarray(pv), rtol=0, atol=1e-8)
    assert float(fitness(pv, model.simulate(op))) < 99.0


def test_predict_one_step_error_is_the_innovation():
    op = paper_op()
    plant = nominal_model(chain=(Kano(20.0, 2.0),))  # noise C/D = 1/(1 - 0.9 q^-1)
    assert eqx.tree_equal(plant.noise, NoiseModel(c=(1.0,), d=(1.0, -0.9)))
    e = 0.7 * np.random.default_rng(3).normal(size=op.shape[0])
    y_sim = np.asarray(plant.simulate(op))
    pv = y_sim + np_lfilter((1.0,), (1.0, -0.9), e)
    pred1 = np.asarray(plant.predict(op, jnp.asarray(pv), 1))
    # Inverse filter of the same filter: exact up to rounding (values are O(10)).
    np.testing.assert_allclose((pv - pred1)[1:], e[1:], rtol=0, atol=1e-10)
    # k steps: pv - yhat is the first k terms of H applied to e, i.e. sum_{j<k} 0.9^j e(t-j).
    pred5 = np.asarray(plant.predict(op, jnp.asarray(pv), 5))
    ref5 = np_lfilter([0.9**j for j in range(5)], (1.0,), e)
    np.testing.assert_allclose(pv - pred5, ref5, rtol=0, atol=1e-10)
    # Errors grow with k towards those of the simulation (0.9^300 ~ 2e-14 of the
    # innovations left out: 1e-9 is loose).
    assert np.std(pv - pred1) < np.std(pv - pred5) < np.std(pv - y_sim)
    np.testing.assert_allclose(np.asarray(plant.predict(op, jnp.asarray(pv), 300)), y_sim, rtol=0, atol=1e-9)
    for k in (0, 2.0, True):
        with pytest.raises(ValueError, match="`k`"):
            plant.predict(op, jnp.asarray(pv), k)


# --------------------------------------------------------------------------------------
# Scenarios
# --------------------------------------------------------------------------------------


@ft.cache
def scenario(name, seed=0):
    return make_scenario(name, seed=seed)


def effect_free(sc):
    """pv_clean minus the noise-free process response to the recorded valve."""
    return np.asarray(sc.full.pv_clean) - g_response(sc.full.valve, rest=rest_output(sc.plant.chain))


EFFECT_BLOCKS = {
    "stiction": Kano,
    "dead_time": DeadTime,
    "valve_characteristic": EqualPercentage,
    "saturation": TravelLimits,
    "external_oscillation": Sinusoid,
    "deadband": Deadband,
    "quantization": Quantiser,
    "drift": Drift,
    "actuator_lag": ActuatorLag,
}


@pytest.mark.parametrize("name", SCENARIOS)
def test_scenario_builds(name):
    sc = scenario(name)
    assert sc.name == name
    assert isinstance(sc.description, str) and sc.description
    assert eqx.tree_equal(sc.nominal, nominal_model())
    # The plant is the nominal model with the hidden blocks in it.
    assert eqx.tree_equal(sc.plant, nominal_model(chain=sc.plant.chain, output=sc.plant.output))
    blocks = {type(b) for b in sc.plant.chain + sc.plant.output}
    assert blocks == {EFFECT_BLOCKS[e] for e in sc.effects}
    assert sc.effect == (sc.effects[0] if sc.effects else "none")
    if name == "paper_sim":
        assert sc.full is None
        assert eqx.tree_equal(sc.plant, nominal_model(chain=(Kano(20.0, 2.0),)))
        assert eqx.tree_equal(sc.experiment, paper_experiment())
        assert len(sc.estimation) == len(sc.validation) == 1500
        assert not np.array_equal(np.asarray(sc.estimation.pv), np.asarray(sc.validation.pv))
        recs = (sc.estimation, sc.validation)
        amp = 20.0
    else:
        assert eqx.tree_equal(sc.experiment, p_experiment())
        assert isinstance(sc.full, LoopRecord)
        assert len(sc.full) == 3000
        assert len(sc.estimation) == 2000 and len(sc.validation) == 1000
        np.testing.assert_array_equal(np.asarray(sc.validation.t), np.arange(2000, 3000))
        np.testing.assert_array_equal(np.asarray(sc.validation.pv), np.asarray(sc.full.pv)[2000:])
        np.testing.assert_array_equal(np.asarray(sc.estimation.op), np.asarray(sc.full.op)[:2000])
        recs = (sc.full,)
        amp = 40.0
    for rec in recs:
        assert set(np.unique(np.asarray(rec.sp))) <= {-amp, amp}
        assert float(rec.loop.ts) == 1.0
        np.testing.assert_array_equal(np.asarray(rec.loop.pv), np.asarray(rec.pv))
        assert abs(float(rec.nsr) / 0.05 - 1) < 0.1
        op = np.asarray(rec.op)
        assert op.min() >= 0.0 and op.max() <= 100.0
        assert np.all(np.isfinite(np.asarray(rec.pv)))


@pytest.mark.parametrize("name", [s for s in SCENARIOS if s != "paper_sim"])
def test_p_case_record_is_the_plant(name):
    """valve = the plant's chain on OP; pv_clean = G(valve) + the additive output
    blocks (the quantiser acts on the measured PV only)."""
    sc = scenario(name)
    op = sc.full.op
    valve = np.asarray(run_chain(sc.plant.chain, with_history(op)))[1:]
    np.testing.assert_allclose(np.asarray(sc.full.valve), valve, rtol=0, atol=1e-10)
    additive = tuple(b for b in sc.plant.output if not isinstance(b, Quantiser))
    expect = np.asarray(run_chain(additive, jnp.zeros(3000)))
    np.testing.assert_allclose(effect_free(sc), expect, rtol=0, atol=1e-8)


def test_scenarios_deterministic():
    a = make_scenario("P1", seed=3)
    b = make_scenario("P1", seed=3)
    c = make_scenario("P1", seed=4)
    np.testing.assert_array_equal(np.asarray(a.full.pv), np.asarray(b.full.pv))
    assert not np.array_equal(np.asarray(a.full.pv), np.asarray(c.full.pv))
    p = make_scenario("paper_sim", seed=3)
    np.testing.assert_array_equal(np.asarray(p.validation.pv),
                                  np.asarray(make_scenario("paper_sim", seed=3).validation.pv))
    # The drift of P8 is drawn from the seed too.
    d3, d4 = make_scenario("P8", seed=3).plant.output[0], make_scenario("P8", seed=4).plant.output[0]
    assert not np.array_equal(np.asarray(d3.key), np.asarray(d4.key))


def test_unknown_scenario():
    with pytest.raises(ValueError, match="paper_sim, P0, P1"):
        make_scenario("P11")


def test_paper_sim_has_kano_stiction():
    for rec in (scenario("paper_sim").estimation, scenario("paper_sim").validation):
        valve = np.asarray(Kano(20.0, 2.0)(with_history(rec.op)))[1:]
        np.testing.assert_allclose(np.asarray(rec.valve), valve, rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.asarray(rec.pv_clean), g_response(rec.valve), rtol=0, atol=1e-8)
        assert np.mean(np.diff(valve) == 0) > 0.2


def test_p0_is_the_nominal_loop():
    sc = scenario("P0")
    assert sc.effects == () and sc.effect == "none"
    np.testing.assert_array_equal(np.asarray(sc.full.valve), np.asarray(sc.full.op))
    np.testing.assert_allclose(effect_free(sc), 0.0, rtol=0, atol=1e-9)


def test_p1_p6_p10_valve_sticks():
    op0 = np.asarray(scenario("P0").full.op)
    for name, model in [("P1", Kano(3.0, 1.0)), ("P6", Deadband(3.0)), ("P10", Kano(4.0, 1.0))]:
        sc = scenario(name)
        op, valve = np.asarray(sc.full.op), np.asarray(sc.full.valve)
        np.testing.assert_allclose(valve, np.asarray(model(with_history(op)))[1:], rtol=0, atol=1e-10)
        assert np.mean(np.diff(valve) == 0) > 0.2  # stuck a good part of the time
        assert not np.allclose(op, op0)


def test_p2_dead_time():
    sc = scenario("P2")
    op = np.asarray(sc.full.op)
    np.testing.assert_array_equal(np.asarray(sc.full.valve), np.concatenate([[50.0, 50.0], op[:-2]]))
    np.testing.assert_allclose(np.asarray(sc.full.pv_clean), g_response(op, delay=2), rtol=0, atol=1e-9)
    # The nominal model (no delay) misses it.
    assert np.max(np.abs(np.asarray(sc.full.pv_clean) - g_response(op))) > 1.0


def test_p3_equal_percentage():
    sc = scenario("P3")
    op, valve = np.asarray(sc.full.op), np.asarray(sc.full.valve)
    np.testing.assert_allclose(valve, (np.power(30.0, op / 100) - 1) / 29 * 100, rtol=1e-13, atol=1e-12)
    assert np.max(np.abs(valve - op)) > 10.0


def test_p4_travel_limit():
    sc = scenario("P4")
    valve, op = np.asarray(sc.full.valve), np.asarray(sc.full.op)
    assert valve.max() == 52.5
    np.testing.assert_array_equal(valve, np.minimum(op, 52.5))
    assert np.mean(op > 52.5) > 0.05


def test_p5_p10_sinusoid():
    t = np.arange(3000)
    for name, amp, period in [("P5", 5.0, 50.0), ("P10", 4.0, 30.0)]:
        np.testing.assert_allclose(effect_free(scenario(name)), amp * np.sin(2 * np.pi * t / period), rtol=0,
                                   atol=1e-8)
    np.testing.assert_array_equal(np.asarray(scenario("P5").full.valve), np.asarray(scenario("P5").full.op))


def test_p7_quantized():
    pv = np.asarray(scenario("P7").full.pv)
    np.testing.assert_allclose(pv / 2.0, np.round(pv / 2.0), rtol=0, atol=1e-9)
    assert np.all(np.fmod(pv, 2.0) == 0.0)
    assert not np.all(np.fmod(np.asarray(scenario("P0").full.pv), 2.0) == 0.0)


def test_p8_drift():
    drift = effect_free(scenario("P8"))
    assert drift[0] == pytest.approx(0.0, abs=1e-9)
    # 2999 increments: the sample std has a relative spread of 1.3 %; 10 % is loose.
    assert np.std(np.diff(drift)) == pytest.approx(0.3, rel=0.1)


def test_p9_actuator_lag():
    sc = scenario("P9")
    op, valve = np.asarray(sc.full.op), np.asarray(sc.full.valve)
    np.testing.assert_allclose(valve, np.asarray(ActuatorLag(0.8)(with_history(op)))[1:], rtol=0, atol=1e-10)
    assert np.max(np.abs(valve - op)) > 1.0
    np.testing.assert_allclose(effect_free(sc), 0.0, rtol=0, atol=1e-8)


def test_p_cases_share_the_draws():
    sp0 = np.asarray(scenario("P0").full.sp)
    for name in ("P1", "P5", "P8"):
        np.testing.assert_array_equal(np.asarray(scenario(name).full.sp), sp0)
    # Same noise too: with no effect on the loop's input side and no output block, the
    # noise (pv - pv_clean) of P0 and P9 differs only by the gain that sets the ratio.
    n0 = np.asarray(scenario("P0").full.pv - scenario("P0").full.pv_clean)
    n9 = np.asarray(scenario("P9").full.pv - scenario("P9").full.pv_clean)
    np.testing.assert_allclose(n9 / float(scenario("P9").full.noise_gain), n0 / float(scenario("P0").full.noise_gain),
                               rtol=1e-9, atol=1e-9)
    assert not np.array_equal(np.asarray(scenario("P0").full.op), np.asarray(scenario("P9").full.op))
