"""Tests for the nominal-model file (`_io/nominal.py`): JSON ⇄ `LoopModel`."""

import json

import numpy as np
import pytest

import jaxstiction as js
from jaxstiction import (
    ActuatorLag,
    Choudhury,
    Deadband,
    DeadTime,
    He,
    Kano,
    LinearProcess,
    LoopModel,
    nominal_to_dict,
    nominal_ts,
    read_nominal,
    Sinusoid,
    SplineValve,
)


try:
    from tests.helpers import raises_one_line
except ImportError:  # pytest with tests/ on sys.path
    from helpers import raises_one_line



NOMINAL = {
    "Ts": 1.0,
    "process": {"b": [0.0, 0.2, 0.1], "a": [1.0, -1.2, 0.5], "delay": 3},
    "op_offset": 50.0,
    "pv_offset": 10.0,
    "valve": {"model": "linear"},
}


def _nominal(**changes):
    """A copy of NOMINAL with dotted keys set (or deleted when the value is None)."""
    m = json.loads(json.dumps(NOMINAL))
    for key, value in changes.items():
        target = m
        *parents, last = key.split(".")
        for p in parents:
            target = target[p]
        if value is None:
            del target[last]
        else:
            target[last] = value
    return m


def reference_pv(b, a, delay, op_offset, pv_offset, op):
    """PV = pv_offset + B/A q^-delay (OP - op_offset) by the difference equation, at
    rest before the first sample (past OP = op[0], past PV at its steady value)."""
    b, a, op = (np.asarray(v, dtype=np.float64) for v in (b, a, op))
    u = op - op_offset
    y_rest = u[0] * b.sum() / a.sum()
    y = np.zeros(op.size)
    for t in range(op.size):
        acc = 0.0
        for j, bj in enumerate(b):
            k = t - delay - j
            acc += bj * (u[k] if k >= 0 else u[0])
        for i in range(1, a.size):
            acc -= a[i] * (y[t - i] if t - i >= 0 else y_rest)
        y[t] = acc / a[0]
    return pv_offset + y


def ramp_and_reverse():
    """OP ramps up 50 → 60, rests, then down to 44 and back up a little."""
    return np.concatenate(
        [np.full(5, 50.0), np.linspace(50, 60, 40), np.full(10, 60.0), np.linspace(60, 44, 60), np.linspace(44, 47, 20)]
    )


# ------------------------------------------------------------------------ reading


def test_exports():
    assert js.read_nominal is read_nominal
    assert js.nominal_ts is nominal_ts
    assert js.nominal_to_dict is nominal_to_dict
    assert not hasattr(js, "NominalModel") and not hasattr(js, "simulate_nominal")


def test_read_nominal_file_and_dict(tmp_path):
    p = tmp_path / "nominal.json"
    p.write_text(json.dumps(NOMINAL))
    for m in (read_nominal(p), read_nominal(str(p)), read_nominal(NOMINAL)):
        assert isinstance(m, LoopModel)
        assert m.chain == () and m.output == ()
        np.testing.assert_allclose(m.process.b, [0.0, 0.2, 0.1])
        np.testing.assert_allclose(m.process.a, [1.0, -1.2, 0.5])
        assert m.process.delay == 3 and isinstance(m.process.delay, int)
        assert float(m.op_offset) == 50.0 and float(m.pv_offset) == 10.0
        # the default noise model
        np.testing.assert_array_equal(m.noise.c, [1.0])
        np.testing.assert_array_equal(m.noise.d, [1.0])
    assert nominal_ts(p) == 1.0 and nominal_ts({"Ts": 2}) == 2.0
    assert isinstance(nominal_ts({"Ts": 2}), float)
    # defaults for optional keys
    d = read_nominal({"Ts": 2, "process": {"b": [1.0], "a": [1.0]}})
    assert d.process.delay == 0 and float(d.op_offset) == 0.0 and float(d.pv_offset) == 0.0
    assert d.chain == ()
    assert read_nominal(_nominal(**{"process.delay": 2.0})).process.delay == 2
    assert read_nominal(_nominal(valve="linear")).chain == ()
    assert read_nominal(_nominal(valve=None)).chain == ()
    assert read_nominal(_nominal(extra_key="ignored")).chain == ()


@pytest.mark.parametrize(
    "valve, cls, params",
    [
        ({"model": "Kano", "S": 3.0, "J": 1.0}, Kano, {"S": 3.0, "J": 1.0}),
        ({"model": "choudhury", "S": 4, "J": 0}, Choudhury, {"S": 4.0, "J": 0.0}),
        ({"model": " he ", "S": 2.0, "J": 0.5}, He, {"S": 2.0, "J": 0.5}),
        ({"model": "deadband", "width": 1.5}, Deadband, {"width": 1.5}),
    ],
)
def test_valve_models_become_blocks(valve, cls, params):
    m = read_nominal(_nominal(valve=valve))
    assert len(m.chain) == 1 and type(m.chain[0]) is cls
    for key, value in params.items():
        assert float(getattr(m.chain[0], key)) == value


