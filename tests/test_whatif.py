"""The loop closed again in simulation: controller identification, the closed-loop
replay against a plain-Python reference, the what-if numbers on a plant whose truth
is known, the knocker and its gradient, and the error paths.

Every loop here is short (a few hundred samples) and every what-if runs with a small
knocker grid and few draws, so the file compiles a handful of programs and runs in
well under a minute."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxstiction import (
    CompensateSettings,
    Controller,
    identify_controller,
    Kano,
    Knocker,
    KnockerGrid,
    make_loop,
    stack,
    WhatIfSettings,
)
from jaxstiction.internal import (
    chi2_quantile,
    closed_loop,
    closed_loop_stable,
    count_reversals,
    initial_and_sync,
    nominal_model,
    smooth_objective,
    SmoothKano,
    whatif_json,
    whatif_model,
)


N = 500
KP, KI = 0.3, 0.01  # the paper's PI, u(t) = u(t-1) + 0.31 e(t) - 0.3 e(t-1)
SMALL = WhatIfSettings(draws=3, min_samples=50,
                       compensate=CompensateSettings(grid=KnockerGrid(amplitudes=(0.2, 0.5), widths=(1,),
                                                                      periods=(3, 6), reinforcement=(0.5,))))


def _signals(seed, n=N, steps=True):
    """A setpoint (three steps, or constant 0) and a disturbance at the output: AR(1)
    noise plus a wandering load through the process, so a sticky loop cycles."""
    rng = np.random.default_rng(seed)
    sp = np.zeros(n)
    if steps:
        for t0 in (n // 5, n // 2, 4 * n // 5):
            sp[t0:] += rng.uniform(-8.0, 8.0)
    e = rng.standard_normal(n) * 0.3
    load = np.cumsum(rng.standard_normal(n)) * 0.05
    v, y = np.zeros(n), np.zeros(n)
    for t in range(n):  # the load through (q^-1 + 0.5 q^-2)/(1 - 1.5 q^-1 + 0.7 q^-2)
        if t >= 2:
            y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + load[t - 1] + 0.5 * load[t - 2]
        v[t] = (0.9 * v[t - 1] if t else 0.0) + e[t]
    return sp, v + y


def reference_loop(S, J, kp, ki, sp, v, op0=50.0, knock=None):
    """The plant (the concealed-case process around OP 50, a Kano valve) under a
    velocity-form PI, one sample at a time in plain Python: `(op, op_valve, valve,
    pv)`. Starts at rest at `op0` with the valve stuck there (direction up);
    `knock = (amplitude, width, period)` adds Hagglund's pulses."""
    b1, b2, a1, a2 = 1.0, 0.5, -1.5, 0.7
    ystat = (b1 + b2) / (1 + a1 + a2) * (op0 - 50.0)
    y_hist = [ystat, ystat]  # y(t-1), y(t-2)
    x_hist = [op0 - 50.0, op0 - 50.0]  # x(t-1), x(t-2): the process input
    y_v, us, stp, d, u_prev, du_prev = op0, op0, 1, 1.0, op0, 0.0
    sign, u_last = 0.0, op0
    out = []
    e0 = sp[0] - (-a1 * y_hist[0] - a2 * y_hist[1] + b1 * x_hist[0] + b2 * x_hist[1] + v[0])
    u1, e1 = op0 - ki * e0, e0
    for t in range(len(sp)):
        y = -a1 * y_hist[0] - a2 * y_hist[1] + b1 * x_hist[0] + b2 * x_hist[1]
        pv = y + v[t]
        e = sp[t] - pv
        u = min(max(u1 + kp * (e - e1) + ki * e, 0.0), 100.0)
        uv = u
        if knock is not None:
            amp, width, period = knock
            if t % period == 0:
                if u != u_last:
                    sign = 1.0 if u > u_last else -1.0
                u_last = u
            uv = min(max(u + (amp * sign if t % period < width else 0.0), 0.0), 100.0)
        du = uv - u_prev
        if du * du_prev <= 0 and stp == 0:
            us, stp = u_prev, 1
        if stp == 0:
            y_v = uv - d * (S - J) / 2
        elif -d * (uv - us) > S:
            d = -d
            y_v = uv - d * (S - J) / 2
            stp = 0
        elif d * (uv - us) > J:
            y_v = uv - d * (S - J) / 2
            stp = 0
        du_prev, u_prev = du, uv
        out.append((u, uv, y_v, pv))
        y_hist = [y, y_hist[0]]
        x_hist = [y_v - 50.0, x_hist[0]]
        u1, e1 = u, e
    return tuple(np.array(c) for c in zip(*out))


