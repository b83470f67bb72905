"""Tests for loop data and nominal model input (`_io`, `_checks`)."""

import json
from pathlib import Path

import numpy as np
import pytest

from jaxstiction._checks import check_loop, LoopDataError
from jaxstiction._io import (
    find_loop_files,
    list_mat_loops,
    LoopData,
    NominalModel,
    read_loop,
    read_nominal,
    simulate_nominal,
)


ISDB = Path(__file__).parents[2] / "shared/data/isdb"

RNG = np.random.default_rng(0)
N = 50
OP = 50 + 5 * np.sin(np.arange(N) / 3.0) + RNG.normal(0, 0.1, N)
PV = 10 + np.cos(np.arange(N) / 3.0) + RNG.normal(0, 0.1, N)
SP = np.full(N, 10.0)


def write_csv(path, header, columns, fmt="{:.10g}", sep=","):
    lines = [sep.join(header)]
    for row in zip(*columns):
        lines.append(sep.join(fmt.format(v) for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def raises_one_line(match, func, *args, **kwargs):
    """Call `func`; assert a one-line LoopDataError (a ValueError) matching `match`."""
    with pytest.raises(LoopDataError, match=match) as info:
        func(*args, **kwargs)
    msg = str(info.value)
    assert isinstance(info.value, ValueError)
    assert "\n" not in msg and "\r" not in msg
    return msg


# ------------------------------------------------------------------ CSV round trips


def test_csv_with_t(tmp_path):
    t = np.arange(N) * 2.5
    p = write_csv(tmp_path / "loop1.csv", ["t", "OP", "PV"], [t, OP, PV])
    d = read_loop(p)
    assert isinstance(d, LoopData)
    assert d.name == "loop1"
    assert d.ts == pytest.approx(2.5)
    assert d.op.dtype == np.float64 and d.pv.dtype == np.float64
    np.testing.assert_allclose(d.op, OP, rtol=1e-9)
    np.testing.assert_allclose(d.pv, PV, rtol=1e-9)
    np.testing.assert_allclose(d.t, t)
    assert d.sp is None
    assert len(d) == N and d.n == N


def test_csv_without_t_defaults_ts_1_and_str_path(tmp_path):
    p = write_csv(tmp_path / "x.csv", ["OP", "PV"], [OP, PV])
    d = read_loop(str(p))
    assert d.ts == 1.0 and d.t is None
    np.testing.assert_allclose(d.time, np.arange(N))
    d2 = read_loop(p, ts=0.2, name="mine")
    assert d2.ts == 0.2 and d2.name == "mine"


def test_csv_with_sp_odd_header_case_and_extra_columns(tmp_path):
    p = write_csv(
        tmp_path / "odd.csv",
        [" Time ", "tag", " op", "Pv ", "s P"],
        [np.arange(N) * 10.0, np.zeros(N), OP, PV, SP],
    )
    d = read_loop(p)
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.pv, PV)
    np.testing.assert_allclose(d.sp, SP)
    assert d.ts == 10.0


def test_csv_semicolon_bom_and_blank_lines(tmp_path):
    p = tmp_path / "semi.csv"
    body = "OP;PV\n\n1;2\n2;3\n\n3;5\n"
    p.write_bytes(b"\xef\xbb\xbf" + body.encode())
    d = read_loop(p)
    np.testing.assert_allclose(d.op, [1, 2, 3])
    np.testing.assert_allclose(d.pv, [2, 3, 5])


def test_ts_precedence(tmp_path):
    p = write_csv(tmp_path / "a.csv", ["t", "OP", "PV"], [np.arange(N) * 4.0, OP, PV])
    assert read_loop(p).ts == 4.0  # from t
    assert read_loop(p, ts=7.0).ts == 7.0  # explicit wins
    m = {"OP": OP, "PV": PV, "Ts": 3.0}
    assert read_loop(m).ts == 3.0  # file Ts
    assert read_loop({**m, "t": np.arange(N) * 5.0}).ts == 5.0  # t beats Ts
    assert read_loop(m, ts=2.0).ts == 2.0  # explicit beats Ts
    assert read_loop({"OP": OP, "PV": PV}).ts == 1.0  # default


# ---------------------------------------------------------------- DataFrame / dict


def test_dataframe():
    pd = pytest.importorskip("pandas")
    df = pd.DataFrame({"OP ": OP, "pv": PV, "Sp": SP})
    d = read_loop(df, ts=0.5, name="df")
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.sp, SP)
    assert d.ts == 0.5 and d.name == "df"
    df2 = pd.DataFrame({"t": np.arange(N) * 2.0, "OP": OP, "PV": PV})
    assert read_loop(df2).ts == 2.0