def test_extended_form():
    m = read_nominal(
        _nominal(
            valve=None,
            chain=[
                {"block": "actuator_lag", "a": 0.8},
                {"block": "Kano", "S": 3.0, "J": 1.0},
                {"block": "travel_limits", "hi": 90},
                {"block": "dead_time", "k": 2.0},
            ],
            output=[{"block": "sinusoid", "amplitude": 1.0, "period": 50}],
        )
    )
    assert [js.block_name(b) for b in m.chain] == ["actuator_lag", "kano", "travel_limits", "dead_time"]
    assert float(m.chain[0].a) == 0.8
    assert float(m.chain[2].lo) == -np.inf and float(m.chain[2].hi) == 90.0
    assert m.chain[3].k == 2 and isinstance(m.chain[3].k, int)
    assert len(m.output) == 1 and type(m.output[0]) is Sinusoid
    assert float(m.output[0].phase) == 0.0
    d = read_nominal(_nominal(valve=None, output=[{"block": "drift", "step_std": 0.3, "key": [0, 7]}]))
    np.testing.assert_array_equal(d.output[0].key, [0, 7])
    assert d.output[0].key.dtype == np.uint32
    nb = read_nominal(_nominal(valve=None, output=[{"block": "narrow_band", "rms": 2.0, "period": 40, "key": [0, 3]}]))
    assert type(nb.output[0]) is js.NarrowBand and float(nb.output[0].r) == 0.99
    np.testing.assert_array_equal(nb.output[0].key, [0, 3])
    assert read_nominal(_nominal(valve=None, chain=[])).chain == ()


# ------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"process.a": [1.0, -1.05]}, r"nominal model is unstable: pole at 1\.05"),
        ({"process.a": [1.0, -1.0]}, r"nominal model is integrating \(pole at 1, as a level loop\)"),
        ({"process.a": [1.0, -1.5, 0.5]}, r"nominal model is integrating"),
        ({"process.a": [1.0, 0.0, 1.21]}, r"unstable: pole at .*j \(modulus 1\.1\)"),
        ({"process.a": [2.0, -1.0]}, r"process\.a\[0\] must be 1"),
        ({"process.a": []}, r"process\.a is empty"),
        ({"process.b": []}, r"process\.b is empty"),
        ({"process.b": None}, r"missing key 'process\.b'"),
        ({"process.a": None}, r"missing key 'process\.a'"),
        ({"process": None}, r"missing key 'process'"),
        ({"process": [1, 2]}, r"'process' must be an object"),
        ({"Ts": None}, r"missing key 'Ts'"),
        ({"Ts": -1}, r"Ts must be positive"),
        ({"Ts": "1"}, r"Ts must be a number"),
        ({"process.delay": -1}, r"delay must be ≥ 0"),
        ({"process.delay": 1.5}, r"delay must be a whole number"),
        ({"process.delay": "2"}, r"delay must be a whole number"),
        ({"process.b": [1.0, "x"]}, r"process\.b\[1\] must be a number"),
        ({"process.b": [1.0, True]}, r"process\.b\[1\] must be a number"),
        ({"process.b": 1.0}, r"process\.b must be a list of numbers"),
        ({"valve": {"model": "magic"}}, r"unknown valve\.model 'magic'"),
        ({"valve": 3}, r"'valve' must be an object with 'model'"),
        ({"valve": {"model": "kano", "S": 1.0}}, r"needs 'valve\.J'"),
        ({"valve": {"model": "he", "J": 1.0}}, r"valve model 'he' needs 'valve\.S'"),
        ({"valve": {"model": "choudhury", "S": 1.0, "J": -1.0}}, r"must be ≥ 0"),
        ({"valve": {"model": "kano", "S": "big", "J": 1.0}}, r"valve\.S must be a number"),
        ({"valve": {"model": "deadband"}}, r"valve model 'deadband' needs 'valve\.width'"),
        ({"valve": {"model": "deadband", "width": -1}}, r"valve\.width must be ≥ 0"),
        ({"op_offset": "fifty"}, r"op_offset must be a number"),
        ({"pv_offset": None, "op_offset": float("nan")}, r"op_offset must be finite"),
        # extended form
        ({"chain": []}, r"give either 'valve' or 'chain', not both"),
        ({"valve": None, "chain": {"block": "kano"}}, r"'chain' must be a list of blocks"),
        ({"valve": None, "chain": ["kano"]}, r"chain\[0\] must be an object with 'block'"),
        ({"valve": None, "chain": [{"block": "magic"}]}, r"unknown block 'magic' in chain\[0\]"),
        ({"valve": None, "chain": [{"block": "sinusoid", "amplitude": 1, "period": 5}]},
         r"block 'sinusoid' in chain\[0\] acts on the process output; list it under 'output'"),
        ({"output": [{"block": "kano", "S": 1, "J": 0}]},
         r"block 'kano' in output\[0\] acts on the process input; list it under 'chain'"),
        ({"valve": None, "chain": [{"block": "kano", "S": 1.0}]}, r"block 'kano' in chain\[0\] needs 'J'"),
        ({"valve": None, "chain": [{"block": "kano", "S": 1.0, "J": 0, "x": 1}]},
         r"block 'kano' in chain\[0\] has no parameter 'x' \(parameters: S, J\)"),
        ({"valve": None, "chain": [{"block": "actuator_lag", "a": 1.0}]}, r"chain\[0\]\.a must be in \[0, 1\)"),
        ({"valve": None, "chain": [{"block": "dead_time", "k": 1.5}]}, r"chain\[0\]\.k must be a whole number"),
        ({"valve": None, "chain": [{"block": "rate_limit", "max_rate": "1"}]},
         r"chain\[0\]\.max_rate must be a number"),
        ({"valve": None, "chain": [{"block": "travel_limits", "lo": 60, "hi": 40}]},
         r"chain\[0\]: lo must be ≤ hi"),
        ({"output": [{"block": "quantiser", "step_size": 0}]}, r"output\[0\]\.step_size must be > 0"),
        ({"output": [{"block": "drift", "step_std": 0.1, "key": [-1]}]}, r"output\[0\]\.key must be a list of int"),
        ({"output": [{"block": "narrow_band", "rms": 1.0, "period": 30.0, "r": 1.0}]},
         r"output\[0\]\.r must be in \[0, 1\)"),
        ({"output": "sinusoid"}, r"'output' must be a list of blocks"),
    ],
)
def test_read_nominal_errors(changes, match):
    raises_one_line(match, read_nominal, _nominal(**changes))