def _rest_state(model, op0):
    return model.rest_state(jnp.full((4,), op0))


def test_closed_loop_matches_the_plain_python_reference():
    sp, v = _signals(0)
    plant = nominal_model(chain=(Kano(4.0, 1.0),))
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))
    for knock in (None, (1.5, 2, 5), (2.0, 1, 1)):
        k = None if knock is None else Knocker(*knock)
        run = closed_loop(plant, ctrl, jnp.asarray(sp), jnp.asarray(v), _rest_state(plant, 50.0), 50.0, k)
        ref = reference_loop(4.0, 1.0, KP, KI, sp, v, knock=knock)
        for got, want in zip((run.op, run.op_valve, run.valve, run.pv), ref):
            np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-9)


def test_constant_reinforcement_is_the_knocker_of_period_one():
    """`Knocker(a, 1, 1)` adds a x the sign of OP's last move, every sample (none
    before OP first moves), and the grid and the JSON call it constant reinforcement."""
    from jaxstiction._whatif.report import knocker_json

    rng = np.random.default_rng(0)
    u = 50.0 + np.cumsum(np.where(rng.random(200) < 0.3, 0.0, rng.standard_normal(200)))
    u[:3] = 50.0  # OP has not moved yet
    k = Knocker(0.7, 1, 1)

    def body(state, tu):
        return k.step(state, tu[0], tu[1])

    _, pulses = jax.lax.scan(body, k.init(50.0), (jnp.arange(200), jnp.asarray(u)))
    sign, prev, want = 0.0, 50.0, []
    for x in u:
        if x != prev:
            sign = 1.0 if x > prev else -1.0
        prev = x
        want.append(0.7 * sign)
    np.testing.assert_array_equal(np.asarray(pulses), np.array(want))
    pts = KnockerGrid(amplitudes=(0.2,), widths=(1,), periods=(4,), reinforcement=(0.4, 0.5)).points()
    assert pts == ((0.2, 1, 4), (0.4, 1, 1), (0.5, 1, 1))
    assert knocker_json(k, 2.0, "grid")["kind"] == "constant reinforcement"
    assert knocker_json(Knocker(0.7, 1, 4), 2.0, "grid")["kind"] == "knocker"