def test_dataframe_datetime_index():
    pd = pytest.importorskip("pandas")
    idx = pd.date_range("2024-01-01", periods=N, freq="5s")
    d = read_loop(pd.DataFrame({"OP": OP, "PV": PV}, index=idx))
    assert d.ts == 5.0
    assert d.t[0] == 0.0


def test_dataframe_bad_values():
    pd = pytest.importorskip("pandas")
    pv = list(PV.astype(object))
    pv[7] = "oops"
    df = pd.DataFrame({"OP": OP, "PV": pv})
    msg = raises_one_line(r"`PV`.*non-numeric.*'oops'.*index 7", read_loop, df)
    assert "loop" in msg
    raises_one_line(r"`PV` column missing", read_loop, pd.DataFrame({"OP": OP}))


def test_dict_and_lists():
    d = read_loop({"op": list(OP), "PV": tuple(PV)}, name="d")
    np.testing.assert_allclose(d.op, OP)
    assert d.name == "d"
    # column vectors are accepted
    d2 = read_loop({"OP": OP[:, None], "PV": PV[None, :]})
    assert d2.op.shape == (N,)


# ------------------------------------------------------------------------- .mat


def _isdb_mat(path, n_loops=1):
    sio = pytest.importorskip("scipy.io")
    chem = {}
    for i in range(n_loops):
        chem[f"loop{23 + i}"] = {
            "OP": OP + i,
            "PV": PV.reshape(-1, 1),
            "Ts": 10.0,
            "comments": "flow loop",
        }
    sio.savemat(str(path), {"cdata": {"chemicals": chem, "info": "isdb"}})
    return path


def test_mat_nested_isdb(tmp_path):
    p = _isdb_mat(tmp_path / "isdb.mat")
    d = read_loop(p)
    assert d.name == "isdb"
    assert d.ts == 10.0
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.pv, PV)
    assert read_loop(p, ts=1.0).ts == 1.0
    assert list_mat_loops(p) == ["cdata.chemicals.loop23"]


def test_mat_several_loops_need_name(tmp_path):
    p = _isdb_mat(tmp_path / "many.mat", n_loops=3)
    msg = raises_one_line(r"holds 3 loops.*loop23.*loop24.*loop25", read_loop, p)
    assert "many.mat" in msg
    d = read_loop(p, name="loop24")
    np.testing.assert_allclose(d.op, OP + 1)
    assert d.name == "loop24"
    d = read_loop(p, name="cdata.chemicals.loop25")
    np.testing.assert_allclose(d.op, OP + 2)
    raises_one_line(r"no loop named 'loop99'.*available", read_loop, p, name="loop99")


def test_mat_flat_variables(tmp_path):
    sio = pytest.importorskip("scipy.io")
    p = tmp_path / "flat.mat"
    sio.savemat(str(p), {"OP": OP, "PV": PV, "Ts": 0.5, "SP": SP})
    d = read_loop(p)
    assert d.ts == 0.5
    np.testing.assert_allclose(d.sp, SP)


def test_mat_errors(tmp_path):
    sio = pytest.importorskip("scipy.io")
    p = tmp_path / "nothing.mat"
    sio.savemat(str(p), {"x": np.arange(3.0)})
    raises_one_line(r"no loop .* found in '.*nothing\.mat'", read_loop, p)
    g = tmp_path / "garbage.mat"
    g.write_bytes(bytes(range(256)) * 4)
    raises_one_line(r"garbage\.mat", read_loop, g)
    m = tmp_path / "nopv.mat"
    sio.savemat(str(m), {"s": {"OP": OP, "PVX": PV, "PV_": PV}})
    raises_one_line(r"no loop", read_loop, m)


# --------------------------------------------------------------- read_loop errors


def test_missing_file(tmp_path):
    p = tmp_path / "nope.csv"
    raises_one_line(r"file not found: '.*nope\.csv'", read_loop, p)


def test_folder_is_not_a_file(tmp_path):
    raises_one_line(r"is a folder", read_loop, tmp_path)


def test_empty_file(tmp_path):
    p = tmp_path / "empty.csv"
    p.write_text("")
    raises_one_line(r"'.*empty\.csv' is empty", read_loop, p)


def test_binary_garbage(tmp_path):
    p = tmp_path / "junk.csv"
    p.write_bytes(bytes(RNG.integers(0, 256, 4000, dtype=np.uint8)))
    raises_one_line(r"junk\.csv' is not a text CSV file", read_loop, p)