def test_read_nominal_file_errors(tmp_path):
    for func in (read_nominal, nominal_ts):
        raises_one_line(r"file not found: '.*none\.json'", func, tmp_path / "none.json")
        raises_one_line(r"'.*' is not a file", func, tmp_path)
        p = tmp_path / "bad.json"
        p.write_text('{"Ts": 1.0,\n "process": }')
        raises_one_line(r"'.*bad\.json' is not valid JSON \(.* line 2", func, p)
        q = tmp_path / "list.json"
        q.write_text("[1, 2]")
        raises_one_line(r"must hold a JSON object", func, q)
        r = tmp_path / "latin1.json"
        r.write_bytes(b'{"Ts": "\xff"}')
        raises_one_line(r"'.*latin1\.json' is not a JSON text file", func, r)
        raises_one_line(r"cannot read a nominal model from a int", func, 3)
    u = tmp_path / "unstable.json"
    u.write_text(json.dumps(_nominal(**{"process.a": [1.0, -1.05]})))
    msg = raises_one_line(r"nominal model is unstable: pole at 1\.05", read_nominal, u)
    assert "unstable.json" in msg
    assert nominal_ts(u) == 1.0  # nominal_ts checks Ts only
    raises_one_line(r"missing key 'Ts'", nominal_ts, {"process": {}})
    raises_one_line(r"Ts must be positive", nominal_ts, {"Ts": 0})


# ---------------------------------------------------------------------- round trip


@pytest.mark.parametrize(
    "changes",
    [
        {},
        {"Ts": 0.5, "process.delay": 0, "op_offset": 0.0},
        {"valve": {"model": "kano", "S": 3.0, "J": 1.0}},
        {"valve": {"model": "choudhury", "S": 3.0, "J": 0.0}},
        {"valve": {"model": "he", "S": 2.5, "J": 0.5}},
        {"valve": {"model": "deadband", "width": 1.5}},
        {
            "valve": None,
            "chain": [
                {"block": "actuator_lag", "a": 0.8},
                {"block": "rate_limit", "max_rate": 2.0},
                {"block": "kano", "S": 3.0, "J": 1.0},
                {"block": "travel_limits", "lo": 5.0},
                {"block": "equal_percentage", "R": 30.0},
                {"block": "dead_time", "k": 2},
            ],
            "output": [
                {"block": "sinusoid", "amplitude": 1.0, "period": 50.0, "phase": 0.25},
                {"block": "drift", "step_std": 0.3, "key": [0, 7]},
                {"block": "narrow_band", "rms": 2.0, "period": 40.0, "r": 0.98, "key": [0, 3]},
                {"block": "quantiser", "step_size": 0.1},
            ],
        },
        {"valve": None, "chain": [{"block": "travel_limits", "lo": 0.0, "hi": 100.0}]},
        {"valve": None, "chain": [{"block": "deadband", "width": 1.0}, {"block": "dead_time", "k": 1}]},
    ],
)
def test_round_trip(changes):
    d = _nominal(**changes)
    m = read_nominal(d)
    back = nominal_to_dict(m, ts=nominal_ts(d))
    assert back == d
    json.dumps(back)
    assert nominal_to_dict(read_nominal(back), ts=back["Ts"]) == back


