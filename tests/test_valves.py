"""The screen read per valve (`screen --by-valve`): recordings grouped by tag, one
verdict per valve. Pure Python on screen entries, and the command line on files
that need no fit."""

import json

import pytest
from helpers import run

import jaxstiction as js
from jaxstiction._io.tags import tag_of
from jaxstiction._screen.html import write_html
from jaxstiction._screen.valves import valve_verdicts, valves_text


def _entry(name, verdict, p=None, file=None, status="ok"):
    return {"name": name, "verdict": verdict, "stiction_probability": p, "status": status,
            "stiction_detected": verdict == "stiction", "file": file or f"/data/{name.split('@')[0]}.csv"}


def _by_tag(valves):
    return {v["tag"]: v for v in valves}


def test_a_valve_takes_the_verdict_of_most_of_its_judged_recordings():
    loops = [
        _entry("FIC1_a", "stiction", 0.9), _entry("FIC1_b", "stiction", 0.7), _entry("FIC1_c", "no_stiction", 0.2),
        _entry("FIC2_a", "no_stiction", 0.1), _entry("FIC2_b", "inconclusive", 0.8),  # not judged: p left out
        _entry("FIC3_a", "stiction", 0.6), _entry("FIC3_b", "no_stiction", 0.3),
        _entry("FIC4_a", "inconclusive", None), _entry("FIC4_b", "x", None, status="unreadable: no PV column"),
        _entry("FIC5_a", "stiction", 0.55), _entry("FIC5_b", "inconclusive", 0.1),
    ]
    valves = valve_verdicts(loops)
    got = _by_tag(valves)
    assert set(got) == {"FIC1", "FIC2", "FIC3", "FIC4", "FIC5"}
    assert got["FIC1"]["verdict"] == "stiction" and (got["FIC1"]["sticky"], got["FIC1"]["not_sticky"]) == (2, 1)
    assert got["FIC1"]["stiction_probability"] == pytest.approx((0.9 + 0.7 + 0.2) / 3)
    assert got["FIC2"]["verdict"] == "no_stiction" and got["FIC2"]["inconclusive"] == 1
    assert got["FIC2"]["stiction_probability"] == pytest.approx(0.1)
    assert got["FIC3"]["verdict"] == "inconclusive" and "split evenly (1 sticky, 1 not)" in got["FIC3"]["reason"]
    # a loop that could not be read counts as inconclusive
    assert got["FIC4"]["verdict"] == "inconclusive" and got["FIC4"]["inconclusive"] == 2
    assert got["FIC4"]["stiction_probability"] is None and "could be judged" in got["FIC4"]["reason"]
    # one judged recording decides, the inconclusive one does not weigh
    assert got["FIC5"]["verdict"] == "stiction" and got["FIC5"]["reason"] is None
    assert got["FIC1"]["recordings"] == ["FIC1_a", "FIC1_b", "FIC1_c"]
    # sticky valves first by falling probability, then the inconclusive, then the healthy
    assert [v["tag"] for v in valves] == ["FIC1", "FIC5", "FIC3", "FIC4", "FIC2"]
    text = "\n".join(valves_text(valves))
    assert all(t in text for t in got)


def test_valves_follow_a_mapping_then_the_file_then_the_name(tmp_path):
    tagged = tmp_path / "day1.csv"
    tagged.write_text("OP,PV,tag\n1,2,LIC7\n2,3,LIC7\n")
    loops = [
        _entry("L46", "stiction", 0.8), _entry("L47", "stiction", 0.9),  # a mapping by name
        _entry("x", "no_stiction", 0.1, file=str(tmp_path / "L48.csv")),  # a mapping by the file's stem
        _entry("day1", "stiction", 0.7, file=str(tagged)),  # the file's tag column
        _entry("PIC9@0-3000", "stiction", 0.6), _entry("PIC9@3000-6000", "no_stiction", 0.2),  # windows
        _entry("PIC9@3000-6000x", "no_stiction", 0.2),  # not a window: a name of its own
    ]
    mapping = {"L46": "2111FIC46005", "L47": "2111FIC46005", "L48": "2111FIC46005"}
    got = _by_tag(valve_verdicts(loops, mapping))
    assert got["2111FIC46005"]["recordings"] == ["L46", "L47", "x"]
    assert got["2111FIC46005"]["verdict"] == "stiction"
    assert got["LIC7"]["recordings"] == ["day1"]
    assert got["PIC9"]["recordings"] == ["PIC9@0-3000", "PIC9@3000-6000"]
    assert got["PIC9"]["verdict"] == "inconclusive"
    assert got["PIC9@3000"]["recordings"] == ["PIC9@3000-6000x"]  # not a window: the name up to its last -
    assert tag_of("FIC101_0301", tmp_path / "FIC101_0301.csv") == "FIC101"


def test_the_report_shows_the_valves(tmp_path):
    loops = [_entry("FIC1_a", "stiction", 0.9), _entry("FIC1_b", "no_stiction", 0.2),
             _entry("FIC2_a", "inconclusive", None)]
    rep = js.ScreenReport(loops=loops, valves=valve_verdicts(loops))
    assert rep.to_json()["valves"] == rep.valves
    assert rep.summary_line().endswith("3 loops: 3 ok, 0 errors, 1 sticky; 2 valves: 0 sticky")
    assert "valves" not in js.ScreenReport(loops=loops).to_json()
    page = write_html(rep, tmp_path / "report.html").read_text()
    assert "Per valve" in page and "split evenly" in page and "none of its recordings" in page
    assert "Per valve" not in write_html(js.ScreenReport(loops=loops), tmp_path / "plain.html").read_text()


def test_cli_screen_by_valve(tmp_path):
    """Files that cannot be screened still count, per valve, as inconclusive; a bad
    tags file stops the command before any loop is read, in one line."""
    folder = tmp_path / "loops"
    folder.mkdir()
    (folder / "FIC1_a.csv").write_text("OP,XX\n1,2\n")
    (folder / "FIC1_b.csv").write_text("")
    (folder / "L9.csv").write_text("t,OP,PV\n")
    tags = tmp_path / "tags.json"
    tags.write_text(json.dumps({"L9": "LIC9"}))
    res = run("screen", str(folder), "--json", "--tags", str(tags))
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    got = _by_tag(out["valves"])
    assert set(got) == {"FIC1", "LIC9"} and got["FIC1"]["inconclusive"] == 2
    assert all(v["verdict"] == "inconclusive" for v in out["valves"])
    assert "3 loops: 0 ok, 3 errors, 0 sticky; 2 valves: 0 sticky" in res.stderr
    res = run("screen", str(folder), "--by-valve")
    assert res.returncode == 0, res.stderr
    assert "per valve" in res.stdout and "FIC1" in res.stdout and "L9" in res.stdout
    bad = tmp_path / "tags.csv"
    bad.write_text("loop,valve\nL9,LIC9\n")
    res = run("screen", str(folder), "--tags", str(bad))
    assert res.returncode != 0 and "tags.csv: the tags file needs `name` and `tag` columns" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
