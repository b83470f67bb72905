"""Whether a valve is getting worse: S and J, with their intervals, per recording of
the same valve, in order ([`jaxstiction.valve_trend`][]).

Recordings are grouped by tag: a mapping given by the user (name → tag; for a
`labels.json` of the plant set, each loop's `valve`), else a `tag` column in the file,
else the file name up to its last `_` or `-` (`FIC101_0301.csv` and
`FIC101_0302.csv` are two recordings of `FIC101`). Within a tag the recordings are
taken in the order of their names (so name the files by date). Each is fitted with
the full Kano search and no held-out part (S and J from the whole record), which
gives S and J with 95 % profile-likelihood intervals.

A valve's band **grows** at a recording when the lower end of that recording's
interval of S lies above the upper end of the interval of the valve's first usable
recording: the change is larger than either fit's uncertainty. It **shrinks** in the
mirror case (a repair, or a retuned positioner). When recordings lie both above and
below it, the change is `inconsistent`: the per-record intervals are then too narrow
to carry a trend.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from .._checks import error_line, LoopDataError, one_line
from .._estimate.report import fit
from .._estimate.settings import FULL_SEARCH_ESTIMATE, Settings
from .._io.read import find_loop_files, list_loops, loop_name, read_loop
from .._io.tags import natural_key, tag_of
from .._misc import json_number as _r


def band_changes(rows: list[dict]) -> tuple[str, str]:
    """Flag, in place, each recording whose band of S `grows` (the lower end of its
    interval above the upper end of the first usable recording's) or `shrinks` (the
    mirror case); return the valve's `change` at its last usable recording
    (`grows`, `shrinks`, `steady`, or `single` with fewer than two usable
    recordings; `inconsistent` when some recordings lie above the first one's
    interval and others below it) and a note. `rows` are in time order, each with `S_interval`
    (`None` when not fitted)."""
    usable = [r for r in rows if r.get("S_interval") is not None and None not in r["S_interval"]]
    for r in rows:
        r["grows"] = r["shrinks"] = False
    if len(usable) < 2:
        return "single", "fewer than two usable recordings: no trend"
    lo0, hi0 = usable[0]["S_interval"]
    for r in usable[1:]:
        r["grows"] = r["S_interval"][0] > hi0
        r["shrinks"] = r["S_interval"][1] < lo0
    if any(r["grows"] for r in usable) and any(r["shrinks"] for r in usable):
        return "inconsistent", ("the band moves both up and down beyond its intervals between recordings: the "
                                "intervals (of each record's own fit) understate how much S varies from record "
                                "to record, so no trend is claimed")
    last = usable[-1]
    change = "grows" if last["grows"] else "shrinks" if last["shrinks"] else "steady"
    note = ""
    if change == "steady" and any(r["grows"] for r in usable):
        note = "the band grew beyond its first interval in between, and is back within it at the last recording"
    return change, note


def valve_trend(paths, *, mapping: Mapping[str, str] | None = None, ts: float | None = None,
                recursive: bool = False, settings: Settings = FULL_SEARCH_ESTIMATE,
                progress: Callable[[str], object] | None = None) -> dict:
    """S and J per recording of each valve, in order, and whether the band grows
    (see the module notes).

    **Arguments:** `paths` (files and folders), `mapping` (recording name → tag),
    `ts` (for files without a time column), `recursive`, `settings` (the estimator's;
    its `validate` is set to 0), `progress` (called with a line per recording).

    **Returns:** `{"valves": [...], "recordings": n}`: per tag, its `recordings` (name,
    file, `S`, `J`, `S_interval`, `J_interval`, `fitness`, `status`, `grows`,
    `shrinks`), `change` (`grows`, `shrinks`, `steady`, `inconsistent`, or `single`
    with one usable recording) and a `note`. Only tags with two or more recordings are trends; the
    others are listed too.

    **Raises:** `ValueError` when a path does not exist or holds no loop files."""
    entries = []
    for path in find_loop_files(paths, recursive=recursive):
        try:
            subs = list(list_loops(path)) or [None]
        except Exception as e:  # noqa: BLE001 - a bad file is that file's entry
            entries.append((path.stem, path, None, f"unreadable: {error_line(e, 200)}"))
            continue
        for sub in subs:
            entries.append((loop_name(path) if not sub else f"{path.stem}:{sub}", path, sub, None))
    groups: dict[str, list] = {}
    for name, path, sub, err in entries:
        groups.setdefault(tag_of(name, path, mapping), []).append((name, path, sub, err))
    valves = []
    settings = dataclasses.replace(settings, validate=0.0)
    for tag in sorted(groups, key=natural_key):
        rows = []
        for name, path, sub, err in sorted(groups[tag], key=lambda e: natural_key(e[0])):
            row = {"name": name, "file": str(path), "S": None, "J": None, "S_interval": None, "J_interval": None,
                   "fitness": None, "status": err or "ok", "grows": False, "shrinks": False}
            if err is None:
                try:
                    loop = read_loop(path, ts=ts, name=sub)
                    r = fit(np.asarray(loop.op), np.asarray(loop.pv), ts=float(loop.ts), validate=0.0, name=name,
                            settings=settings)
                    row.update(S=_r(r.S), J=_r(r.J), S_interval=[_r(v) for v in r.S_interval],
                               J_interval=[_r(v) for v in r.J_interval], fitness=_r(r.fitness),
                               status=r.status)
                except (LoopDataError, ValueError, OSError) as e:
                    row["status"] = one_line(e)[:300]
            if progress is not None:
                progress(f"{tag}: {name}: S = {row['S']}, J = {row['J']} ({row['status']})")
            rows.append(row)
        change, note = band_changes(rows)
        valves.append({"tag": tag, "recordings": rows, "change": change, "note": note})
    return {"valves": valves, "recordings": sum(len(v["recordings"]) for v in valves)}


def trend_text(report: dict) -> str:
    """The text summary of a `valve_trend` report."""
    lines = []
    for v in report["valves"]:
        lines.append(f"valve {v['tag']}: {v['change']}" + (f" ({v['note']})" if v["note"] else ""))
        for r in v["recordings"]:
            if r["S"] is None:
                lines.append(f"  {r['name']:<14} {r['status']}")
                continue
            si, ji = r["S_interval"], r["J_interval"]
            flag = "  <- grows" if r["grows"] else "  <- shrinks" if r["shrinks"] else ""
            lines.append(f"  {r['name']:<14} S = {r['S']:.3g} [{si[0]:.3g}, {si[1]:.3g}], J = {r['J']:.3g} "
                         f"[{ji[0]:.3g}, {ji[1]:.3g}] % of span, fitness {r['fitness']:.1f} %{flag}")
    return "\n".join(lines)


def write_trend_figures(report: dict, out: Path) -> list[Path]:
    """One picture per valve with two or more recordings: `trend/TAG.png`."""
    from .figure import write_trend_figure

    out = Path(out)
    written = []
    for v in report["valves"]:
        if len(v["recordings"]) >= 2:
            safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in v["tag"])
            written.append(write_trend_figure(v["tag"], v["recordings"], out / "trend" / f"{safe}.png"))
    return written
