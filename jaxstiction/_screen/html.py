"""The screen's files: `summary.csv` and `report.html`.

`report.html` is one self-contained page: its style, a small inline script (sort
by a column, filter by verdict, cause and gate) and its histogram (inline SVG,
drawn here) are all in the file, so it opens offline in any browser from its
folder, with no server and nothing downloaded. It is laid out for a 1400-px-wide
window: a fixed-layout table at 100 % width whose long texts wrap and clip."""

from __future__ import annotations

import csv
import html
import math
import statistics
from collections import Counter
from pathlib import Path

from .._verdict.settings import VerdictSettings


VERDICT_NAMES = ("stiction", "no_stiction", "inconclusive")
INDICATORS = ("period_samples", "regularity", "oscillation_share", "periods", "horch", "shape_op", "shape_pv",
              "ngi", "nli", "stuck_pv", "stuck_dpv")
COLUMNS = ("rank", "name", "verdict", "stiction_probability", "gate", "reason", "status", "stiction_detected",
           "cause", "slip_identified", "band_percent", "model_wins", "crossval_median",
           *(f"indicator_{k}" for k in INDICATORS),
           "S", "J", "evidence", "evidence_estimation", "evidence_prediction", "evidence_prediction_estimation",
           "fitness", "fitness_kano", "fitness_linear", "oscillation", "oscillation_kano",
           "period_samples", "model", "samples", "Ts", "note", "file")


def verdict_of(r: dict) -> str:
    """The loop's verdict; an entry without one (an older screen's) is read from
    its `status` and `stiction_detected`."""
    v = r.get("verdict")
    if v in VERDICT_NAMES:
        return v
    if r.get("status") != "ok":
        return "inconclusive"
    return "stiction" if r.get("stiction_detected") else "no_stiction"


def crossval_median(r: dict) -> float | None:
    """The median of the loop's per-fold cross-validation gains (points), or `None`."""
    gains = [float(g) for g in r.get("crossval") or () if g is not None and math.isfinite(float(g))]
    return statistics.median(gains) if gains else None


def _value(r: dict, column: str):
    if column == "verdict":
        return verdict_of(r)
    if column == "crossval_median":
        return crossval_median(r)
    if column.startswith("indicator_"):
        return (r.get("indicators") or {}).get(column[len("indicator_"):])
    return r.get(column)