def test_closed_loop_jit_equals_no_jit():
    sp, v = _signals(1, n=120)
    plant = nominal_model(chain=(Kano(3.0, 1.0),))
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI), lag=jnp.asarray(1))
    init = _rest_state(plant, 50.0)
    k = Knocker(1.0, 1, 4)
    args = (plant, ctrl, jnp.asarray(sp), jnp.asarray(v), init, 50.0, k)
    jitted = eqx.filter_jit(closed_loop)(*args)
    with jax.disable_jit():
        plain = closed_loop(*args)
    assert eqx.tree_equal(jitted, plain, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("lag", [0, 1])
def test_identify_controller_recovers_a_known_pi(lag):
    sp, v = _signals(2)
    plant = nominal_model(chain=(Kano(3.0, 1.0),))
    ctrl = Controller(kp=jnp.asarray(0.1), ki=jnp.asarray(0.01), lag=jnp.asarray(lag))
    run = closed_loop(plant, ctrl, jnp.asarray(sp), jnp.asarray(v), _rest_state(plant, 50.0), 50.0)
    got = identify_controller(run.op, run.pv, jnp.asarray(sp), jnp.ones(N))
    assert abs(float(got.kp) - 0.1) < 1e-8 and abs(float(got.ki) - 0.01) < 1e-8
    assert int(got.lag) == lag and float(got.fit) > 0.999 and int(got.source) == 0
    # without the setpoint (it is constant): the gains and the level, from OP and PV alone
    sp0 = np.full(N, 3.0)
    run = closed_loop(plant, ctrl, jnp.asarray(sp0), jnp.asarray(v), _rest_state(plant, 50.0), 50.0)
    got = identify_controller(run.op, run.pv, jnp.full(N, jnp.nan), jnp.ones(N))
    assert abs(float(got.kp) - 0.1) < 1e-7 and abs(float(got.ki) - 0.01) < 1e-7
    assert abs(float(got.setpoint) - 3.0) < 1e-5 and int(got.source) == 1


def test_controller_pi_from_a_standard_tuning():
    c = Controller.pi(0.5, 20.0, 2.0)
    assert float(c.kp) == 0.5 and abs(float(c.ki) - 0.05) < 1e-15 and int(c.source) == 2
    for bad in (dict(gain=0.0, integral_time=10.0, ts=1.0), dict(gain=1.0, integral_time=-1.0, ts=1.0),
                dict(gain=1.0, integral_time=10.0, ts=0.0)):
        with pytest.raises(ValueError) as info:
            Controller.pi(**bad)
        assert "\n" not in str(info.value)


def test_count_reversals():
    x = jnp.asarray([0.0, 1.0, 2.0, 1.95, 2.5, 1.0, 0.5, 0.55, 3.0])
    w = jnp.ones(9)
    assert float(count_reversals(x, w, 0.1)) == 2.0  # 2.5 -> 1.0 and 0.5 -> 3.0; the 0.05 wiggles are not moves
    assert float(count_reversals(x, w, 0.0)) == 4.0


def test_smooth_kano_tends_to_kano():
    t = jnp.arange(300.0)
    u = 50 + 6 * jnp.sin(t / 17) + 0.8 * jnp.sin(t / 3.1)
    exact = Kano(3.0, 1.0)(u)
    smooth = SmoothKano(3.0, 1.0, 1e-4)(u)
    assert float(jnp.max(jnp.abs(exact - smooth))) < 1e-3


def _plant_loop(seed, S=4.0, J=1.5, steps=True, sp_recorded=True):
    sp, v = _signals(seed, steps=steps)
    plant = nominal_model(chain=(Kano(S, J),))
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))
    run = closed_loop(plant, ctrl, jnp.asarray(sp), jnp.asarray(v), _rest_state(plant, 50.0), 50.0)
    loop = make_loop(np.asarray(run.op), np.asarray(run.pv), 2.0, sp=sp if sp_recorded else None)
    return plant, loop, sp, v


