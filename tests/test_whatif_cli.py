"""The what-if on the command line and in the screen: `fit --whatif`, `screen
--whatif` (the maintenance ranking and its criticality table), `compensate` and
`trend` (the valve trend's grouping and its flags). The end-to-end runs fit whole
loops and are slow; the ranking, the tables and the flags are pure and fast."""

import json

import numpy as np
import pytest
from helpers import run

from jaxstiction import LoopDataError
from jaxstiction._io.tags import default_tag, read_tags
from jaxstiction._screen.whatif import rank_by_benefit, read_criticality
from jaxstiction._whatif.trend import band_changes


CONTRACT = ("error_std_as_is", "error_std_repaired", "error_std_compensated", "error_std_repaired_interval",
            "benefit", "travel_as_is", "travel_repaired", "travel_compensated", "reversals_as_is",
            "reversals_repaired", "reversals_compensated", "compensator", "controller", "note")


def _sticky_csv(path, seed=0, n=900, S=4.0, J=1.5, sp_column=True):
    """A sticky loop (the concealed-case process, a Kano valve, the paper's PI) with
    setpoint steps and noise, written as `t,OP,PV,SP`."""
    import jax
    import jax.numpy as jnp

    from jaxstiction import Controller, Kano
    from jaxstiction.internal import closed_loop, nominal_model

    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(seed)
    sp = np.zeros(n)
    for t0 in (n // 4, n // 2, 3 * n // 4):
        sp[t0:] += rng.uniform(-6, 6)
    v = np.zeros(n)
    e = rng.standard_normal(n) * 0.3
    for t in range(1, n):
        v[t] = 0.9 * v[t - 1] + e[t]
    plant = nominal_model(chain=(Kano(S, J),))
    ctrl = Controller(kp=jnp.asarray(0.3), ki=jnp.asarray(0.01))
    r = closed_loop(plant, ctrl, jnp.asarray(sp), jnp.asarray(v), plant.rest_state(jnp.full((4,), 50.0)), 50.0)
    op, pv = np.asarray(r.op), np.asarray(r.pv)
    cols = ["t", "OP", "PV"] + (["SP"] if sp_column else [])
    rows = [",".join(cols)] + [",".join(f"{x:.6g}" for x in ((i, op[i], pv[i], sp[i]) if sp_column else
                                                            (i, op[i], pv[i]))) for i in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


# ---------------------------------------------------------------------------- ranking


def _entry(name, verdict, benefit_pct, file=None):
    w = None if benefit_pct is False else {"benefit_percent_of_range": benefit_pct, "note": ""}
    return {"name": name, "verdict": verdict, "file": file, **({"whatif": w} if w is not None else {})}


def test_rank_by_benefit_orders_sticky_loops_and_keeps_the_others_in_place():
    loops = [_entry("A", "stiction", 1.0), _entry("x", "no_stiction", False), _entry("B", "stiction", 5.0),
             _entry("C", "stiction", None), _entry("D", "stiction", 3.0), _entry("y", "inconclusive", False)]
    out = rank_by_benefit(loops)
    assert [e["name"] for e in out] == ["B", "x", "D", "A", "C", "y"]
    assert [e["whatif"]["priority"] for e in out if "whatif" in e] == [5.0, 3.0, 1.0, None]
    # a criticality weight multiplies the benefit; a loop the table leaves out weighs 1 and says so
    out = rank_by_benefit(loops, {"A": 10.0, "B": 0.5, "D": 1.0})
    assert [e["name"] for e in out if "whatif" in e] == ["A", "D", "B", "C"]  # 10, 3, 2.5, none
    assert out[0]["whatif"]["priority"] == 10.0 and out[0]["whatif"]["criticality"] == 10.0
    assert "does not name this loop" in next(e for e in out if e["name"] == "C")["whatif"]["note"]


def test_criticality_by_tag_of_a_file_or_of_a_mat_loop():
    loops = [_entry("plant:FIC1", "stiction", 1.0), _entry("L46", "stiction", 2.0, file="/d/L46.csv")]
    out = rank_by_benefit(loops, {"FIC1": 3.0, "L46": 1.0})
    assert [e["name"] for e in out] == ["plant:FIC1", "L46"]


def test_read_criticality(tmp_path):
    f = tmp_path / "crit.csv"
    f.write_text("Tag,Weight\nFIC1,2\nLIC2,0.5\n")
    assert read_criticality(f) == {"FIC1": 2.0, "LIC2": 0.5}
    for text, match in (("tag,w\nA,1\n", "`weight` column"), ("tag,weight\nA,-1\n", ">= 0"),
                        ("tag,weight\nA,high\n", "line 2"), ("tag,weight\n", "no rows")):
        f.write_text(text)
        with pytest.raises(LoopDataError, match=match) as info:
            read_criticality(f)
        assert "\n" not in str(info.value)
    with pytest.raises(LoopDataError, match="cannot read"):
        read_criticality(tmp_path / "missing.csv")


# ---------------------------------------------------------------------------- trend


def _row(lo, hi):
    return {"S_interval": None if lo is None else [lo, hi]}


@pytest.mark.parametrize("intervals, change, flags", [
    ([(1.0, 1.2), (1.1, 1.3), (1.5, 1.7)], "grows", [False, False, True]),
    ([(1.0, 1.2), (1.5, 1.7), (1.1, 1.3)], "steady", [False, True, False]),
    ([(2.0, 2.2), (1.0, 1.2)], "shrinks", [False, False]),
    ([(1.0, 1.2), (None, None)], "single", [False, False]),
    ([(None, None), (1.0, 1.2), (1.3, 1.4)], "grows", [False, False, True]),
    ([(1.0, 1.2), (1.5, 1.7), (0.1, 0.2)], "inconsistent", [False, True, False]),
])
def test_band_changes(intervals, change, flags):
    rows = [_row(*iv) for iv in intervals]
    got, note = band_changes(rows)
    assert got == change
    assert [r["grows"] for r in rows] == flags
    assert ("in between" in note) == (change == "steady" and any(flags))
    if change in ("shrinks", "inconsistent"):
        assert rows[-1]["shrinks"]
    if change == "inconsistent":
        assert "understate" in note


def test_tags_of_recordings(tmp_path):
    assert default_tag("FIC101_0301") == "FIC101" and default_tag("2411LIC30501-b") == "2411LIC30501"
    assert default_tag("L46") == "L46"
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps({"loops": {"L46": {"valve": "2111FIC46005"}, "L47": {"valve": "2111FIC46005"}}}))
    assert read_tags(labels) == {"L46": "2111FIC46005", "L47": "2111FIC46005"}
    plain = tmp_path / "tags.json"
    plain.write_text(json.dumps({"a": "V1"}))
    assert read_tags(plain) == {"a": "V1"}
    table = tmp_path / "tags.csv"
    table.write_text("name,tag\na,V1\nb,V1\n")
    assert read_tags(table) == {"a": "V1", "b": "V1"}
    table.write_text("file,x\na,V1\n")
    with pytest.raises(LoopDataError, match="`name` and `tag`"):
        read_tags(table)


# ---------------------------------------------------------------------------- command line


def _one_line_error(res, match):
    assert res.returncode == 2, res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and match in errors[0], res.stderr
    assert "Traceback" not in res.stderr


def test_bad_whatif_options_are_one_line_errors(tmp_path):
    f = tmp_path / "loop.csv"
    f.write_text("t,OP,PV\n0,1,2\n")
    _one_line_error(run("fit", str(f), "--whatif", "--pi", "0.5"), "--pi")
    _one_line_error(run("compensate", str(f), "--pi", "a,b"), "--pi")
    _one_line_error(run("compensate", str(f), "--travel-weight", "-1"), "travel_weight")
    _one_line_error(run("screen", str(f), "--criticality", str(f)), "needs --whatif")
    crit = tmp_path / "crit.csv"
    crit.write_text("tag,weight\nA,-2\n")
    _one_line_error(run("screen", str(f), "--whatif", "--criticality", str(crit)), ">= 0")


@pytest.mark.slow
def test_fit_whatif_json_contract(tmp_path):
    f = _sticky_csv(tmp_path / "FIC1_01.csv")
    res = run("fit", str(f), "--whatif", "--json", "--out", str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    w = json.loads(res.stdout)["whatif"]
    assert set(CONTRACT) <= set(w)
    assert w["controller"]["source"] == "identified from SP, OP and PV" and w["controller"]["fit"] > 0.95
    assert w["benefit"] == pytest.approx(w["error_std_as_is"] - w["error_std_repaired"], abs=2e-4)
    # the intervals are null, with the note saying why, when fewer than two drawn
    # models fit the record (the polished valve sits at a sharp optimum of S)
    if w["error_std_repaired_interval"] is None:
        assert "no intervals" in w["note"]
    else:
        lo, hi = w["error_std_repaired_interval"]
        assert lo <= w["error_std_repaired"] <= hi
    assert w["benefit"] > 0 and w["compensator"]["kind"] in ("knocker", "constant reinforcement")
    assert (tmp_path / "out" / "whatif.png").stat().st_size > 0
    # a given tuning replaces the identified one
    res = run("fit", str(f), "--whatif", "--json", "--pi", "0.31,2")
    c = json.loads(res.stdout)["whatif"]["controller"]
    assert c["source"] == "given" and c["gain"] == pytest.approx(0.31)


@pytest.mark.slow
def test_compensate_json_and_out(tmp_path):
    f = _sticky_csv(tmp_path / "FIC1_01.csv", seed=1)
    res = run("compensate", str(f), "--json", "--out", str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    k = out["compensator"]
    assert k["amplitude"] > 0
    if k["kind"] == "knocker":
        assert k["period_samples"] >= 2 * k["width_samples"]
    else:
        assert k["kind"] == "constant reinforcement" and k["period_samples"] == k["width_samples"] == 1
    assert out["error_std_compensated"] <= out["error_std_as_is"]
    assert out["extra_travel"] == pytest.approx(out["travel_compensated"] - out["travel_as_is"], abs=0.02)
    assert (tmp_path / "out" / "compensate.png").stat().st_size > 0


@pytest.mark.slow
def test_screen_whatif_ranks_sticky_loops(tmp_path):
    d = tmp_path / "loops"
    d.mkdir()
    _sticky_csv(d / "FIC1.csv", seed=2, S=6.0, J=2.0)
    _sticky_csv(d / "FIC2.csv", seed=3, S=2.0, J=0.5, sp_column=False)
    crit = tmp_path / "crit.csv"
    crit.write_text("tag,weight\nFIC1,1\nFIC2,2\n")
    # a low threshold: these short simulated loops sit near the verdict's default one
    # (probabilities 0.2-0.6), and this test is about the ranking of the loops called sticky
    res = run("screen", str(d), "--whatif", "--criticality", str(crit), "--threshold", "0.1", "--json", "--out",
              str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    loops = json.loads(res.stdout)["loops"]
    sticky = [e for e in loops if e["verdict"] == "stiction"]
    assert sticky, [(e["name"], e["verdict"]) for e in loops]
    for e in sticky:
        assert set(CONTRACT) <= set(e["whatif"]), e["whatif"]
        assert e["whatif"]["criticality"] == {"FIC1": 1.0, "FIC2": 2.0}[e["name"]]
        assert (tmp_path / "out" / "whatif" / f"{e['name']}.png").is_file()
    prio = [e["whatif"]["priority"] for e in sticky if e["whatif"]["priority"] is not None]
    assert prio == sorted(prio, reverse=True)
    for e in loops:
        if e["verdict"] != "stiction":
            assert "whatif" not in e
    assert "what a repair would buy" in (tmp_path / "out" / "report.html").read_text()


@pytest.mark.slow
def test_trend_groups_recordings_of_a_tag(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    _sticky_csv(d / "FIC1_1.csv", seed=4, S=2.0, J=0.5)
    _sticky_csv(d / "FIC1_2.csv", seed=5, S=7.0, J=2.0)
    res = run("trend", str(d), "--json", "--out", str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    v = json.loads(res.stdout)["valves"]
    assert [x["tag"] for x in v] == ["FIC1"] and [r["name"] for r in v[0]["recordings"]] == ["FIC1_1", "FIC1_2"]
    assert v[0]["change"] == "grows" and v[0]["recordings"][1]["grows"]
    assert (tmp_path / "out" / "trend" / "FIC1.png").stat().st_size > 0


def test_a_parked_compensated_valve_is_flagged():
    from jaxstiction._whatif.report import _parked

    assert _parked(2.76, 37.3)  # CHEM23's knocker: the valve sits at its balance point
    assert not _parked(30.0, 37.3) and not _parked(80.0, 37.3) and not _parked(0.0, 0.0)
