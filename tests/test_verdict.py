"""The stiction verdict's evidence beside the model: indicators, blocked
cross-validation, gate and probability. Each piece against a slow NumPy reference
(`reference_verdict.py`), under jit and vmap, and on loops made to show what it is
for."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_verdict as R

import jaxstiction as js
import jaxstiction.internal as internal
from jaxstiction._fleet import LONGEST
from jaxstiction.internal import fit_calibration, gate, GATES, kstep_prediction


# Called eagerly, the indicators re-trace their loops on every call (seconds each on a
# cold cache); the tests call them jitted, compiled once per record length, and
# `test_indicators_under_jit_and_vmap` compares jitted with eager.
bicoherence, gate_measures, horch_phase, indicators, oscillation, shape_index, stuck_share = (
    eqx.filter_jit(getattr(internal, name)) for name in (
        "bicoherence", "gate_measures", "horch_phase", "indicators", "oscillation", "shape_index", "stuck_share"))


@pytest.fixture(scope="module")
def records():
    """Three records of different character: a sticky valve's limit cycle, a
    sinusoidal oscillation with OP in phase with the error (as an oscillation near
    the loop's crossover, from tuning or from outside, shows), and noise alone."""
    t = np.arange(1200.0)
    rng = np.random.default_rng(0)
    square = np.sign(np.sin(2 * np.pi * t / 120.0))  # PV jumps when the valve slips ...
    pv = 10 + 2 * square + 0.1 * rng.normal(size=t.size)
    op = 50 - 0.1 * np.cumsum(pv - 10)  # ... and OP, the integral of the error, ramps: a triangle
    sticky = (op, pv)
    sine = np.sin(2 * np.pi * t / 80.0)  # an oscillation near the loop's crossover: OP in phase with the error
    external = (50 + 2 * sine + 0.2 * rng.normal(size=t.size), 10 - 0.5 * sine + 0.2 * rng.normal(size=t.size))
    noise = (50 + rng.normal(size=t.size).cumsum() * 0.05, 10 + rng.normal(size=t.size))
    return {"sticky": sticky, "external": external, "noise": noise}


@pytest.mark.parametrize("name", ["sticky", "external", "noise"])
def test_indicators_equal_their_references(records, name):
    op, pv = records[name]
    e = -pv
    m = jnp.ones(op.shape)
    T, reg, share = oscillation(jnp.asarray(e), m)
    Tr, regr, sharer = R.oscillation(e)
    assert float(T) == pytest.approx(Tr, rel=1e-9) and float(share) == pytest.approx(sharer, rel=1e-9)
    assert float(reg) == pytest.approx(regr, rel=1e-6)
    assert float(horch_phase(op, e, m, T)) == pytest.approx(R.horch_phase(op, e, Tr), abs=1e-9)
    assert float(shape_index(op, m, T)) == pytest.approx(R.shape_index(op, Tr), abs=1e-9)
    assert [float(v) for v in bicoherence(e, m)] == pytest.approx(list(R.bicoherence(e)), abs=1e-9)
    assert float(stuck_share(op, pv, m, T)) == pytest.approx(R.stuck_share(op, pv, Tr), abs=1e-9)


def test_indicators_tell_a_limit_cycle_from_a_sinusoid(records):
    """A sticky valve's cycle: regular, OP odd against the error (Horch), OP
    triangular (He); an external sinusoid: regular, but OP in phase with the error and
    sinusoidal; noise: no regular oscillation."""
    m = jnp.ones(1200)
    ind = {k: indicators(jnp.asarray(op), jnp.asarray(pv), jnp.full(1200, jnp.nan), m)
           for k, (op, pv) in records.items()}
    s, x, n = ind["sticky"], ind["external"], ind["noise"]
    assert float(s.period) == pytest.approx(120, rel=0.05) and float(s.regularity) > 1
    assert float(s.horch) > 0.9 and float(s.shape_op) > 0.6 and float(s.stuck_pv) > 0.2
    assert float(x.regularity) > 1 and float(x.horch) < 0.3 and float(x.shape_op) < 0.5
    assert float(n.regularity) < 1


def test_indicators_under_jit_and_vmap(records):
    """`indicators` jitted equals it eager, and vmapped over padded records equals a
    loop over the records, and (up to the periodogram's grid) the records cut to their
    real samples."""
    recs = [records[k] for k in ("sticky", "external", "sticky")]
    lengths = (1200, 1000, 900)
    loops = js.stack([js.make_loop(op[:n], pv[:n]) for (op, pv), n in zip(recs, lengths)])
    nan = jnp.full_like(loops.op, jnp.nan)
    batched = eqx.filter_jit(jax.vmap(internal.indicators))(loops.op, loops.pv, nan, loops.mask)
    first = (loops.op[0], loops.pv[0], nan[0], loops.mask[0])
    for a, b in zip(jax.tree.leaves(internal.indicators(*first)), jax.tree.leaves(indicators(*first))):
        assert float(b) == pytest.approx(float(a), rel=1e-9, abs=1e-12, nan_ok=True)
    for i, ((op, pv), n) in enumerate(zip(recs, lengths)):
        one = indicators(loops.op[i], loops.pv[i], nan[i], loops.mask[i])
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batched)):
            assert float(b[i]) == pytest.approx(float(a), rel=1e-9, abs=1e-12, nan_ok=True)
        # the padding changes only the periodogram's grid: the same oscillation, read
        # off a finer or coarser grid
        alone = indicators(jnp.asarray(op[:n]), jnp.asarray(pv[:n]), jnp.full(n, jnp.nan), jnp.ones(n))
        assert float(batched.period[i]) == pytest.approx(float(alone.period), rel=0.02)


