"""The screen's files: `summary.csv` and a static `report.html` (no server, no
scripts, no downloads: it opens in any browser from the folder it is in)."""

from __future__ import annotations

import csv
import html
from pathlib import Path


COLUMNS = ("rank", "name", "status", "stiction_detected", "cause", "slip_identified", "band_percent", "S", "J",
           "evidence", "evidence_estimation", "evidence_prediction", "evidence_prediction_estimation", "fitness",
           "fitness_kano", "fitness_linear", "oscillation", "oscillation_kano",
           "period_samples", "model", "samples", "Ts", "note", "file")


def _cell(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def write_summary_csv(loops: list[dict], path: Path) -> Path:
    """One row per loop, in rank order, with the columns of `COLUMNS`."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for i, r in enumerate(loops, 1):
            w.writerow([i if c == "rank" else _cell(r.get(c)) for c in COLUMNS])
    return path


_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; }
th, td { padding: 4px 10px; border-bottom: 1px solid #ddd; text-align: left; vertical-align: middle; }
th { background: #f3f3f3; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.sticky td.verdict { color: #b00; font-weight: bold; }
tr.error td { color: #777; }
img { width: 260px; border: 1px solid #ccc; }
"""


def _fmt(v, nd=2):
    return "–" if v is None else f"{v:.{nd}f}"


def write_html(report, path: Path) -> Path:
    """`report.html`: the loops ranked, with verdict, cause, band, evidence and a
    thumbnail linking to each loop's picture."""
    c = report.counts
    rows = []
    for i, r in enumerate(report.loops, 1):
        e = html.escape
        ok = r["status"] == "ok"
        cls = "sticky" if r["stiction_detected"] else ("" if ok else "error")
        pic = r.get("picture")
        thumb = f'<a href="{e(pic)}"><img src="{e(pic)}" alt="{e(r["name"])}"></a>' if pic else ""
        note = f'<br><small>{e(r["note"])}</small>' if r.get("note") else ""
        verdict = ("no stiction" if not r["stiction_detected"] else
                   "stiction" if r.get("slip_identified") else "stiction (no slip seen)") if ok else "error"
        rows.append(
            f'<tr class="{cls}"><td class="num">{i}</td><td>{e(r["name"])}</td>'
            f'<td class="verdict">{e(verdict)}</td><td>{e(str(r.get("cause") or ""))}</td>'
            f'<td class="num">{_fmt(r.get("band_percent"))}</td><td class="num">{_fmt(r.get("evidence"))}</td>'
            f'<td class="num">{_fmt(r.get("fitness"))}</td>'
            f'<td>{"ok" if ok else e(r["status"])}{note}</td><td>{thumb}</td></tr>'
        )
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>jaxstiction screen</title>
<style>{_STYLE}</style></head><body>
<h1>Stiction screen</h1>
<p>{c['loops']} loops: {c['ok']} ok, {c['errors']} errors, <b>{c['sticky']} sticky</b>.
Ranked by stiction evidence (held-out simulation fitness gained by a Kano stiction
valve over a linear valve, in points, with a slow trend removed from both) and band.
<i>cause</i> names what explains a loop that is not sticky. "No slip seen": the valve
has a band but its slip jump is not identified, so a deadband (backlash) of that width fits as well. Notes under a
loop's status say what to know before trusting its fit.</p>
<table><thead><tr><th>#</th><th>loop</th><th>verdict</th><th>cause</th><th>band (% OP)</th>
<th>evidence (points)</th><th>fitness (%)</th><th>status</th><th>picture</th></tr></thead>
<tbody>
{chr(10).join(rows)}
</tbody></table></body></html>
"""
    path.write_text(page, encoding="utf-8")
    return path