def test_header_only(tmp_path):
    p = tmp_path / "hdr.csv"
    p.write_text("t,OP,PV\n")
    raises_one_line(r"hdr\.csv' has a header but no data rows", read_loop, p)


def test_missing_column(tmp_path):
    p = write_csv(tmp_path / "x.csv", ["t", "OP"], [np.arange(N), OP])
    msg = raises_one_line(
        r"`PV` column missing in '.*x\.csv' \(found: t, OP\)", read_loop, p
    )
    assert msg.endswith("(found: t, OP)")
    p2 = write_csv(tmp_path / "y.csv", ["PV"], [PV])
    raises_one_line(r"`OP` column missing", read_loop, p2)


def test_ambiguous_columns(tmp_path):
    p = write_csv(tmp_path / "dup.csv", ["OP", "op", "PV"], [OP, OP, PV])
    raises_one_line(r"ambiguous columns", read_loop, p)


def test_non_numeric(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t,OP,PV\n0,1,2\n1,2,abc\n2,3,4\n")
    raises_one_line(
        r"non-numeric value 'abc' in column `PV` at line 3 of '.*bad\.csv'",
        read_loop,
        p,
    )


def test_short_row(tmp_path):
    p = tmp_path / "short.csv"
    p.write_text("t,OP,PV\n0,1,2\n1,2\n")
    raises_one_line(r"line 3 of '.*short\.csv' has 2 fields", read_loop, p)


def test_nan_and_inf(tmp_path):
    p = tmp_path / "nan.csv"
    p.write_text("OP,PV\n1,2\n2,nan\n3,\n4,inf\n")
    raises_one_line(
        r"nan\.csv: `PV` has 2 NaN and 1 inf values \(first at sample index 1",
        read_loop,
        p,
    )
    q = tmp_path / "nanop.csv"
    q.write_text("OP,PV\n1,2\n2,3\nNaN,4\n")
    raises_one_line(r"`OP` has 1 NaN value \(first at sample index 2", read_loop, q)


def test_sp_and_t_problems(tmp_path):
    p = tmp_path / "sp.csv"
    p.write_text("OP,PV,SP\n1,2,3\n2,3,\n")
    raises_one_line(r"`SP` has 1 NaN", read_loop, p)
    q = tmp_path / "t.csv"
    q.write_text("t,OP,PV\n5,1,2\n4,2,3\n3,3,4\n")
    raises_one_line(r"`t` is not increasing in '.*t\.csv'", read_loop, q)
    assert read_loop(q, ts=2.0).ts == 2.0  # explicit ts overrides a broken t


def test_bad_explicit_ts(tmp_path):
    p = write_csv(tmp_path / "x.csv", ["OP", "PV"], [OP, PV])
    raises_one_line(r"must be positive", read_loop, p, ts=0.0)
    raises_one_line(r"must be positive", read_loop, p, ts=float("nan"))


def test_unknown_extension(tmp_path):
    p = tmp_path / "loop.xlsx"
    p.write_text("OP,PV\n1,2\n")
    raises_one_line(r"unknown file type '\.xlsx'.*loop\.xlsx", read_loop, p)


def test_unsupported_source_type():
    raises_one_line(r"cannot read loop data from a int", read_loop, 42)


def test_mismatched_lengths_in_dict():
    raises_one_line(
        r"`OP` has 50 samples but `PV` has 49", read_loop, {"OP": OP, "PV": PV[:-1]}
    )


def test_constant_op_is_read_but_flagged_by_check_loop(tmp_path):
    p = write_csv(tmp_path / "flat.csv", ["OP", "PV"], [np.full(N, 50.0), PV])
    d = read_loop(p)  # read_loop checks structure only
    raises_one_line(
        r"`OP` is constant .*without valve movement", check_loop, d.op, d.pv
    )


# -------------------------------------------------------------------- check_loop


def test_check_loop_ok_returns_arrays():
    op, pv = check_loop(list(OP), PV, min_length=10)
    assert op.dtype == np.float64 and op.shape == (N,)


def test_check_loop_problems():
    msg = raises_one_line(
        r"^CHEM: `OP` has 1500 samples but `PV` has 1499$",
        check_loop,
        np.arange(1500.0),
        np.arange(1499.0),
        name="CHEM",
    )
    assert msg.startswith("CHEM")
    raises_one_line(
        r"`OP` is constant \(50 over all 50 samples\); "
        r"stiction cannot be identified without valve movement",
        check_loop,
        np.full(N, 50.0),
        PV,
    )
    # relative tolerance: tiny wiggle on a large mean still counts as constant
    raises_one_line(
        r"`OP` is constant", check_loop, 1e6 + 1e-6 * np.sin(np.arange(N)), PV
    )
    raises_one_line(r"`PV` is constant", check_loop, OP, np.zeros(N))
    raises_one_line(
        r"needs at least 100 samples for the chosen orders, got 50",
        check_loop,
        OP,
        PV,
        min_length=100,
    )
    raises_one_line(r"empty", check_loop, [], [])
    raises_one_line(r"`PV` has 1 inf value", check_loop, OP, np.r_[PV[:-1], np.inf])
    raises_one_line(
        r"`OP` has a non-numeric value 'x' at index 1",
        check_loop,
        [1.0, "x"],
        [1.0, 2.0],
    )
    raises_one_line(r"one-dimensional", check_loop, np.ones((3, 3)), np.ones((3, 3)))
    # small but real variation is fine
    check_loop(1e-6 * np.sin(np.arange(N)), PV)


def test_error_message_is_always_one_line():
    e = LoopDataError("first\nsecond\r\nthird\x00")
    assert str(e) == "first second third?"


# ------------------------------------------------------------------------- split


def test_split():
    d = LoopData(op=OP, pv=PV, sp=SP, t=np.arange(N) * 2.0, ts=2.0, name="s")
    est, val = d.split(0.0)
    assert est is d and val is d
    est, val = d.split(0.3)
    assert len(est) == 35 and len(val) == 15
    np.testing.assert_allclose(np.r_[est.op, val.op], OP)
    np.testing.assert_allclose(val.t, np.arange(35, N) * 2.0)
    assert val.sp.shape == (15,) and val.ts == 2.0 and val.name == "s"
    est, val = d.split(0.001)
    assert len(val) == 1
    for bad in (1.0, -0.1, float("nan")):
        raises_one_line(r"fraction", d.split, bad)


def test_loopdata_constructor_checks():
    raises_one_line(r"`SP` has 3", LoopData, op=OP, pv=PV, sp=np.ones(3))
    raises_one_line(r"sampling time must be positive", LoopData, op=OP, pv=PV, ts=-1.0)
    assert "n=50" in repr(LoopData(op=OP, pv=PV))


# ------------------------------------------------------------------- find_loop_files


def test_find_loop_files(tmp_path):
    for name in ("b.csv", "a.CSV", "c.mat", "notes.txt", ".hidden.csv"):
        (tmp_path / name).write_text("OP,PV\n1,2\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "z.csv").write_text("OP,PV\n1,2\n")
    extra = tmp_path / "notes.txt"
    files = find_loop_files([tmp_path, extra, tmp_path / "b.csv"])
    assert [f.name for f in files] == ["a.CSV", "b.csv", "c.mat", "notes.txt"]
    assert find_loop_files(str(tmp_path / "sub")) == [tmp_path / "sub" / "z.csv"]
    raises_one_line(
        r"file not found: '.*missing\.csv'", find_loop_files, [tmp_path / "missing.csv"]
    )
    (tmp_path / "empty").mkdir()
    raises_one_line(
        r"no \.csv or \.mat files in folder", find_loop_files, [tmp_path / "empty"]
    )
    assert find_loop_files([]) == []


# ------------------------------------------------------------------ nominal model


NOMINAL = {
    "Ts": 1.0,
    "process": {"b": [0.0, 0.2, 0.1], "a": [1.0, -1.2, 0.5], "delay": 3},
    "op_offset": 50.0,
    "pv_offset": 10.0,
    "valve": {"model": "linear"},
}


def _nominal(**changes):
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


def test_read_nominal_file_and_dict(tmp_path):
    p = tmp_path / "nominal.json"
    p.write_text(json.dumps(NOMINAL))
    m = read_nominal(p)
    assert isinstance(m, NominalModel)
    np.testing.assert_allclose(m.b, [0.0, 0.2, 0.1])
    np.testing.assert_allclose(m.a, [1.0, -1.2, 0.5])
    assert m.delay == 3 and m.op_offset == 50.0 and m.pv_offset == 10.0
    assert m.valve == "linear" and m.S is None and m.ts == 1.0
    assert read_nominal(m.to_dict()).to_dict() == m.to_dict()
    k = read_nominal(_nominal(valve={"model": "Kano", "S": 3.0, "J": 1.0}))
    assert k.valve == "kano" and k.S == 3.0 and k.J == 1.0
    # defaults for optional keys
    d = read_nominal({"Ts": 2, "process": {"b": [1.0], "a": [1.0]}})
    assert d.delay == 0 and d.op_offset == 0.0 and d.valve == "linear"
    assert read_nominal(_nominal(**{"process.delay": 2.0})).delay == 2


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"process.a": [1.0, -1.05]}, r"nominal model is unstable: pole at 1\.05"),
        ({"process.a": [1.0, -1.0]}, r"nominal model is unstable: pole at 1\b"),
        ({"process.a": [1.0, 0.0, 1.21]}, r"unstable: pole at .*j \(modulus 1\.1\)"),
        ({"process.a": [2.0, -1.0]}, r"process\.a\[0\] must be 1"),
        ({"process.a": []}, r"process\.a is empty"),
        ({"process.b": []}, r"process\.b is empty"),
        ({"process.b": None}, r"missing key 'process\.b'"),
        ({"process": None}, r"missing key 'process'"),
        ({"Ts": None}, r"missing key 'Ts'"),
        ({"Ts": -1}, r"Ts must be positive"),
        ({"process.delay": -1}, r"delay must be ≥ 0"),
        ({"process.delay": 1.5}, r"delay must be a whole number"),
        ({"process.delay": "2"}, r"delay must be a whole number"),
        ({"process.b": [1.0, "x"]}, r"process\.b\[1\] must be a number"),
        ({"valve": {"model": "magic"}}, r"unknown valve\.model 'magic'"),
        ({"valve": {"model": "kano", "S": 1.0}}, r"needs 'valve\.J'"),
        ({"valve": {"model": "choudhury", "S": 1.0, "J": -1.0}}, r"must be ≥ 0"),
        ({"op_offset": "fifty"}, r"op_offset must be a number"),
    ],
)
def test_read_nominal_errors(changes, match):
    raises_one_line(match, read_nominal, _nominal(**changes))


