"""Tests for loop data input (`_io/`, `_checks`) and the `Loop` record
(`_loop`); the nominal-model file is tested in `test_nominal.py`."""

import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jaxstiction as js
from jaxstiction import (
    check_loop,
    find_loop_files,
    list_mat_loops,
    Loop,
    loop_name,
    LoopDataError,
    make_loop,
    read_loop,
    stack,
    unstack,
)


try:
    from tests.helpers import raises_one_line
except ImportError:  # pytest with tests/ on sys.path
    from helpers import raises_one_line



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


def assert_plain_loop(d, n):
    """`d` is an unpadded `Loop` of `n` samples: mask all ones, scalar ts."""
    assert isinstance(d, Loop)
    assert d.op.shape == d.pv.shape == d.mask.shape == (n,)
    assert d.ts.shape == ()
    np.testing.assert_array_equal(d.mask, np.ones(n))
    assert d.length == n


# ------------------------------------------------------------------ CSV round trips


def test_csv_with_t(tmp_path):
    t = np.arange(N) * 2.5
    p = write_csv(tmp_path / "loop1.csv", ["t", "OP", "PV"], [t, OP, PV])
    d = read_loop(p)
    assert_plain_loop(d, N)
    assert float(d.ts) == pytest.approx(2.5)
    # float64 because the tests enable x64 (conftest)
    assert d.op.dtype == jnp.float64 and d.pv.dtype == jnp.float64
    np.testing.assert_allclose(d.op, OP, rtol=1e-9)
    np.testing.assert_allclose(d.pv, PV, rtol=1e-9)
    assert loop_name(p) == "loop1"


def test_csv_without_t_defaults_ts_1_and_str_path(tmp_path):
    p = write_csv(tmp_path / "x.csv", ["OP", "PV"], [OP, PV])
    d = read_loop(str(p))
    assert_plain_loop(d, N)
    assert float(d.ts) == 1.0
    d2 = read_loop(p, ts=0.2, name="ignored for csv")
    assert float(d2.ts) == 0.2
    np.testing.assert_array_equal(d2.op, d.op)


def test_loop_name():
    assert loop_name("data/CHEM23.csv") == "CHEM23"
    assert loop_name(Path("x/loop.v2.mat")) == "loop.v2"
    assert loop_name({"OP": OP, "PV": PV}) == "loop"
    assert js.loop_name is loop_name


def test_csv_tagged_historian_columns(tmp_path):
    """A historian export names columns by tag (`FIC101.OP`): with no plain `OP`/`PV`
    the one tag holding both is read; a file with several tags holds several loops
    (`list_loops`), `name` picks one (any case), and without it the error lists them."""
    p = write_csv(tmp_path / "one.csv", ["Date Time", "FIC101.OP", "FIC101.PV", "FIC101.SP", "note"],
                  [np.arange(N) * 2.0, OP, PV, SP, np.zeros(N)])
    d = read_loop(p)
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.pv, PV)
    assert float(d.ts) == 2.0 and js.list_loops(p) == ["FIC101"]
    p = write_csv(tmp_path / "two.csv", ["t", "FIC101_PV", "FIC101_OP", "LIC 7 OP", "LIC 7 PV", "TI9/PV"],
                  [np.arange(N), PV, OP, OP + 1, PV + 1, PV])
    assert js.list_loops(p) == ["FIC101", "LIC 7"]  # TI9 has no OP: not a loop
    np.testing.assert_allclose(read_loop(p, name="lic 7").op, OP + 1)
    np.testing.assert_allclose(read_loop(p, name="FIC101").pv, PV)
    raises_one_line(r"2 loops in .*two.csv.*FIC101, LIC 7.*name", read_loop, p)
    raises_one_line(r"no loop named 'X' in .*FIC101, LIC 7", read_loop, p, name="X")
    # plain OP and PV columns win over tagged ones; the file is then one loop
    p = write_csv(tmp_path / "plain.csv", ["OP", "PV", "A.OP", "A.PV"], [OP, PV, OP + 1, PV + 1])
    assert js.list_loops(p) == []
    np.testing.assert_allclose(read_loop(p).op, OP)
    raises_one_line(r"ambiguous columns 'A.OP' and 'A_OP'.*of 'A'", read_loop,
                    write_csv(tmp_path / "dup.csv", ["A.OP", "A_OP", "A.PV"], [OP, OP, PV]))
    raises_one_line(r"`OP` column missing.*found: B.PV", read_loop,
                    write_csv(tmp_path / "nop.csv", ["B.PV", "C"], [PV, PV]))
    # the same in a mapping: `name` picks the tag
    np.testing.assert_allclose(read_loop({"X.OP": OP, "X.PV": PV, "Y.OP": OP + 1, "Y.PV": PV}, name="y").op, OP + 1)


