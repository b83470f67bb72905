"""The screen read per valve: several recordings of one valve (segments of different
days, or a long record's windows) give one verdict for the valve.

A plant engineer repairs valves, not recordings. `screen --by-valve` groups the
screened recordings by tag (`--tags FILE`, else a `tag` column, else the file name
up to its last `_` or `-`; a window `NAME@START-STOP` of a long record goes with
`NAME`) and gives each valve:

- `verdict`: `stiction` when most of its judged recordings (those whose verdict is
  `stiction` or `no_stiction`) are sticky, `no_stiction` when most are not, and
  `inconclusive` when none could be judged or the judged ones split evenly (the
  `reason` says which);
- `stiction_probability`: the mean of the judged recordings' probabilities;
- the counts of its recordings by verdict, and their names in the screen's order.

Host-side Python on the screen's entries; no JAX.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from .._io.tags import natural_key, tag_of
from .._loop import recording_of
from .html import verdict_of


def valve_verdicts(loops: list[dict], mapping: Mapping[str, str] | None = None) -> list[dict]:
    """One entry per valve tag of the screen entries `loops` (see the module notes),
    sorted by verdict (`stiction` first), then by falling probability, then by tag.

    Each: `tag`, `verdict`, `stiction_probability` (or `None`), `recordings` (their
    names), `sticky`, `not_sticky`, `inconclusive` (counts; a loop that could not be
    read or fitted is inconclusive) and `reason` (`None` unless inconclusive)."""
    groups: dict[str, list[dict]] = {}
    for r in loops:
        name = str(r.get("name", ""))
        rec = recording_of(name)
        path = Path(r.get("file") or rec)
        groups.setdefault(tag_of(rec, path, mapping), []).append(r)
    out = []
    for tag, rows in groups.items():
        verdicts = [verdict_of(r) for r in rows]
        sticky, healthy = verdicts.count("stiction"), verdicts.count("no_stiction")
        probs = [float(r["stiction_probability"]) for r, v in zip(rows, verdicts)
                 if v != "inconclusive" and r.get("stiction_probability") is not None]
        if sticky > healthy:
            verdict, reason = "stiction", None
        elif healthy > sticky:
            verdict, reason = "no_stiction", None
        elif sticky:
            verdict, reason = "inconclusive", f"its judged recordings split evenly ({sticky} sticky, {healthy} not)"
        else:
            verdict, reason = "inconclusive", "none of its recordings could be judged"
        out.append({"tag": tag, "verdict": verdict,
                    "stiction_probability": sum(probs) / len(probs) if probs else None,
                    "recordings": [r.get("name") for r in rows], "sticky": sticky, "not_sticky": healthy,
                    "inconclusive": len(rows) - sticky - healthy, "reason": reason})
    order = {"stiction": 0, "inconclusive": 1, "no_stiction": 2}
    return sorted(out, key=lambda v: (order[v["verdict"]], -(v["stiction_probability"] or 0.0),
                                      natural_key(v["tag"])))


def valves_text(valves: list[dict]) -> list[str]:
    """The per-valve table of `screen --by-valve`'s text output."""
    lines = ["per valve (the verdict of most of its judged recordings):",
             f"  {'valve':<28} {'verdict':<13} {'p':>5} {'sticky':>6} {'not':>4} {'incon.':>6}  recordings"]
    for v in valves:
        p = "–" if v["stiction_probability"] is None else f"{v['stiction_probability']:.2f}"
        lines.append(f"  {v['tag']:<28} {v['verdict']:<13} {p:>5} {v['sticky']:>6} {v['not_sticky']:>4} "
                     f"{v['inconclusive']:>6}  {', '.join(map(str, v['recordings']))}")
    return lines