def test_read_nominal_file_errors(tmp_path):
    raises_one_line(
        r"file not found: '.*none\.json'", read_nominal, tmp_path / "none.json"
    )
    p = tmp_path / "bad.json"
    p.write_text('{"Ts": 1.0,\n "process": }')
    raises_one_line(r"'.*bad\.json' is not valid JSON \(.* line 2", read_nominal, p)
    q = tmp_path / "list.json"
    q.write_text("[1, 2]")
    raises_one_line(r"must hold a JSON object", read_nominal, q)
    u = tmp_path / "unstable.json"
    u.write_text(json.dumps(_nominal(**{"process.a": [1.0, -1.05]})))
    msg = raises_one_line(r"nominal model is unstable: pole at 1\.05", read_nominal, u)
    assert "unstable.json" in msg


def test_simulate_nominal_matches_lfilter():
    signal = pytest.importorskip("scipy.signal")
    m = read_nominal(NOMINAL)
    op = 50 + RNG.normal(0, 2, 300)
    y = simulate_nominal(m, op)
    u = np.r_[np.zeros(m.delay), op - m.op_offset][: op.size]
    expected = m.pv_offset + signal.lfilter(m.b, m.a, u)
    np.testing.assert_allclose(y, expected, rtol=1e-10, atol=1e-10)
    # FIR process, no delay
    f = read_nominal(
        {"Ts": 1, "process": {"b": [0.5, 0.25], "a": [1]}, "op_offset": 1.0}
    )
    np.testing.assert_allclose(simulate_nominal(f, [1.0, 3.0, 5.0]), [0.0, 1.0, 2.5])