def test_csv_with_sp_odd_header_case_and_extra_columns(tmp_path):
    p = write_csv(
        tmp_path / "odd.csv",
        [" Time ", "tag", " op", "Pv ", "s P"],
        [np.arange(N) * 10.0, np.zeros(N), OP, PV, SP],
    )
    d = read_loop(p)  # SP is read and checked, but not part of the Loop
    assert_plain_loop(d, N)
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.pv, PV)
    assert float(d.ts) == 10.0


def test_csv_decimal_comma_with_semicolons_or_tabs(tmp_path):
    """European exports: decimal commas beside semicolon or tab separators read as
    numbers; with comma separators a comma is never a decimal mark."""
    for sep, name in ((";", "semi.csv"), ("\t", "tab.tsv")):
        p = write_csv(tmp_path / name, ["t", "OP", "PV"], [np.arange(N) * 0.5, OP, PV], sep=sep)
        p.write_text(p.read_text().replace(".", ","))
        d = read_loop(p)
        np.testing.assert_allclose(d.op, OP, rtol=1e-9)
        np.testing.assert_allclose(d.pv, PV, rtol=1e-9)
        assert float(d.ts) == 0.5
    p = tmp_path / "both.csv"
    p.write_text("OP;PV\n1.5;2,5\n1,000.5;3\n")  # a thousands separator is not guessed at
    raises_one_line(r"non-numeric value '1,000.5' in column `OP` at line 3", read_loop, p)


def test_csv_iso_timestamps(tmp_path):
    """A `t`/`time`/`timestamp` column of ISO 8601 date-times gives the sampling time
    (time zones honoured); a stamp that is neither a number nor a date-time, or a mix
    of zone-aware and naive stamps, is a one-line error naming the line."""
    stamps = [f"2024-03-01 23:59:{50 + 2 * i:02d}" if 50 + 2 * i < 60 else
              f"2024-03-02 00:{(2 * i - 10) // 60:02d}:{(2 * i - 10) % 60:02d}" for i in range(N)]
    p = write_csv(tmp_path / "stamps.csv", ["Timestamp", "OP", "PV"], [stamps, OP, PV], fmt="{}")
    d = read_loop(p)
    assert float(d.ts) == 2.0
    np.testing.assert_allclose(d.op, OP)
    # ISO stamps with offsets: the same instants written in two zones
    zoned = ["2024-03-01T12:00:00Z", "2024-03-01T13:00:05+01:00", "2024-03-01T12:00:10+00:00"]
    p = write_csv(tmp_path / "zoned.csv", ["time", "OP", "PV"], [zoned, OP[:3], PV[:3]], fmt="{}")
    assert float(read_loop(p).ts) == 5.0
    bad = list(stamps)
    bad[4] = "yesterday"
    p = write_csv(tmp_path / "bad.csv", ["t", "OP", "PV"], [bad, OP, PV], fmt="{}")
    raises_one_line(r"`t` value 'yesterday' at line 6 of .*bad.csv.*ISO 8601", read_loop, p)
    p = write_csv(tmp_path / "mixed.csv", ["t", "OP", "PV"], [[zoned[0], "2024-03-01T12:00:05"], OP[:2], PV[:2]],
                  fmt="{}")
    raises_one_line(r"mixes date-times with and without a time zone", read_loop, p)