def test_whatif_with_the_true_model_predicts_the_repaired_plant():
    """With the plant's own model, the replayed disturbance is the plant's, so the
    as-is replay is the record and, once the valve's start and the repaired loop's
    settling are behind, the repaired loop is the plant with a linear valve under
    the same noise and setpoint."""
    plant, loop, sp, v = _plant_loop(3)
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))
    w = whatif_model(plant, loop, jnp.asarray([3.8, 4.2]), jnp.asarray([1.3, 1.7]), SMALL, controller=ctrl)
    np.testing.assert_allclose(np.asarray(w.pv_as_is), np.asarray(loop.pv), atol=1e-8)
    # identified, the controller is exact to ~1e-10: the replay is the record until a
    # slip lands a sample apart (a sticky loop is chaotic), and keeps its statistics
    w_id = whatif_model(plant, loop, jnp.asarray([3.8, 4.2]), jnp.asarray([1.3, 1.7]), SMALL)
    assert abs(float(w_id.as_is.error_std) / float(w.as_is.error_std) - 1) < 0.05
    _, _, _, pv_lin = reference_loop(0.0, 0.0, KP, KI, sp, v)
    start = int(w.start)
    assert 0 < start < N - 100
    # the repaired loop forgets how it started (to 5 % of a step by `start`)
    gap = np.abs(np.asarray(w.pv_repaired) - pv_lin)
    assert gap[start:].max() < 0.05 * np.ptp(pv_lin) and gap[-50:].max() < 1e-3
    true_std = np.std((sp - pv_lin)[start:])
    assert abs(float(w.repaired.error_std) / true_std - 1) < 0.01
    assert float(w.benefit) > 0 and bool(w.enough) and bool(w.stable)
    lo, hi = np.asarray(w.repaired_interval.error_std)
    assert lo <= float(w.repaired.error_std) <= hi
    # the knocker helps this loop, and costs travel
    assert float(w.compensated.error_std) < float(w.as_is.error_std)
    # hours of 2-s samples: travel and reversals are per hour
    hours = int(w.samples) * 2.0 / 3600
    valve = np.asarray(w.valve_as_is)
    travel = np.sum(np.abs(np.diff(valve[start:]))) / hours
    assert abs(float(w.as_is.travel) / travel - 1) < 1e-9
    js = whatif_json(jax.tree.map(np.asarray, w), 2.0, SMALL)
    for key in ("error_std_as_is", "error_std_repaired", "error_std_compensated", "error_std_repaired_interval",
                "benefit", "travel_as_is", "travel_repaired", "travel_compensated", "reversals_as_is",
                "reversals_repaired", "reversals_compensated", "compensator", "controller", "note"):
        assert key in js
    assert js["compensator"]["kind"] in ("knocker", "constant reinforcement")
    assert js["controller"]["source"] == "given"


def test_the_repaired_run_forgets_a_start_far_larger_than_its_error():
    """Where a repair removes almost all the variability, the repaired run's transient
    from the record's as-is start must fall below the repaired error's size, not only
    to 5 % of its own peak: with the plant's own model the repaired prediction is
    then the truth's (read from 5 % of the peak alone, this loop's is 7 % high)."""
    plant, loop, sp, v = _plant_loop(3, S=8.0, J=7.9, steps=False)
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))
    nan2 = jnp.full((2,), jnp.nan)
    w = whatif_model(plant, loop, nan2, nan2, dataclasses.replace(SMALL, draws=0), controller=ctrl)
    _, _, _, pv_lin = reference_loop(0.0, 0.0, KP, KI, sp, v)
    true_std = np.std((sp - pv_lin)[int(w.start):])
    assert float(w.as_is.error_std) > 15 * true_std
    assert abs(float(w.repaired.error_std) / true_std - 1) < 0.02


def test_whatif_vmap_equals_single_calls():
    loops, models = [], []
    for seed, steps in ((4, True), (5, False)):
        plant, loop, _, _ = _plant_loop(seed, steps=steps, sp_recorded=steps)
        loops.append(loop)
        models.append(plant)
    batch = stack(loops)
    batch = eqx.tree_at(lambda lp: lp.sp, batch, batch.sp)
    iv = jnp.asarray([[3.8, 4.2], [3.8, 4.2]])
    jv = jnp.asarray([[1.3, 1.7], [1.3, 1.7]])
    batched = eqx.filter_vmap(lambda m, lp, s, j: whatif_model(m, lp, s, j, SMALL))(
        jax.tree.map(lambda *t: jnp.stack(t), *models), batch, iv, jv)
    for i, (m, lp) in enumerate(zip(models, loops)):
        one = whatif_model(m, lp, iv[i], jv[i], SMALL)
        got = jax.tree.map(lambda t: t[i], batched)
        for name in ("as_is", "repaired", "compensated"):
            assert eqx.tree_equal(getattr(got, name), getattr(one, name), rtol=1e-9, atol=1e-9), name
        assert int(got.start) == int(one.start)