def _cell(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def write_summary_csv(loops: list[dict], path: Path) -> Path:
    """One row per loop, in rank order, with the columns of `COLUMNS` (the
    indicators flattened as `indicator_horch` and so on)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for i, r in enumerate(loops, 1):
            w.writerow([i if c == "rank" else _cell(_value(r, c)) for c in COLUMNS])
    return path


# --- report.html --------------------------------------------------------------------------------------

_COLOURS = {"stiction": "#c62828", "no_stiction": "#2e7d32", "inconclusive": "#b26a00"}
_LABELS = {"stiction": "stiction", "no_stiction": "no stiction", "inconclusive": "inconclusive"}

_STYLE = """
* { box-sizing: border-box; }
body { font: 13px/1.35 system-ui, -apple-system, "Segoe UI", sans-serif; margin: 12px 16px; color: #222; }
h1 { font-size: 20px; margin: 0 0 4px; }
h2 { font-size: 13px; margin: 0 0 6px; text-transform: uppercase; letter-spacing: .04em; color: #555; }
p.lead { margin: 0 0 10px; color: #444; }
.summary { display: flex; flex-wrap: wrap; align-items: flex-start; gap: 10px; margin-bottom: 8px; }
.card { border: 1px solid #ddd; border-radius: 6px; padding: 8px 10px; background: #fafafa; }
.card table { border-collapse: collapse; }
.card td { padding: 1px 6px 1px 0; border: 0; }
.card td.n { text-align: right; font-variant-numeric: tabular-nums; font-weight: 600; }
.big { display: flex; gap: 14px; }
.big div { text-align: center; }
.big b { display: block; font-size: 24px; line-height: 1.1; }
.controls { display: flex; flex-wrap: wrap; align-items: center; gap: 6px 16px; padding: 6px 0;
            border-top: 1px solid #ddd; margin-bottom: 4px; }
.controls label { white-space: nowrap; }
details { margin: 0 0 8px; color: #444; }
details dl { display: grid; grid-template-columns: max-content 1fr; gap: 2px 12px; margin: 6px 0; }
details dt { font-weight: 600; }
details dd { margin: 0; }
table.loops { width: 100%; table-layout: fixed; border-collapse: collapse; }
table.loops th, table.loops td { padding: 3px 4px; border-bottom: 1px solid #e3e3e3; text-align: left;
                                 vertical-align: top; overflow-wrap: anywhere; word-break: break-word; }
table.loops th { background: #f0f0f0; position: sticky; top: 0; cursor: pointer; user-select: none;
                 font-weight: 600; white-space: normal; }
table.loops th:hover { background: #e4e4e4; }
th.asc::after { content: " \\25B2"; font-size: 9px; }
th.desc::after { content: " \\25BC"; font-size: 9px; }
table.loops td.num, table.loops th.num { text-align: right; font-variant-numeric: tabular-nums; }
tr:hover td { background: #fbfbf2; }
.pill { display: inline-block; padding: 1px 6px; border-radius: 9px; color: #fff; font-weight: 600;
        font-size: 12px; white-space: nowrap; }
.v-stiction { background: #c62828; }
.v-no_stiction { background: #2e7d32; }
.v-inconclusive { background: #b26a00; }
tr.r-stiction td:first-child { box-shadow: inset 4px 0 #c62828; }
tr.r-no_stiction td:first-child { box-shadow: inset 4px 0 #2e7d32; }
tr.r-inconclusive td:first-child { box-shadow: inset 4px 0 #b26a00; }
.gate { font-weight: 600; color: #8a5200; }
.note { color: #555; }
.clip { display: -webkit-box; -webkit-box-orient: vertical; -webkit-line-clamp: 3; overflow: hidden;
        cursor: pointer; }
.clip.open { display: block; }
.sub { color: #777; font-size: 11px; }
td.pic img { width: 100%; max-width: 124px; height: auto; border: 1px solid #ccc; display: block; }
svg text { font: 10px system-ui, sans-serif; fill: #444; }
table.valves { border-collapse: collapse; margin: 4px 0 6px; }
table.valves th, table.valves td { padding: 2px 8px 2px 4px; border-bottom: 1px solid #e3e3e3; text-align: left; }
table.valves td.num, table.valves th.num { text-align: right; font-variant-numeric: tabular-nums; }
"""

# Sorting: a click on a heading sorts by that column (again: the other way; `#`
# restores the screen's rank); empty cells stay last. Filtering: verdict
# checkboxes, cause and gate selects and a name search. A click on a clipped text
# shows all of it.
_SCRIPT = """
(function () {
  var table = document.getElementById("loops"), body = table.tBodies[0];
  var heads = table.tHead.rows[0].cells;
  function key(row, i) { var c = row.cells[i]; return c.hasAttribute("data-v") ? c.getAttribute("data-v")
                                                                               : c.textContent.trim(); }
  function sortBy(i, th) {
    var num = th.getAttribute("data-sort") === "num";
    var dir = th.classList.contains("asc") ? -1 : 1;
    for (var k = 0; k < heads.length; k++) heads[k].classList.remove("asc", "desc");
    th.classList.add(dir > 0 ? "asc" : "desc");
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function (a, b) {
      var x = key(a, i), y = key(b, i);
      if (x === "" || y === "") return (x === "") - (y === "");
      if (num) { x = parseFloat(x); y = parseFloat(y); return dir * (x - y); }
      return dir * x.localeCompare(y, undefined, {numeric: true});
    });
    rows.forEach(function (r) { body.appendChild(r); });
  }
  for (var k = 0; k < heads.length; k++) {
    (function (i) { heads[i].addEventListener("click", function () { sortBy(i, heads[i]); }); })(k);
  }
  var boxes = document.querySelectorAll("input[name=verdict]");
  var cause = document.getElementById("f-cause"), gate = document.getElementById("f-gate");
  var query = document.getElementById("f-name"), shown = document.getElementById("shown");
  function filter() {
    var on = {};
    boxes.forEach(function (b) { on[b.value] = b.checked; });
    var q = query.value.trim().toLowerCase(), n = 0;
    Array.prototype.forEach.call(body.rows, function (r) {
      var ok = on[r.getAttribute("data-verdict")] &&
               (cause.value === "*" || r.getAttribute("data-cause") === cause.value) &&
               (gate.value === "*" || r.getAttribute("data-gate") === gate.value) &&
               (q === "" || r.getAttribute("data-name").toLowerCase().indexOf(q) >= 0);
      r.style.display = ok ? "" : "none";
      n += ok ? 1 : 0;
    });
    shown.textContent = n;
  }
  boxes.forEach(function (b) { b.addEventListener("change", filter); });
  [cause, gate].forEach(function (s) { s.addEventListener("change", filter); });
  query.addEventListener("input", filter);
  body.addEventListener("click", function (ev) {
    var c = ev.target.closest(".clip");
    if (c) c.classList.toggle("open");
  });
  filter();
})();
"""

# (heading, tooltip, sort kind, width in % of the table). The note column takes
# what is left; together they fit a 1400-px window.
_HEADS = (
    ("#", "the screen's rank", "num", 2.6),
    ("loop", "the loop's name (its file in the tooltip)", "text", 7.5),
    ("verdict", "stiction, no stiction, or inconclusive when the data cannot decide", "text", 7.0),
    ("P", "stiction probability (calibrated, 0-1)", "num", 4.2),
    ("cause", "what explains the loop's behaviour", "text", 7.5),
    ("band %", "the Kano fit's stick band S, in % of OP", "num", 4.4),
    ("slip", "the slip jump J is identified (else a deadband of that width fits as well)", "text", 3.4),
    ("horch", "Horch's cross-correlation indicator", "num", 4.3),
    ("shape OP", "shape of OP's cycle (triangular for a sticky valve)", "num", 4.3),
    ("regul.", "regularity of the oscillation", "num", 4.3),
    ("CV", "median held-out gain of the Kano valve over a linear one across the cross-validation folds "
     "(points)", "num", 4.3),
    ("evidence", "model evidence: held-out gain of the Kano valve over a linear valve, in simulation / in "
     "short-horizon prediction (points); bold when the model-based test calls it sticky", "num", 6.5),
    ("why inconclusive / note", "the gate's reason for an inconclusive loop, then what to know before "
     "trusting the fit; click a clipped text to see all of it", "text", None),
    ("picture", "the loop's picture: click to enlarge", "text", 9.5),
)


def _num(v, nd=2) -> str:
    if v is None or not math.isfinite(float(v)):
        return "–"
    v = float(v)
    return f"{v:.{nd}f}" if abs(v) < 1e4 else f"{v:.1e}"  # a run-away gain must not widen its column


def _data(v) -> str:
    return "" if v is None or not math.isfinite(float(v)) else f"{float(v):.6g}"


def _words(name) -> str:
    return "–" if name is None else str(name).replace("_", " ")


def _pill(verdict: str) -> str:
    return f'<span class="pill v-{verdict}">{_LABELS[verdict]}</span>'


def _row(rank: int, r: dict) -> str:
    e = html.escape
    verdict = verdict_of(r)
    p = r.get("stiction_probability")
    ind = r.get("indicators") or {}
    cause = r.get("cause")
    gate = r.get("gate") or ("ok" if r.get("status") == "ok" else "data_error")
    slip = r.get("slip_identified")
    ev, evp = r.get("evidence"), r.get("evidence_prediction")
    gains = [g for g in (ev, evp) if g is not None and math.isfinite(float(g))]
    ev_txt = "–" if not gains else f"{_num(ev, 1)} / {_num(evp, 1)}"
    if r.get("model_wins"):
        ev_txt = f"<b>{ev_txt}</b>"
    why = []
    if verdict == "inconclusive":
        reason = r.get("reason") or (r.get("status") if r.get("status") != "ok" else "")
        why.append(f'<span class="gate">{e(_words(gate))}</span>' + (f": {e(reason)}" if reason else ""))
    if r.get("note"):
        why.append(f'<span class="note">{e(r["note"])}</span>')
    why_html = f'<div class="clip" title="{e(" | ".join(_plain(w) for w in why))}">{"<br>".join(why)}</div>' \
        if why else ""
    pic = r.get("picture")
    thumb = (f'<a href="{e(pic)}" target="_blank" title="open the picture"><img src="{e(pic)}" loading="lazy" '
             f'alt="{e(r["name"])}"></a>') if pic else ""
    if r.get("whatif_picture"):  # `screen --whatif`: as is, repaired, compensated
        thumb += (f'<br><a href="{e(r["whatif_picture"])}" target="_blank" title="as is, repaired and compensated">'
                  "what a repair would buy</a>")
    bar = "" if p is None else (f' style="background: linear-gradient(to right, {_tint(verdict)} '
                                f'{100 * float(p):.0f}%, transparent {100 * float(p):.0f}%)"')
    cells = [
        f'<td class="num">{rank}</td>',
        f'<td title="{e(str(r.get("file") or ""))}">{e(r["name"])}</td>',
        f'<td data-v="{VERDICT_NAMES.index(verdict)}">{_pill(verdict)}</td>',
        f'<td class="num" data-v="{_data(p)}"{bar}>{_num(p)}</td>',
        f'<td>{e(_words(cause))}</td>',
        f'<td class="num" data-v="{_data(r.get("band_percent"))}">{_num(r.get("band_percent"), 1)}</td>',
        f'<td>{"–" if slip is None else ("yes" if slip else "no")}</td>',
        *(f'<td class="num" data-v="{_data(ind.get(k))}">{_num(ind.get(k))}</td>'
          for k in ("horch", "shape_op", "regularity")),
        f'<td class="num" data-v="{_data(crossval_median(r))}">{_num(crossval_median(r), 1)}</td>',
        f'<td class="num" data-v="{_data(max(gains) if gains else None)}">{ev_txt}</td>',
        f"<td>{why_html}</td>",
        f'<td class="pic">{thumb}</td>',
    ]
    return (f'<tr class="r-{verdict}" data-verdict="{verdict}" data-cause="{e(str(cause or ""))}" '
            f'data-gate="{e(gate)}" data-name="{e(r["name"])}">' + "".join(cells) + "</tr>")


def _plain(fragment: str) -> str:
    """The text of a small HTML fragment made here (tags dropped, entities kept)."""
    out, inside = [], False
    for ch in fragment:
        if ch in "<>":
            inside = ch == "<"
        elif not inside:
            out.append(ch)
    return "".join(out)


def _tint(verdict: str) -> str:
    return {"stiction": "#f6d3d0", "no_stiction": "#d5ebd6", "inconclusive": "#f5e3c4"}[verdict]


def histogram_svg(loops: list[dict], bins: int = 10, width: int = 340, height: int = 110) -> str:
    """An inline SVG histogram of the loops' stiction probability, each bar stacked
    by verdict, with the default decision threshold dashed."""
    counts = [Counter() for _ in range(bins)]
    for r in loops:
        p = r.get("stiction_probability")
        if p is not None and math.isfinite(float(p)):
            counts[min(int(float(p) * bins), bins - 1)][verdict_of(r)] += 1
    top = max([sum(c.values()) for c in counts] + [1])
    left, bottom, right, head = 26, 18, 6, 6
    w, h = width - left - right, height - bottom - head
    bw = w / bins
    parts = [f'<svg width="{width}" height="{height}" role="img" '
             f'aria-label="histogram of the stiction probability">']
    for k, c in enumerate(counts):
        y = head + h
        for v in VERDICT_NAMES:
            if c[v]:
                bh = h * c[v] / top
                y -= bh
                parts.append(f'<rect x="{left + k * bw + 1:.1f}" y="{y:.1f}" width="{bw - 2:.1f}" height="{bh:.1f}" '
                             f'fill="{_COLOURS[v]}"><title>{k / bins:.1f}-{(k + 1) / bins:.1f}: {c[v]} '
                             f'{_LABELS[v]}</title></rect>')
    x_t = left + w * VerdictSettings().threshold
    parts += [f'<line x1="{left}" y1="{head + h}" x2="{left + w}" y2="{head + h}" stroke="#888"/>',
              f'<line x1="{left}" y1="{head}" x2="{left}" y2="{head + h}" stroke="#888"/>',
              f'<line x1="{x_t:.1f}" y1="{head}" x2="{x_t:.1f}" y2="{head + h}" stroke="#333" '
              f'stroke-dasharray="3,3"><title>default threshold</title></line>',
              f'<text x="{left - 3}" y="{head + 8}" text-anchor="end">{top}</text>',
              f'<text x="{left - 3}" y="{head + h}" text-anchor="end">0</text>']
    for t in (0.0, 0.5, 1.0):
        parts.append(f'<text x="{left + w * t:.1f}" y="{height - 5}" text-anchor="middle">{t:g}</text>')
    parts.append("</svg>")
    return "".join(parts)


def _count_table(counter: Counter, label=_words) -> str:
    rows = "".join(f'<tr><td>{html.escape(label(k))}</td><td class="n">{n}</td></tr>'
                   for k, n in sorted(counter.items(), key=lambda kn: (-kn[1], str(kn[0]))))
    return f"<table>{rows}</table>"


def _summary(loops: list[dict]) -> str:
    verdicts = Counter(verdict_of(r) for r in loops)
    causes = Counter(r.get("cause") for r in loops)
    gates = Counter(r.get("gate") or ("ok" if r.get("status") == "ok" else "data_error")
                    for r in loops if verdict_of(r) == "inconclusive")
    no_p = sum(r.get("stiction_probability") is None for r in loops)
    big = "".join(f'<div><b style="color:{_COLOURS[v]}">{verdicts[v]}</b>{_LABELS[v]}</div>' for v in VERDICT_NAMES)
    return f"""<div class="summary">
<div class="card"><h2>Verdicts</h2><div class="big">{big}</div></div>
<div class="card"><h2>Stiction probability</h2>{histogram_svg(loops)}
<div class="sub">loops per tenth, coloured by verdict; dashed: the default<br>threshold{
        f"; {no_p} loop{'s' * (no_p != 1)} without a probability" if no_p else ""}</div></div>
<div class="card"><h2>Causes</h2>{_count_table(causes, lambda k: "not fitted" if k is None else _words(k))}</div>
<div class="card"><h2>Why inconclusive</h2>{_count_table(gates) if gates else "none"}</div>
</div>"""


def _valves(valves: list[dict] | None) -> str:
    """`screen --by-valve`: one row per valve, its verdict first (`valve_verdicts`)."""
    if valves is None:
        return ""
    e = html.escape
    rows = "".join(
        f'<tr class="r-{v["verdict"]}"><td>{e(str(v["tag"]))}</td><td>{_pill(v["verdict"])}</td>'
        f'<td class="num">{_num(v["stiction_probability"])}</td><td class="num">{v["sticky"]}</td>'
        f'<td class="num">{v["not_sticky"]}</td><td class="num">{v["inconclusive"]}</td>'
        f'<td>{e(", ".join(map(str, v["recordings"])))}</td><td class="note">{e(v["reason"] or "")}</td></tr>'
        for v in valves)
    sticky = sum(v["verdict"] == "stiction" for v in valves)
    return f"""<details class="valves" open><summary><b>Per valve</b>: {len(valves)} valve{
        "s" * (len(valves) != 1)}, {sticky} sticky (the verdict of most of a valve's judged recordings;
p the mean of their stiction probabilities)</summary>
<table class="valves"><thead><tr><th>valve</th><th>verdict</th><th class="num">p</th>
<th class="num">sticky</th><th class="num">not sticky</th><th class="num">inconclusive</th>
<th>recordings</th><th>why inconclusive</th></tr></thead>
<tbody>{rows}</tbody></table></details>"""


def _controls(loops: list[dict]) -> str:
    e = html.escape
    boxes = "".join(f'<label><input type="checkbox" name="verdict" value="{v}" checked> {_pill(v)}</label>'
                    for v in VERDICT_NAMES)
    causes = sorted({str(r.get("cause") or "") for r in loops})
    cause_opts = "".join(f'<option value="{e(c)}">{e(_words(c) if c else "not fitted")}</option>' for c in causes)
    gates = sorted({r.get("gate") or ("ok" if r.get("status") == "ok" else "data_error") for r in loops})
    gate_opts = "".join(f'<option value="{e(g)}">{e(_words(g))}</option>' for g in gates)
    return (f'<div class="controls">{boxes}'
            f'<label>cause <select id="f-cause"><option value="*">all</option>{cause_opts}</select></label>'
            f'<label>gate <select id="f-gate"><option value="*">all</option>{gate_opts}</select></label>'
            f'<label>loop <input id="f-name" type="search" placeholder="name contains" size="14"></label>'
            f'<span><b id="shown">{len(loops)}</b> of {len(loops)} loops shown</span></div>')


def _legend() -> str:
    items = "".join(f"<dt>{html.escape(h)}</dt><dd>{html.escape(tip)}</dd>" for h, tip, _, _ in _HEADS)
    return f"<details><summary>What the columns mean</summary><dl>{items}</dl></details>"


def write_html(report, path: Path) -> Path:
    """`report.html`: a summary (counts by verdict, cause and gate, and a histogram
    of the stiction probability), then the loops in rank order in a table that
    sorts by a click on a heading and filters by verdict, cause, gate and name,
    with each loop's verdict, probability, cause, band, indicators, evidence, note
    and a thumbnail linking to its picture. Self-contained: no server, no downloads."""
    loops = list(report.loops)
    e = html.escape
    cols = "".join(f'<col style="width:{w}%">' if w else "<col>" for _, _, _, w in _HEADS)
    heads = "".join(f'<th title="{e(tip)}" data-sort="{kind}"{" class=num" if kind == "num" else ""}>{e(h)}</th>'
                    for h, tip, kind, _ in _HEADS)
    rows = "\n".join(_row(i, r) for i, r in enumerate(loops, 1))
    n_err = sum(r.get("status") != "ok" for r in loops)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>jaxstiction screen</title>
<style>{_STYLE}</style></head><body>
<h1>Stiction screen</h1>
<p class="lead">{len(loops)} loops, in the screen's rank order{
        f"; {n_err} could not be read or fitted (inconclusive, with the reason)" if n_err else ""}.
Click a column heading to sort (again to reverse; <b>#</b> restores the rank), hover over a heading for its
meaning, and click a picture to enlarge it.</p>
{_summary(loops)}
{_valves(report.valves)}
{_legend()}
{_controls(loops)}
<table class="loops" id="loops"><colgroup>{cols}</colgroup>
<thead><tr>{heads}</tr></thead>
<tbody>
{rows}
</tbody></table>
<script>{_SCRIPT}</script>
</body></html>
"""
    path.write_text(page, encoding="utf-8")
    return path