def test_datetime_time_columns_in_frames_and_mappings():
    pd = pytest.importorskip("pandas")
    stamps = pd.date_range("2024-03-31 01:59:00", periods=N, freq="3s", tz="Europe/Berlin")  # across a DST change
    assert float(read_loop(pd.DataFrame({"time": stamps, "OP": OP, "PV": PV})).ts) == 3.0
    spans = pd.to_timedelta(np.arange(N) * 4.0, unit="s")
    assert float(read_loop(pd.DataFrame({"t": spans, "OP": OP, "PV": PV})).ts) == 4.0
    t = np.datetime64("2024-01-01T00:00") + np.arange(N) * np.timedelta64(250, "ms")
    assert float(read_loop({"t": t, "OP": OP, "PV": PV}).ts) == 0.25


def test_csv_semicolon_bom_and_blank_lines(tmp_path):
    p = tmp_path / "semi.csv"
    body = "OP;PV\n\n1;2\n2;3\n\n3;5\n"
    p.write_bytes(b"\xef\xbb\xbf" + body.encode())
    d = read_loop(p)
    np.testing.assert_allclose(d.op, [1, 2, 3])
    np.testing.assert_allclose(d.pv, [2, 3, 5])


def test_ts_precedence(tmp_path):
    p = write_csv(tmp_path / "a.csv", ["t", "OP", "PV"], [np.arange(N) * 4.0, OP, PV])
    assert float(read_loop(p).ts) == 4.0  # from t
    assert float(read_loop(p, ts=7.0).ts) == 7.0  # explicit wins
    m = {"OP": OP, "PV": PV, "Ts": 3.0}
    assert float(read_loop(m).ts) == 3.0  # file Ts
    assert float(read_loop({**m, "t": np.arange(N) * 5.0}).ts) == 5.0  # t beats Ts
    assert float(read_loop(m, ts=2.0).ts) == 2.0  # explicit beats Ts
    assert float(read_loop({"OP": OP, "PV": PV}).ts) == 1.0  # default
    # t recorded as decimals: the step is rounded to 12 significant digits
    assert float(read_loop({"OP": OP, "PV": PV, "t": np.arange(N) * 0.2}).ts) == 0.2


def test_uneven_t_warns_and_takes_the_median_step(tmp_path):
    """A gap, a repeated or a reversed stamp in `t`: one `LoopDataWarning` (one line,
    naming the file, the count and the first uneven step), the samples taken as
    equally spaced at the median step. Jitter within half a step, or an explicit
    `ts`, says nothing."""
    t = np.arange(N) * 2.0
    gap = t.copy()
    gap[20:] += 6.0  # three samples missing before sample 20
    p = write_csv(tmp_path / "gap.csv", ["t", "OP", "PV"], [gap, OP, PV])
    with pytest.warns(js.LoopDataWarning) as caught:
        d = read_loop(p)
    assert float(d.ts) == 2.0 and d.length == N
    (w,) = caught
    msg = str(w.message)
    assert "\n" not in msg and "'" + str(p) + "'" in msg and "not evenly spaced" in msg
    assert "1 of 49 time steps" in msg and "from 2 to 8 s" in msg and "sample 20" in msg
    assert w.filename == __file__  # points at the caller of read_loop
    repeated = t.copy()
    repeated[10] = repeated[9]
    with pytest.warns(js.LoopDataWarning, match="2 of 49 time steps"):  # 0 s, then 4 s
        read_loop({"OP": OP, "PV": PV, "t": repeated})
    jitter = t + np.random.default_rng(1).uniform(-0.45, 0.45, N)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert float(read_loop({"OP": OP, "PV": PV, "t": jitter}).ts) == pytest.approx(2.0, abs=0.3)
        assert float(read_loop(p, ts=2.0).ts) == 2.0