@pytest.mark.slow
def test_whatif_jit_equals_no_jit():
    from jaxstiction._whatif.whatif import _whatif_model

    plant, loop, _, _ = _plant_loop(10)
    args = (plant, loop, jnp.asarray([3.8, 4.2]), jnp.asarray([1.3, 1.7]), SMALL)
    jitted = whatif_model(*args)
    eager = _whatif_model(*args)  # op by op (each scan compiles its own body)
    for name in ("as_is", "repaired", "compensated", "repaired_interval"):
        assert eqx.tree_equal(getattr(jitted, name), getattr(eager, name), rtol=1e-8, atol=1e-8), name
    assert int(jitted.start) == int(eager.start)
    assert eqx.tree_equal(jitted.knocker, eager.knocker, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_compensate_vmap_equals_single_calls():
    from jaxstiction import compensate, estimate, Settings

    settings = CompensateSettings(grid=SMALL.compensate.grid)
    fits, loops = [], []
    for seed in (11, 12):
        _, loop, _, _ = _plant_loop(seed)
        fits.append(estimate(make_loop(loop.op, loop.pv, loop.ts), Settings(use_spline=False)))
        loops.append(loop)
    batch = stack(loops)
    # the fit's process as fitted: the process refit stops its local search at a
    # tolerance (rtol 1e-6), a batch's last bits can stop it an iteration apart, and a
    # sticky loop's replay amplifies that (test_whatif_refine checks the refit batched)
    batched = eqx.filter_vmap(lambda f, lp: compensate(f, lp, settings, refine=False))(
        jax.tree.map(lambda *t: jnp.stack(t), *fits), batch)
    for i in range(2):
        one = compensate(fits[i], loops[i], settings, refine=False)
        got = jax.tree.map(lambda t: t[i], batched)
        for name in ("error_std_as_is", "error_std_compensated", "error_std_repaired", "travel_compensated"):
            np.testing.assert_allclose(float(getattr(got, name)), float(getattr(one, name)), rtol=1e-8)
        assert eqx.tree_equal(got.knocker, one.knocker, rtol=1e-10, atol=1e-10)
        assert float(one.error_std_compensated) <= float(one.error_std_as_is)


def test_knocker_design_is_the_worst_over_the_valve_neighbours():
    """The chosen knocker's objective is the worst, over the fitted valve and its four
    neighbours (S ± 3 %, J ± 10 % of S), of its objective against each one's own run
    without a knocker (a plain loop of closed-loop runs as reference), and the least
    over the grid; a grid of knockers that all hurt gives no knocker."""
    from jaxstiction._whatif.compensate import design_knocker
    from jaxstiction._whatif.stats import loop_stats
    from jaxstiction._whatif.whatif import _prepare
    from jaxstiction.internal import with_valve

    plant, loop, _, _ = _plant_loop(3)
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))
    p = _prepare(plant, loop, ctrl, 8, SMALL.reversal_threshold, SMALL.min_samples)
    settings = SMALL.compensate
    d = design_knocker(plant, ctrl, p.replay, p.window, p.ts, p.as_is_stats, settings, SMALL.reversal_threshold)
    rp = p.replay

    def stats(model, knocker):
        run = closed_loop(model, ctrl, rp.sp_sim, rp.disturbance, rp.initial, rp.op0, knocker)
        return loop_stats(run.pv, rp.sp_stat, run.valve, p.window, p.ts, SMALL.reversal_threshold)

    none = Knocker(amplitude=0.0, width=1.0, period=2)
    worst, least_gain = 0.0, 1.0
    for S, J in ((4.0, 1.5), (3.88, 1.5), (4.12, 1.5), (4.0, 1.1), (4.0, 1.9)):
        m = with_valve(plant, jnp.asarray(S), jnp.asarray(J))
        k, n = stats(m, d.knocker), stats(m, none)
        obj = float(k.error_std / n.error_std + settings.travel_weight * k.travel / n.travel)
        worst = max(worst, obj)
        least_gain = min(least_gain, 1 - float(k.error_std / n.error_std))
    assert float(d.knocker.amplitude) > 0
    # the chosen knocker lowers the error by `min_gain` at least on every valve
    assert least_gain >= settings.min_gain
    assert float(d.objective) == pytest.approx(worst, rel=1e-9)
    assert float(d.objective) == pytest.approx(float(jnp.min(d.grid_objective)), rel=1e-12)
    assert float(d.objective) < 1 + settings.travel_weight
    # pulses of three bands hurt every neighbour: no knocker, and the as-is run
    hurts = CompensateSettings(grid=KnockerGrid(amplitudes=(3.0,), widths=(1,), periods=(2,), reinforcement=(3.0,)))
    d = design_knocker(plant, ctrl, p.replay, p.window, p.ts, p.as_is_stats, hurts, SMALL.reversal_threshold)
    assert float(d.knocker.amplitude) == 0 and float(d.objective) == pytest.approx(1 + hurts.travel_weight)
    assert float(d.compensated.error_std) == pytest.approx(float(p.as_is_stats.error_std), rel=1e-12)
    assert float(d.grid_objective[0]) > 1 + hurts.travel_weight
    # a gain no knocker buys everywhere: none is chosen, however good its objective
    greedy = dataclasses.replace(settings, min_gain=0.99)
    d = design_knocker(plant, ctrl, p.replay, p.window, p.ts, p.as_is_stats, greedy, SMALL.reversal_threshold)
    assert float(d.knocker.amplitude) == 0 and float(d.objective) == pytest.approx(1 + greedy.travel_weight)
    assert float(jnp.min(d.grid_objective)) < 1 + greedy.travel_weight