@pytest.mark.parametrize("name", ["sticky", "external", "noise"])
def test_segmented_indicators_equal_their_reference(records, name):
    """A record longer than `segment` is read in equal segments: the period from the
    segments' averaged periodogram, the rest the median over the segments, as the
    slow reference computes them piece by piece."""
    op, pv = records[name]
    ind = indicators(jnp.asarray(op), jnp.asarray(pv), jnp.full(op.shape, jnp.nan), jnp.ones(op.shape), 400)
    ref = R.segmented(op, pv, 400)
    for key, value in ref.items():
        assert float(getattr(ind, key)) == pytest.approx(value, rel=1e-6, abs=1e-9, nan_ok=True), key


def test_segments_find_a_limit_cycle_under_a_slow_swing():
    """Over a long record a slow swing of the error carries more power than a fast
    limit cycle: read whole, the record shows the swing; read in segments of the
    default length, the limit cycle, regular and with its sticky signature."""
    t = np.arange(7200.0)
    rng = np.random.default_rng(1)
    square = np.sign(np.sin(2 * np.pi * t / 20.0))
    pv = 10 + 0.5 * square + 3.0 * np.sin(2 * np.pi * t / 1400.0) + 0.05 * rng.normal(size=t.size)
    op = 50 - 0.2 * np.cumsum(pv - 10 - 3.0 * np.sin(2 * np.pi * t / 1400.0))
    args = (jnp.asarray(op), jnp.asarray(pv), jnp.full(t.size, jnp.nan), jnp.ones(t.size))
    whole = indicators(*args)
    seg = indicators(*args, js.VerdictSettings().segment)
    assert float(whole.period) > 200
    assert float(seg.period) == pytest.approx(20, rel=0.05) and float(seg.regularity) > 1
    assert float(seg.share) > 0.5
    assert float(seg.horch) > 0.9 and float(seg.periods) == pytest.approx(7200 / float(seg.period))


def test_segmented_indicators_under_vmap_and_padding(records):
    """Segmented or whole is chosen per loop by its real samples: vmapped over padded
    records, the indicators equal a loop over the records; a record no longer than
    `segment` is read whole whatever its padding, and one cut to its real samples
    reads the same as padded."""
    op, pv = records["sticky"]
    lengths = (1200, 1000, 480)
    loops = js.stack([js.make_loop(op[:n], pv[:n]) for n in lengths])
    nan = jnp.full_like(loops.op, jnp.nan)
    batched = eqx.filter_jit(jax.vmap(lambda *a: internal.indicators(*a, segment=500)))(
        loops.op, loops.pv, nan, loops.mask)
    for i, n in enumerate(lengths):
        one = indicators(loops.op[i], loops.pv[i], nan[i], loops.mask[i], 500)
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batched)):
            assert float(b[i]) == pytest.approx(float(a), rel=1e-9, abs=1e-12, nan_ok=True)
        cut = indicators(jnp.asarray(op[:n]), jnp.asarray(pv[:n]), jnp.full(n, jnp.nan), jnp.ones(n), 500)
        if n > 500:  # each segment sits in an array of `segment` samples, padded or not
            for a, b in zip(jax.tree.leaves(cut), jax.tree.leaves(one)):
                assert float(b) == pytest.approx(float(a), rel=1e-9, abs=1e-12, nan_ok=True)
    whole = indicators(loops.op[2], loops.pv[2], nan[2], loops.mask[2])
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(batched)):
        assert float(b[2]) == pytest.approx(float(a), rel=1e-12, abs=1e-15, nan_ok=True)