# ---------------------------------------------------------------- DataFrame / dict


def test_dataframe():
    pd = pytest.importorskip("pandas")
    df = pd.DataFrame({"OP ": OP, "pv": PV, "Sp": SP})
    d = read_loop(df, ts=0.5, name="df")
    assert_plain_loop(d, N)
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.pv, PV)
    assert float(d.ts) == 0.5
    df2 = pd.DataFrame({"t": np.arange(N) * 2.0, "OP": OP, "PV": PV})
    assert float(read_loop(df2).ts) == 2.0


def test_dataframe_datetime_index():
    pd = pytest.importorskip("pandas")
    idx = pd.date_range("2024-01-01", periods=N, freq="5s")
    d = read_loop(pd.DataFrame({"OP": OP, "PV": PV}, index=idx))
    assert float(d.ts) == 5.0
    tidx = pd.to_timedelta(np.arange(N) * 3.0, unit="s")
    assert float(read_loop(pd.DataFrame({"OP": OP, "PV": PV}, index=tidx)).ts) == 3.0


def test_dataframe_bad_values():
    pd = pytest.importorskip("pandas")
    pv = list(PV.astype(object))
    pv[7] = "oops"
    df = pd.DataFrame({"OP": OP, "PV": pv})
    msg = raises_one_line(r"`PV`.*non-numeric.*'oops'.*index 7", read_loop, df)
    assert "loop" in msg
    # `name` labels the messages for a DataFrame or a mapping
    msg = raises_one_line(r"`PV`.*non-numeric", read_loop, df, name="FIC101")
    assert "FIC101" in msg
    raises_one_line(r"`PV` column missing", read_loop, pd.DataFrame({"OP": OP}))


def test_dict_and_lists():
    d = read_loop({"op": list(OP), "PV": tuple(PV)}, name="d")
    assert_plain_loop(d, N)
    np.testing.assert_allclose(d.op, OP)
    # column vectors are accepted
    d2 = read_loop({"OP": OP[:, None], "PV": PV[None, :]})
    assert_plain_loop(d2, N)


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
    assert_plain_loop(d, N)
    assert float(d.ts) == 10.0
    np.testing.assert_allclose(d.op, OP)
    np.testing.assert_allclose(d.pv, PV)
    assert float(read_loop(p, ts=1.0).ts) == 1.0
    assert list_mat_loops(p) == ["cdata.chemicals.loop23"]
    assert js.list_mat_loops is list_mat_loops


def test_mat_several_loops_need_name(tmp_path):
    p = _isdb_mat(tmp_path / "many.mat", n_loops=3)
    msg = raises_one_line(r"holds 3 loops.*loop23.*loop24.*loop25", read_loop, p)
    assert "many.mat" in msg
    d = read_loop(p, name="loop24")
    np.testing.assert_allclose(d.op, OP + 1)
    d = read_loop(p, name="cdata.chemicals.loop25")
    np.testing.assert_allclose(d.op, OP + 2)
    raises_one_line(r"no loop named 'loop99'.*available", read_loop, p, name="loop99")
    assert list_mat_loops(p) == [f"cdata.chemicals.loop{i}" for i in (23, 24, 25)]


def test_mat_flat_variables(tmp_path):
    sio = pytest.importorskip("scipy.io")
    p = tmp_path / "flat.mat"
    sio.savemat(str(p), {"OP": OP, "PV": PV, "Ts": 0.5, "SP": SP})
    d = read_loop(p)
    assert_plain_loop(d, N)
    assert float(d.ts) == 0.5
    np.testing.assert_allclose(d.pv, PV)
    assert list_mat_loops(p) == [""]


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
    raises_one_line(r"file not found: '.*none\.mat'", list_mat_loops, tmp_path / "none.mat")


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
    assert float(read_loop(q, ts=2.0).ts) == 2.0  # explicit ts overrides a broken t
    r = tmp_path / "tlen.csv"
    r.write_text("OP,PV,t\n1,2,0\n2,3,\n")
    raises_one_line(r"tlen\.csv: `t` has 1 NaN", read_loop, r)
    raises_one_line(
        r"`OP` has 50 samples but `SP` has 49", read_loop, {"OP": OP, "PV": PV, "SP": SP[:-1]}
    )


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
    assert_plain_loop(d, N)
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
        r"needs at least 100 samples for the chosen orders and delays, got 50",
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