def test_simulate_nominal_step_gain_and_valve_fn():
    m = read_nominal(NOMINAL)
    y = simulate_nominal(m, np.full(400, 51.0))  # +1 step at t=0
    gain = sum(m.b) / sum(m.a)
    assert y[-1] == pytest.approx(m.pv_offset + gain, rel=1e-6)
    assert np.all(y[: m.delay + 1] == m.pv_offset)  # b0 = 0 and delay 3
    y2 = simulate_nominal(m, np.full(400, 50.0), valve_fn=lambda u: u + 1.0)
    np.testing.assert_allclose(y2, y)


def test_simulate_nominal_stiction_valves_not_here():
    k = read_nominal(_nominal(valve={"model": "kano", "S": 3.0, "J": 1.0}))
    with pytest.raises(NotImplementedError, match="kano.*provided elsewhere"):
        simulate_nominal(k, OP)


# ----------------------------------------------------------------------- ISDB file


@pytest.mark.skipif(
    not (ISDB / "CHEM23.csv").exists(), reason="ISDB data not available"
)
def test_isdb_chem23():
    d = read_loop(ISDB / "CHEM23.csv")
    assert d.name == "CHEM23"
    assert d.ts == 10.0
    assert len(d) == 1500
    check_loop(d.op, d.pv, min_length=100, name=d.name)