def test_no_setpoint_is_a_constant_setpoint():
    plant, loop, _, _ = _plant_loop(6, steps=False, sp_recorded=False)
    w = whatif_model(plant, loop, jnp.full(2, jnp.nan), jnp.full(2, jnp.nan), SMALL)
    assert not bool(w.has_setpoint) and int(w.controller.source) == 1
    # the errors are about the mean: std(SP - PV) is PV's own spread
    assert abs(float(w.as_is.error_std) - float(w.as_is.pv_std)) < 1e-9
    js = whatif_json(jax.tree.map(np.asarray, w), 2.0, SMALL)
    assert "no setpoint recorded" in js["note"]
    assert js["error_std_repaired_interval"] is not None  # NaN intervals of S and J: S and J are kept


def test_an_unstable_repaired_loop_is_not_read():
    """Under a PI that makes the linear loop unstable, the runs stay bounded (OP
    clipped to its limits) and give numbers, but the repaired one would be the
    runaway's: `stable` is false, and the JSON's numbers are null with the reason."""
    plant, loop, _, _ = _plant_loop(6, steps=False)
    hot = Controller(kp=jnp.asarray(2.0), ki=jnp.asarray(0.5))
    assert not bool(closed_loop_stable(plant, hot, 40.0, 60.0))
    w = whatif_model(plant, loop, jnp.full(2, jnp.nan), jnp.full(2, jnp.nan), SMALL, controller=hot)
    assert np.isfinite(float(w.repaired.error_std))
    assert not bool(w.stable) and not bool(w.enough)
    js = whatif_json(jax.tree.map(np.asarray, w), 2.0, SMALL)
    assert js["error_std_repaired"] is None and "is unstable or runs away" in js["note"]


