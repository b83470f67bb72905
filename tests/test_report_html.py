"""The screen's `report.html` and `summary.csv`, from hand-made entries (no fits)."""

import csv
import html
import re
from html.parser import HTMLParser

import pytest

import jaxstiction as js
from jaxstiction._screen.html import COLUMNS, crossval_median, histogram_svg, write_html, write_summary_csv


def _ok(name, verdict, p, cause, **kw):
    entry = {
        "name": name, "file": f"/plant/{name}.csv", "status": "ok", "converged": True, "note": "",
        "samples": 1500, "Ts": 1.0, "verdict": verdict, "stiction_detected": verdict == "stiction",
        "stiction_probability": p, "gate": "ok", "reason": "", "cause": cause, "band_seen": verdict == "stiction",
        "slip_identified": verdict == "stiction", "model_wins": verdict == "stiction",
        "indicators": {"period_samples": 60.0, "regularity": 3.1, "oscillation_share": 0.7, "periods": 25.0,
                       "horch": 0.42, "shape_op": 0.8, "shape_pv": 0.3, "ngi": 0.01, "nli": 0.2,
                       "stuck_pv": 0.1, "stuck_dpv": 0.05},
        "crossval": [4.0, 1.0, 2.0, None], "features": {"horch": 0.42}, "band_percent": 3.5, "fitness": 71.2,
        "S": 3.5, "J": 1.0, "evidence": 6.0, "evidence_prediction": 2.5, "model": "kano", "delay": 2,
        "picture": f"loops/{name}.png",
    }
    entry.update(kw)
    return entry


@pytest.fixture
def report():
    loops = [
        _ok("FC101", "stiction", 0.93, "stiction", note="the fit hit its iteration limit " * 8),
        _ok("TC7 <hot>", "no_stiction", 0.12, "external_oscillation", slip_identified=False, evidence=None,
            evidence_prediction=-1.0, crossval=[]),
        _ok("LC3", "inconclusive", 0.55, "none", gate="setpoint_moves",
            reason="the setpoint moves: its variance is 80 % of PV's", picture=None),
        {"name": "PC9", "file": "/plant/PC9.csv", "status": "`OP` has 3 samples", "samples": 3, "Ts": 1.0,
         "verdict": "inconclusive", "stiction_detected": False, "stiction_probability": None,
         "gate": "data_error", "reason": "`OP` has 3 samples", "cause": None, "band_percent": None,
         "fitness": None},
    ]
    return js.ScreenReport(loops=loops)