# ----------------------------------------------------------- Loop, stack, unstack


def _loops(lengths=(50, 80, 65), ts=(1.0, 2.0, 0.5)):
    rng = np.random.default_rng(3)
    return [make_loop(rng.normal(50, 5, n), rng.normal(10, 1, n), t) for n, t in zip(lengths, ts)]


def test_make_loop():
    d = make_loop(list(OP), PV, ts=2.0)
    assert_plain_loop(d, N)
    assert float(d.ts) == 2.0
    np.testing.assert_array_equal(d.op, OP)
    assert float(make_loop(OP, PV).ts) == 1.0
    with pytest.raises(ValueError, match=r"one length, got shapes \(50,\) and \(49,\)"):
        make_loop(OP, PV[:-1])
    with pytest.raises(ValueError, match="1-D"):
        make_loop(np.ones((3, 3)), np.ones((3, 3)))


def test_stack_pads_and_masks():
    loops = _loops()
    batch = js.stack(loops)
    assert isinstance(batch, Loop)
    assert batch.op.shape == batch.pv.shape == batch.mask.shape == (3, 80)
    assert batch.ts.shape == (3,)
    np.testing.assert_array_equal(batch.mask.sum(axis=1), [50, 80, 65])
    np.testing.assert_array_equal(batch.ts, [1.0, 2.0, 0.5])
    for i, lp in enumerate(loops):
        n = lp.op.shape[0]
        np.testing.assert_array_equal(batch.op[i, :n], lp.op)
        np.testing.assert_array_equal(batch.pv[i, :n], lp.pv)
        np.testing.assert_array_equal(batch.mask[i, :n], 1.0)
        np.testing.assert_array_equal(batch.mask[i, n:], 0.0)
        # padding repeats the last real value
        np.testing.assert_array_equal(batch.op[i, n:], lp.op[-1])
        np.testing.assert_array_equal(batch.pv[i, n:], lp.pv[-1])
    # a longer length pads every loop
    assert stack(loops, length=100).op.shape == (3, 100)
    with pytest.raises(ValueError, match="cannot pad"):
        stack(loops, length=60)


def test_unstack_round_trips():
    loops = _loops()
    back = js.unstack(js.stack(loops))
    assert len(back) == 3
    for a, b in zip(loops, back):
        assert isinstance(b, Loop)
        for field in ("op", "pv", "mask", "ts"):
            x, y = np.asarray(getattr(a, field)), np.asarray(getattr(b, field))
            assert x.shape == y.shape and x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
    assert [b.length for b in back] == [50, 80, 65]
    assert unstack(stack(loops[:1]))[0].op.shape == (50,)


def test_decimate_takes_block_means():
    """Against a loop over blocks: the means of `k` samples, `ts` times `k`, a ragged
    tail dropped; on a stacked batch a block reaching into padding is padding."""
    loops = _loops()  # 50, 80 and 65 samples
    for lp in loops:
        d = js.decimate(lp, 3)
        n = lp.op.shape[0] // 3
        ref_op = [float(np.mean(np.asarray(lp.op)[3 * i:3 * i + 3])) for i in range(n)]
        ref_pv = [float(np.mean(np.asarray(lp.pv)[3 * i:3 * i + 3])) for i in range(n)]
        np.testing.assert_allclose(d.op, ref_op, rtol=1e-12)
        np.testing.assert_allclose(d.pv, ref_pv, rtol=1e-12)
        assert d.mask.shape == (n,) and float(d.mask.min()) == 1.0 and float(d.ts) == 3 * float(lp.ts)
    batch = js.decimate(js.stack(loops), 3)
    assert batch.op.shape == (3, 26)
    np.testing.assert_array_equal(batch.mask.sum(axis=1), [16, 26, 21])  # 50 // 3, 80 // 3, 65 // 3
    np.testing.assert_array_equal(batch.ts, [3.0, 6.0, 1.5])
    for i, lp in enumerate(loops):
        n = lp.op.shape[0] // 3
        np.testing.assert_allclose(batch.op[i, :n], js.decimate(lp, 3).op, rtol=1e-12)
    assert js.decimate(loops[0], 1) is loops[0]
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(ValueError, match="decimation factor must be a positive integer"):
            js.decimate(loops[0], bad)