@pytest.mark.slow
def test_a_slow_repaired_loop_is_read_on_the_last_samples():
    """A repaired loop that settles for longer than the record leaves is read on the
    record's last `min_samples` samples after the valve's start, and says so; with
    a `min_samples` beyond what the valve's start leaves, the numbers are null."""
    plant, loop, _, _ = _plant_loop(9)
    slow = Controller(kp=jnp.asarray(0.01), ki=jnp.asarray(0.0005))  # does not settle within the record
    w = whatif_model(plant, loop, jnp.full(2, jnp.nan), jnp.full(2, jnp.nan), SMALL, controller=slow)
    assert int(w.sync) + int(w.settle) > N - SMALL.min_samples and not bool(w.settled)
    assert int(w.start) == max(int(w.sync), N - SMALL.min_samples) and bool(w.enough)
    js = whatif_json(jax.tree.map(np.asarray, w), 2.0, SMALL)
    assert js["error_std_repaired"] is not None and "repaired loop settles in" in js["note"]
    assert js["window"]["settled"] is False
    strict = WhatIfSettings(draws=3, min_samples=N + 1, compensate=SMALL.compensate)
    w = whatif_model(plant, loop, jnp.full(2, jnp.nan), jnp.full(2, jnp.nan), strict, controller=slow)
    js = whatif_json(jax.tree.map(np.asarray, w), 2.0, strict)
    assert not bool(w.enough) and js["error_std_repaired"] is None and js["benefit"] is None
    assert "too few to read the numbers on" in js["note"]


def test_knocker_gradient_matches_finite_differences():
    plant, loop, sp, v = _plant_loop(7)
    sm = eqx.tree_at(lambda m: m.chain[0], plant, SmoothKano(4.0, 1.5, 0.2))
    ctrl = Controller(kp=jnp.asarray(KP), ki=jnp.asarray(KI))
    op = jnp.asarray(loop.op)
    init, _ = initial_and_sync(plant, op, jnp.asarray(loop.pv), jnp.ones(N), 4)
    from jaxstiction.internal import loop_stats, replay

    rp = replay(plant, loop, ctrl, initial=init, sync=0)
    run = closed_loop(plant, ctrl, rp.sp_sim, rp.disturbance, rp.initial, rp.op0)
    base = loop_stats(run.pv, rp.sp_stat, run.valve, jnp.ones(N), 2.0, 0.1)
    f = smooth_objective(sm, ctrl, rp, jnp.ones(N), 2.0, base, 0.05)

    def g(x):
        return f(Knocker(x[0], x[1], 5, soft=0.5))

    x = jnp.asarray([1.2, 1.6])
    grad = jax.grad(g)(x)
    h = 1e-5
    fd = jnp.stack([(g(x + h * e) - g(x - h * e)) / (2 * h) for e in jnp.eye(2)])
    np.testing.assert_allclose(np.asarray(grad), np.asarray(fd), rtol=1e-4, atol=1e-7)


def test_chi2_quantile():
    # scipy.stats.chi2.ppf(0.9, k) for k = 2, 5, 10
    for k, want in ((2, 4.605), (5, 9.236), (10, 15.987)):
        assert abs(float(chi2_quantile(0.9, k)) / want - 1) < 0.01


def test_bad_input_is_one_line():
    plant, loop, _, _ = _plant_loop(8)
    for call, match in ((lambda: whatif_model(plant, loop.op, None, None), "must be a jaxstiction.Loop"),
                        (lambda: whatif_model(nominal_model(), loop, None, None), "Kano valve"),
                        (lambda: WhatIfSettings(level=1.5), "level"),
                        (lambda: KnockerGrid(widths=(0,)), "widths"),
                        (lambda: KnockerGrid(reinforcement=(0.0,)), "reinforcement"),
                        (lambda: KnockerGrid(reinforcement=0.5), "reinforcement"),
                        (lambda: CompensateSettings(method="newton"), "method"),
                        (lambda: CompensateSettings(robust_S=1.5), "robust_S"),
                        (lambda: CompensateSettings(min_gain=1.0), "min_gain")):
        with pytest.raises(ValueError, match=match) as info:
            call()
        assert "\n" not in str(info.value)
    from jaxstiction import whatif

    with pytest.raises(ValueError, match="LoopFit"):
        whatif(plant, loop)