def test_segment_setting():
    """The default segment is the longest record of the calibration's fleet; a bad
    one is refused."""
    assert js.VerdictSettings().segment == LONGEST
    with pytest.raises(ValueError, match="segment"):
        js.VerdictSettings(segment=0)


def test_setpoint_gives_the_control_error(records):
    """With a recorded setpoint the indicators read SP − PV: a setpoint that moves
    with PV leaves no error oscillation; without one they read −PV."""
    op, pv = records["sticky"]
    m = jnp.ones(pv.shape)
    none = indicators(op, pv, jnp.full(pv.shape, jnp.nan), m)
    flat = indicators(op, pv, jnp.full(pv.shape, 7.0), m)
    assert float(flat.period) == pytest.approx(float(none.period)) and float(flat.horch) == pytest.approx(
        float(none.horch))


def test_kstep_prediction_equals_the_plain_recursion():
    rng = np.random.default_rng(1)
    y, x = rng.normal(size=200).cumsum(), rng.normal(size=200)
    theta = np.array([0.6, 0.2, 0.5, -0.3, 0.1])  # a1, a2, b0, b1, c
    for k in (1, 3, 5):
        got = np.asarray(kstep_prediction(jnp.asarray(theta), jnp.asarray(y), jnp.asarray(x), 2, 2, 3, k))
        want = R.kstep(theta, y, x, 2, 2, 3, k)
        np.testing.assert_allclose(got[20:], want[20:], rtol=1e-10, atol=1e-10)


def _arx_record(sticky: bool, seed: int, n=1200):
    """`(op, pv)`: OP a wandering signal that reverses often, PV an ARX model
    (a = 0.7, b = [0.5, 0.2], two samples of delay) driven by OP through a Kano valve
    with S 0.3 of OP's range and J half of S (a point of the cross-validation's grid)
    when `sticky`, else by OP itself; plus white noise."""
    rng = np.random.default_rng(seed)
    op = 50 + np.cumsum(rng.normal(0, 0.5, n))
    span = np.ptp(op)
    x = np.asarray(js.Kano(0.3 * span, 0.15 * span)(jnp.asarray(op))) if sticky else op
    pv = np.full(n, (0.5 + 0.2) * x[0] / 0.3)  # at rest at the start
    for t in range(3, n):
        pv[t] = 0.7 * pv[t - 1] + 0.5 * x[t - 2] + 0.2 * x[t - 3]
    return op, pv + rng.normal(0, 0.05 * np.std(pv), n)


def test_crossval_finds_the_sticky_valve():
    """Blocked cross-validation where the truth is in its model class: a Kano valve
    removes most of the linear valve's held-out prediction error of a record driven
    through a sticky valve, and none of a record driven by OP itself; vmapped over
    padded records it equals the record-by-record values."""
    op, pv = _arx_record(False, 2)
    loops = [js.make_loop(*_arx_record(True, 1)), js.make_loop(op[:1000], pv[:1000])]
    gains = [np.asarray(internal.crossval_gain(lp.op, lp.pv, lp.mask)) for lp in loops]
    assert np.min(gains[0]) > 30 and np.max(gains[1]) < 5  # no fold credits a Kano valve on a linear record
    batch = js.stack(loops)
    together = np.asarray(eqx.filter_jit(jax.vmap(internal.crossval_gain))(batch.op, batch.pv, batch.mask))
    np.testing.assert_allclose(together[0], gains[0], rtol=1e-6, atol=1e-6)


def _gate_of(op, pv, sp=None, settings=js.VerdictSettings()):
    op, pv = jnp.asarray(op, float), jnp.asarray(pv, float)
    sp = jnp.full_like(pv, jnp.nan) if sp is None else jnp.asarray(sp, float)
    m = jnp.ones_like(op)
    return GATES[int(gate(gate_measures(op, pv, sp, m), indicators(op, pv, sp, m), settings))]