def test_windows_cut_the_record_into_equal_windows():
    """Against a slow reference: the fewest windows of at most `length` samples,
    their lengths within one sample of each other, consecutive and covering every
    sample, each a slice of the record (the setpoint too); a record no longer than
    `length` is one window; a bad length is refused."""
    from jaxstiction.internal import windows

    rng = np.random.default_rng(5)
    for n, length in ((1000, 300), (1000, 250), (7201, 2400), (999, 1000), (10, 1)):
        lp = make_loop(rng.normal(50, 5, n), rng.normal(10, 1, n), 2.0, sp=rng.normal(10, 1, n))
        parts = windows(lp, length)
        k = -(-n // length)
        assert len(parts) == k
        assert [a for a, _, _ in parts][0] == 0 and parts[-1][1] == n
        assert all(b == a2 for (_, b, _), (a2, _, _) in zip(parts[:-1], parts[1:]))
        sizes = [b - a for a, b, _ in parts]
        assert max(sizes) <= length and max(sizes) - min(sizes) <= 1
        for a, b, part in parts:
            np.testing.assert_array_equal(part.op, np.asarray(lp.op)[a:b])
            np.testing.assert_array_equal(part.pv, np.asarray(lp.pv)[a:b])
            np.testing.assert_array_equal(part.sp, np.asarray(lp.sp)[a:b])
            assert part.mask.shape == (b - a,) and float(part.ts) == 2.0
    assert windows(_loops()[0], 60)[0][2] is not None and len(windows(_loops()[0], 60)) == 1
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(ValueError, match="window length must be a positive integer"):
            windows(_loops()[0], bad)


def test_stack_empty():
    with pytest.raises(ValueError, match="empty"):
        js.stack([])


def test_read_loops_stack(tmp_path):
    a = write_csv(tmp_path / "a.csv", ["OP", "PV"], [OP, PV])
    b = {"OP": OP[:30], "PV": PV[:30], "Ts": 2.0}
    batch = stack([read_loop(a), read_loop(b)])
    assert batch.op.shape == (2, N)
    np.testing.assert_array_equal(batch.mask.sum(axis=1), [N, 30])


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
    # recursive: subfolders too (hidden ones skipped), sorted by path
    (tmp_path / ".git").mkdir()
    (tmp_path / ".git" / "x.csv").write_text("OP,PV\n1,2\n")
    (tmp_path / "sub" / "deeper").mkdir()
    (tmp_path / "sub" / "deeper" / "y.mat").write_text("")
    files = find_loop_files(tmp_path, recursive=True)
    assert [f.relative_to(tmp_path).as_posix() for f in files] == ["a.CSV", "b.csv", "c.mat", "sub/deeper/y.mat",
                                                                   "sub/z.csv"]
    assert find_loop_files(tmp_path) == files[:3]


# ----------------------------------------------------------------------- ISDB file


def test_isdb_chem23(isdb):
    p = isdb / "CHEM23.csv"
    d = read_loop(p)
    assert_plain_loop(d, 1500)
    assert loop_name(p) == "CHEM23"
    assert float(d.ts) == 10.0
    check_loop(d.op, d.pv, min_length=100, name=loop_name(p))