def test_nominal_to_dict_of_built_models():
    m = LoopModel(
        chain=(Kano(3, 1),),
        process=LinearProcess(b=(0.0, 1.0, 0.5), a=(1.0, -1.5, 0.7)),
        op_offset=50,
    )
    assert nominal_to_dict(m) == {
        "Ts": 1.0,
        "process": {"b": [0.0, 1.0, 0.5], "a": [1.0, -1.5, 0.7], "delay": 0},
        "op_offset": 50.0,
        "pv_offset": 0.0,
        "valve": {"model": "kano", "S": 3.0, "J": 1.0},
    }
    d = nominal_to_dict(LoopModel(chain=(ActuatorLag(0.5), DeadTime(1)), process=m.process), ts=2)
    assert d["Ts"] == 2.0 and "valve" not in d
    assert d["chain"] == [{"block": "actuator_lag", "a": 0.5}, {"block": "dead_time", "k": 1}]
    with pytest.raises(TypeError, match="needs a LoopModel"):
        nominal_to_dict(NOMINAL)
    with pytest.raises(ValueError, match="ts must be positive"):
        nominal_to_dict(m, ts=0.0)
    spline = SplineValve.linear(0.0, 100.0, 5)
    with pytest.raises(ValueError, match=r"chain\[0\]: a SplineValve cannot be written") as info:
        nominal_to_dict(LoopModel(chain=(spline,), process=m.process))
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------- simulation


def test_linear_simulate_matches_difference_equation():
    rng = np.random.default_rng(0)
    m = read_nominal(NOMINAL)
    op = 53 + rng.normal(0, 2, 300)  # starts away from op_offset: the rest state matters
    b, a = NOMINAL["process"]["b"], NOMINAL["process"]["a"]
    expected = reference_pv(b, a, 3, 50.0, 10.0, op)
    np.testing.assert_allclose(m.simulate(op), expected, rtol=1e-10, atol=1e-10)
    # FIR process, no delay, by hand: u = [2, 2, 4] with u(-1) = 2
    f = read_nominal({"Ts": 1, "process": {"b": [0.5, 0.25], "a": [1]}, "op_offset": 1.0})
    np.testing.assert_allclose(f.simulate(np.array([3.0, 3.0, 5.0])), [1.5, 1.5, 2.5])
    np.testing.assert_allclose(reference_pv([0.5, 0.25], [1.0], 0, 1.0, 0.0, [3.0, 3.0, 5.0]), [1.5, 1.5, 2.5])


def test_linear_step_gain_and_delay():
    m = read_nominal(NOMINAL)
    op = np.r_[np.full(10, 50.0), np.full(400, 51.0)]  # +1 step at t = 10
    y = np.asarray(m.simulate(op))
    gain = sum(NOMINAL["process"]["b"]) / sum(NOMINAL["process"]["a"])
    assert y[-1] == pytest.approx(10.0 + gain, rel=1e-6)
    assert np.all(y[: 10 + 3 + 1] == 10.0)  # b0 = 0 and delay 3
    assert y[14] != 10.0


def test_kano_nominal_model_simulates_through_kano():
    op = ramp_and_reverse()
    lin = read_nominal(NOMINAL)
    k = read_nominal(_nominal(valve={"model": "kano", "S": 3.0, "J": 1.0}))
    y_lin, y_k = np.asarray(lin.simulate(op)), np.asarray(k.simulate(op))
    assert np.max(np.abs(y_k - y_lin)) > 0.5
    # the valve sticks at the reversal: position differs from OP there
    assert np.max(np.abs(np.asarray(k.valve(op)) - op)) >= 1.0
    same = LoopModel(
        chain=(Kano(3.0, 1.0),),
        process=LinearProcess(b=NOMINAL["process"]["b"], a=NOMINAL["process"]["a"], delay=3),
        op_offset=50.0,
        pv_offset=10.0,
    )
    np.testing.assert_array_equal(y_k, np.asarray(same.simulate(op)))
    # the process sees exactly the Kano valve's output
    valve = np.asarray(Kano(3.0, 1.0)(op))
    b, a = NOMINAL["process"]["b"], NOMINAL["process"]["a"]
    np.testing.assert_allclose(y_k, reference_pv(b, a, 3, 50.0, 10.0, valve), rtol=1e-10, atol=1e-10)