def test_gate_names_each_reason(records):
    """Each reason on a record made to show it; a clean limit cycle passes."""
    op, pv = records["sticky"]
    assert _gate_of(op, pv) == "ok"
    assert _gate_of(op, np.full_like(pv, 3.5)) == "frozen_sensor"
    assert _gate_of(np.clip(op, None, np.quantile(op, 0.6)), pv) == "saturated"
    step = np.round(pv / 2.0) * 2.0  # a historian's coarse steps: flat runs, then jumps
    held = pv.copy()
    for i in range(1, len(held)):  # deadband compression
        held[i] = held[i - 1] if abs(pv[i] - held[i - 1]) < 1.5 else pv[i]
    assert _gate_of(op, held) == "compressed" or _gate_of(op, step) == "compressed"
    assert _gate_of(op, held) == "compressed"
    t = np.arange(len(pv))
    sp = 10 + 20 * (t > 600)
    assert _gate_of(op, pv + 20 * (t > 600), sp) == "setpoint_moves"
    slow = 50 + 3 * np.sin(2 * np.pi * t / 900.0)  # under two periods in the record
    assert _gate_of(slow, -slow + np.random.default_rng(0).normal(0, 0.01, t.size)) == "few_periods"


def test_hard_gated_is_the_gate_s_hard_codes(records):
    """`hard_gated` is True exactly where `gate` returns a code of `HARD`, one record
    at a time and vmapped over a batch of them."""
    op, pv = records["sticky"]
    held = pv.copy()
    for i in range(1, len(held)):
        held[i] = held[i - 1] if abs(pv[i] - held[i - 1]) < 1.5 else pv[i]
    t = np.arange(len(pv))
    cases = [(op, pv), (op, np.full_like(pv, 3.5)), (np.clip(op, None, np.quantile(op, 0.6)), pv), (op, held),
             (op, pv + 20 * (t > 600))]
    sp = np.full(len(pv), np.nan)
    m = np.ones(len(pv))
    one = []
    for o, p in cases:
        g = internal.gate_measures(jnp.asarray(o, float), jnp.asarray(p, float), jnp.asarray(sp), jnp.asarray(m))
        code = GATES[int(gate(g, internal.indicators(jnp.asarray(o, float), jnp.asarray(p, float), sp, m),
                              js.VerdictSettings()))]
        one.append(bool(internal.hard_gated(g)))
        assert one[-1] == (code in internal.HARD), code
    assert one == [False, True, True, True, False]
    ops, pvs = (jnp.asarray(np.stack(x), float) for x in zip(*cases))
    batched = jax.vmap(lambda o, p: internal.hard_gated(internal.gate_measures(o, p, sp, m)))(ops, pvs)
    assert [bool(b) for b in batched] == one


def test_setpoint_moves_leave_the_call_to_a_model_that_explains_them():
    """Under setpoint moves a low probability is `inconclusive`, unless the model-based
    test wins with a Kano model that simulates the held-out PV well and a band that
    is a sizeable part of OP's travel; elsewhere the model-based test alone never
    calls a loop sticky, and a hard gate stays inconclusive whatever it says."""
    s = js.VerdictSettings()
    sp, ok, frozen = (GATES.index(g) for g in ("setpoint_moves", "ok", "frozen_sensor"))

    def call(code, p=0.1, wins=True, fitness=75.0, band=0.2, judged=True):
        return internal.VERDICTS[int(internal.decide(jnp.asarray(judged), jnp.asarray(code), jnp.asarray(p),
                                                     jnp.asarray(wins), jnp.asarray(fitness), jnp.asarray(band), s))]

    assert call(sp) == "stiction"
    assert call(sp, wins=False) == "inconclusive"
    assert call(sp, fitness=s.setpoint_fitness - 1) == "inconclusive"
    assert call(sp, fitness=jnp.nan) == "inconclusive"
    assert call(sp, band=s.setpoint_band / 2) == "inconclusive"
    assert call(sp, wins=False, p=0.9) == "stiction"
    assert call(sp, judged=False) == "inconclusive"
    assert call(ok) == "no_stiction" and call(ok, p=0.9) == "stiction"
    assert call(frozen, p=0.9) == "inconclusive"
    codes = jnp.asarray([sp, ok, sp, frozen])
    fitness = jnp.asarray([75.0, 75, 10, 75])
    batched = jax.vmap(lambda c, f: internal.decide(True, c, 0.1, True, f, 0.2, s))(codes, fitness)
    assert [internal.VERDICTS[int(v)] for v in batched] == ["stiction", "no_stiction", "inconclusive", "inconclusive"]


def test_a_stuck_valve_is_not_a_compressed_record():
    """PV flat over most of the record while OP travels is left to the evidence (a
    stuck valve); PV in many short flat runs is compression."""
    t = np.arange(900.0)
    op = 5 + 0.1 * t
    pv = np.where(t < 60, 0.3 * np.exp(-t / 20) + 0.01 * np.sin(t), 1e-16)
    m = gate_measures(jnp.asarray(op), jnp.asarray(pv), jnp.full(900, jnp.nan), jnp.ones(900))
    assert float(m.compressed) > 0.5 and float(m.longest_flat) > 0.5