class _Page(HTMLParser):
    """The parts of the page the tests look at: each body row's attributes and
    cells' text, the form controls, the scripts and every referenced resource."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.rows, self.inputs, self.selects, self.scripts, self.refs, self.heads = [], [], [], [], [], []
        self._in, self._stack = None, []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self._stack.append(tag)
        for k in ("href", "src", "action", "data"):
            if a.get(k):
                self.refs.append(a[k])
        if tag == "tr" and "data-verdict" in a:
            self.rows.append({"attrs": a, "cells": []})
        elif tag == "td" and self.rows and "tbody" in self._stack:
            self.rows[-1]["cells"].append("")
            self._in = "td"
        elif tag == "th":
            self.heads.append(a)
        elif tag == "input":
            self.inputs.append(a)
        elif tag == "select":
            self.selects.append(a)
        elif tag == "script":
            self.scripts.append("")
            self._in = "script"

    def handle_endtag(self, tag):
        while self._stack and self._stack.pop() != tag:
            pass
        if tag in ("td", "script"):
            self._in = None

    def handle_data(self, data):
        if self._in == "td":
            self.rows[-1]["cells"][-1] += data
        elif self._in == "script":
            self.scripts[-1] += data


@pytest.fixture
def page(report, tmp_path):
    text = write_html(report, tmp_path / "report.html").read_text(encoding="utf-8")
    parser = _Page()
    parser.feed(text)
    parser.close()
    return text, parser


def test_one_row_per_loop_in_rank_order(report, page):
    _, p = page
    assert [r["attrs"]["data-name"] for r in p.rows] == [r["name"] for r in report.loops]
    assert [r["attrs"]["data-verdict"] for r in p.rows] == ["stiction", "no_stiction", "inconclusive",
                                                            "inconclusive"]
    assert [r["cells"][0] for r in p.rows] == ["1", "2", "3", "4"]
    assert all(len(r["cells"]) == len(p.heads) for r in p.rows)


def test_rows_show_what_the_engineer_needs(page):
    _, p = page
    sticky, clean, gated, error = (r["cells"] for r in p.rows)
    assert sticky[2] == "stiction" and sticky[3] == "0.93" and sticky[4] == "stiction"
    assert sticky[5] == "3.5" and sticky[6] == "yes"
    assert sticky[7:11] == ["0.42", "0.80", "3.10", "2.0"]  # horch, shape OP, regularity, CV median
    assert sticky[11] == "6.0 / 2.5"
    assert "iteration limit" in sticky[12]
    assert clean[4] == "external oscillation" and clean[6] == "no" and clean[10] == "–"
    assert clean[11] == "– / -1.0"
    assert "setpoint moves" in gated[12] and "80 % of PV's" in gated[12]
    assert error[3] == "–" and error[4] == "–" and "3 samples" in error[12]
    assert "data error" in error[12]


def test_names_are_escaped(page):
    text, _ = page
    assert "TC7 &lt;hot&gt;" in text and "TC7 <hot>" not in text


def test_filters_and_sort_script_present(page):
    text, p = page
    assert sorted(i["value"] for i in p.inputs if i.get("name") == "verdict") == sorted(
        ["stiction", "no_stiction", "inconclusive"])
    assert {s.get("id") for s in p.selects} >= {"f-cause", "f-gate"}
    causes = re.search(r'<select id="f-cause">(.*?)</select>', text).group(1)
    assert all(f'value="{c}"' in causes for c in ("stiction", "external_oscillation", "none", ""))
    assert len(p.scripts) == 1
    script = p.scripts[0]
    assert "addEventListener" in script and "sort(" in script and "f-cause" in script
    assert all(h.get("data-sort") in ("num", "text") for h in p.heads)


def test_summary_counts_and_histogram(page):
    text, _ = page
    assert "<svg" in text and text.count("<rect") >= 3  # three loops have a probability
    summary = text[text.index('<div class="summary">'):text.index("<details>")]
    assert ">2</b>inconclusive" in summary and ">1</b>stiction" in summary and ">1</b>no stiction" in summary
    assert "setpoint moves" in summary and "data error" in summary and "not fitted" in summary
    assert "1 loop without a probability" in summary


def test_works_offline(page):
    text, p = page
    assert "http://" not in text and "https://" not in text
    assert all(not re.match(r"^[a-z]+:", ref) or ref.startswith("#") for ref in p.refs), p.refs
    assert "loops/FC101.png" in p.refs
    assert "<link" not in text and "@import" not in text and "src=\"/" not in text


def test_fits_the_window(page):
    text, _ = page
    assert "table-layout: fixed" in text and "width: 100%" in text and "overflow-wrap: anywhere" in text
    widths = [float(w) for w in re.findall(r'<col style="width:([0-9.]+)%">', text)]
    assert sum(widths) < 90  # the note column keeps the rest


def test_summary_csv_has_the_new_columns(report, tmp_path):
    write_summary_csv(report.loops, tmp_path / "summary.csv")
    with open(tmp_path / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(COLUMNS)
    for c in ("verdict", "stiction_probability", "gate", "reason", "crossval_median", "indicator_horch",
              "indicator_shape_op", "indicator_regularity", "indicator_stuck_dpv"):
        assert c in COLUMNS
    assert [r["name"] for r in rows] == [r["name"] for r in report.loops]
    assert [r["verdict"] for r in rows] == ["stiction", "no_stiction", "inconclusive", "inconclusive"]
    assert rows[0]["stiction_probability"] == "0.93" and rows[0]["indicator_horch"] == "0.42"
    assert rows[0]["crossval_median"] == "2"
    assert rows[2]["gate"] == "setpoint_moves" and "setpoint moves" in rows[2]["reason"]
    assert rows[3]["gate"] == "data_error" and rows[3]["indicator_horch"] == "" and rows[3]["rank"] == "4"


def test_crossval_median_and_empty_histogram():
    assert crossval_median({"crossval": [3.0, None, 1.0, float("nan"), 2.0]}) == 2.0
    assert crossval_median({}) is None
    svg = histogram_svg([{"stiction_probability": None, "status": "x"}])
    assert svg.startswith("<svg") and "<rect" not in svg


def test_older_entries_without_a_verdict(tmp_path):
    """An entry from before the verdict (no `verdict`, `indicators`, `crossval`)
    still makes a page and a CSV."""
    old = [{"name": "A", "file": None, "status": "ok", "stiction_detected": True, "cause": "stiction",
            "band_percent": 2.0, "evidence": 3.0, "note": "n"},
           {"name": "B", "file": None, "status": "unreadable", "stiction_detected": False}]
    text = write_html(js.ScreenReport(loops=old), tmp_path / "r.html").read_text()
    assert 'data-verdict="stiction"' in text and 'data-verdict="inconclusive"' in text
    assert html.escape("unreadable") in text
    write_summary_csv(old, tmp_path / "s.csv")
    with open(tmp_path / "s.csv", newline="") as f:
        assert [r["verdict"] for r in csv.DictReader(f)] == ["stiction", "inconclusive"]