def test_fit_calibration_equals_newton_reference():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(300, 3)) * [1, 2, 0.5] + [0, 1, -1]
    y = (rng.random(300) < 1 / (1 + np.exp(-(X @ [1.0, -0.5, 2.0] + 0.3)))).astype(float)
    w = rng.uniform(0.5, 2, 300)
    cal = fit_calibration(X, y, w, l2=1.0, names=("a", "b", "c"))
    mean, scale, weights, bias = R.logistic(X, y, w, 1.0)
    np.testing.assert_allclose(np.asarray(cal.mean), mean, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(cal.scale), scale, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(cal.weights), weights, rtol=1e-7)
    assert float(cal.bias) == pytest.approx(bias, rel=1e-7)


def test_calibration_is_reliable_where_the_model_holds():
    """Reliability table of `fit_calibration` on data from a logistic model: in every
    probability band with enough points, the observed rate is within the sampling
    error of the mean predicted probability (on fresh data, not the fitted rows)."""
    rng = np.random.default_rng(3)

    def draw(n):
        X = rng.normal(size=(n, 2))
        p = 1 / (1 + np.exp(-(1.5 * X[:, 0] - X[:, 1])))
        return X, (rng.random(n) < p).astype(float)

    cal = fit_calibration(*draw(4000), l2=0.1)
    X, y = draw(4000)
    p = np.asarray(jax.vmap(cal.probability)(jnp.asarray(X)))
    for lo in np.arange(0, 1, 0.2):
        m = (p >= lo) & (p < lo + 0.2)
        if m.sum() > 100:
            assert abs(y[m].mean() - p[m].mean()) < 3 * np.sqrt(0.25 / m.sum()) + 0.01


def test_probability_gradient_matches_finite_differences():
    """The probability is smooth in its features: its gradient by autodiff equals
    central differences (a research user may differentiate through it)."""
    from jaxstiction.internal import CALIBRATION

    x = jnp.asarray(np.asarray(CALIBRATION.mean) + 0.3 * np.asarray(CALIBRATION.scale))
    g = jax.grad(CALIBRATION.probability)(x)
    h = 1e-6
    fd = [(CALIBRATION.probability(x.at[i].add(h)) - CALIBRATION.probability(x.at[i].add(-h))) / (2 * h)
          for i in range(x.shape[0])]
    np.testing.assert_allclose(np.asarray(g), np.asarray(fd), rtol=1e-5, atol=1e-9)


@pytest.mark.slow
def test_screen_says_inconclusive_with_the_reason(records):
    """End to end through the screen: a record made to show each gate's reason gets
    `inconclusive` with that reason named (a frozen sensor before any fit); a clean
    limit cycle passes the gate. One length bucket, so one compilation."""
    op, pv = records["sticky"]
    t = np.arange(op.size)
    held = pv.copy()
    for i in range(1, len(held)):  # a historian's deadband compression
        held[i] = held[i - 1] if abs(pv[i] - held[i - 1]) < 1.5 else pv[i]
    loops = {
        "clean": js.make_loop(op, pv),
        "frozen": js.make_loop(op, np.full_like(pv, 3.5)),
        "saturated": js.make_loop(np.clip(op, None, np.quantile(op, 0.6)), pv),
        "compressed": js.make_loop(op, held),
        "setpoint": js.make_loop(op, pv + 20 * (t > 600), sp=10 + 20 * (t > 600)),
    }
    out = {e["name"]: e for e in js.screen_loops(loops, js.ScreenSettings(chunk=2))}
    assert out["clean"]["gate"] == "ok" and out["clean"]["reason"] == ""
    assert out["frozen"]["verdict"] == "inconclusive" and out["frozen"]["gate"] == "frozen_sensor"
    assert "frozen sensor" in out["frozen"]["reason"] and out["frozen"]["stiction_detected"] is False
    for name in ("saturated", "compressed"):
        assert out[name]["verdict"] == "inconclusive" and out[name]["gate"] == name and out[name]["reason"]
        assert out[name]["stiction_detected"] is False
    e = out["setpoint"]
    assert e["gate"] == "setpoint_moves"
    by_model = e["model_wins"] and (e["fitness_kano"] or -1e9) >= 50 and e["band_fraction"] >= 0.10
    assert e["verdict"] == ("stiction" if e["stiction_probability"] >= 0.5 or by_model else "inconclusive")
    for e in out.values():
        assert "\n" not in e.get("reason", "")
