"""`screen --whatif`: what a repair would buy each sticky loop, and the maintenance
ranking by it.

`add_whatif` runs [`jaxstiction.whatif`][] on the sticky loops of a fitted chunk
(batched, on the chunk's own fits: no loop is fitted twice) and gives each a
`whatif` object; `rank_by_benefit` then orders the sticky loops by the predicted
benefit of a repair in % of their PV range, times an optional criticality weight
per tag (`read_criticality`). Kept apart from the batching and the verdict: the
chunk runner calls `add_whatif` only when `ScreenSettings.whatif` is set.
"""

from __future__ import annotations

import csv
import functools
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import error_line, LoopDataError
from .._loop import Loop
from .._programs import exported_call
from .._whatif.report import whatif_json
from .._whatif.settings import WhatIfSettings
from .._whatif.whatif import whatif


@eqx.filter_jit
def _whatif_vmapped(fits, loops: Loop, settings: WhatIfSettings):
    return eqx.filter_vmap(lambda f, lp: whatif(f, lp, settings))(fits, loops)


def _whatif_batch(fits, loops: Loop, settings: WhatIfSettings):
    """The what-if of a batch of loops, from its exported program (`exported_call`:
    a new process loads it instead of tracing it again)."""
    return exported_call("whatif", functools.partial(_whatif_vmapped, settings=settings), fits, loops,
                         static=repr(settings))


def whatif_batch_size(chunk: int) -> int:
    """Sticky loops per batched what-if call: one on a CPU, where a batch costs
    as much per loop as single calls (the refits' searches run to the batch's slowest
    member) and padding a partly sticky chunk to its size would repeat work; the
    chunk's size on an accelerator, where the batch runs in parallel. Either way
    every call has one shape, so one compiled program serves the screen."""
    return 1 if jax.default_backend() == "cpu" else chunk


def add_whatif(records: list[dict], fits, loops: Loop, settings: WhatIfSettings, pictures: bool = False) -> None:
    """Give every sticky loop of a chunk (`records[i]["verdict"] == "stiction"`) its
    `whatif` object, in place. `fits` and `loops` are the chunk's batched fit and
    loops (setpoints included); the sticky members run in batched calls of
    `whatif_batch_size` (a last partial batch repeats its first member, dropped), so
    every call shares one compiled program. With `pictures`, each entry also keeps
    the arrays of its what-if picture (`whatif_figure`)."""
    sticky = [i for i, r in enumerate(records) if r.get("verdict") == "stiction" and r.get("status") == "ok"]
    if not sticky:
        return
    batch = whatif_batch_size(loops.op.shape[0])
    for first in range(0, len(sticky), batch):
        group = sticky[first:first + batch]
        pick = np.asarray(group + [group[0]] * (batch - len(group)))
        try:
            sub_fits, sub_loops = jax.tree.map(lambda t: jnp.asarray(t)[pick], (fits, loops))
            w = jax.tree.map(np.asarray, _whatif_batch(sub_fits, sub_loops, settings))
        except Exception as e:  # noqa: BLE001 - a failed what-if costs only its own field
            for i in group:
                records[i]["whatif"] = {"note": f"what-if failed: {error_line(e, 300)}"}
            continue
        for k, i in enumerate(group):
            _add_one(records[i], jax.tree.map(lambda t, k=k: t[k], w), loops, i, settings, pictures)


def _add_one(rec: dict, wi, loops: Loop, i: int, settings: WhatIfSettings, pictures: bool) -> None:
    """Loop `i`'s `whatif` object (and, with `pictures`, its picture's arrays)."""
    try:
        rec["whatif"] = whatif_json(wi, rec["Ts"], settings)
    except Exception as e:  # noqa: BLE001
        rec["whatif"] = {"note": f"what-if report failed: {error_line(e, 300)}"}
        return
    if pictures:
        n = int(rec["samples"])
        sp = np.asarray(loops.setpoint[i])[:n]
        sp = sp if np.all(np.isfinite(sp)) else np.full(n, float(np.mean(np.asarray(loops.pv[i])[:n])))
        rec["whatif_figure"] = {"sp": sp, "start": int(wi.start),
                                **{f"{q}_{s}": np.asarray(getattr(wi, f"{q}_{s}"))[:n]
                                   for q in ("pv", "valve", "op") for s in ("as_is", "repaired", "compensated")}}


def read_criticality(path) -> dict[str, float]:
    """Criticality weights per tag from a CSV file with a header holding a `tag`
    column and a `weight` (or `criticality`) column: `{tag: weight}`.

    **Raises:** a one-line `LoopDataError` for a missing file or column, or a weight
    that is not a non-negative number."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise LoopDataError(f"{path}: cannot read the criticality file ({e.strerror or e})") from e
    if not rows:
        raise LoopDataError(f"{path}: the criticality file has no rows")
    columns = {c.strip().lower(): c for c in rows[0] if c is not None}
    tag = columns.get("tag")
    weight = columns.get("weight") or columns.get("criticality")
    if tag is None or weight is None:
        raise LoopDataError(f"{path}: the criticality file needs a `tag` and a `weight` column, got "
                            f"{', '.join(c for c in rows[0] if c)}")
    out = {}
    for k, row in enumerate(rows, 2):
        try:
            w = float(row[weight])
        except (TypeError, ValueError):
            w = float("nan")
        if not (math.isfinite(w) and w >= 0):
            raise LoopDataError(f"{path}: line {k}: the weight of {row[tag]!r} must be a number >= 0, "
                                f"got {row[weight]!r}")
        out[str(row[tag]).strip()] = w
    return out


def _weight(entry: dict, criticality: dict[str, float]):
    """The criticality weight of a loop: its name, the tag after a `file:` prefix, or
    its file's stem; `None` when the table does not name it."""
    name = str(entry.get("name", ""))
    keys = [name, name.split(":")[-1], name.split("/")[-1]]
    if entry.get("file"):
        keys.append(Path(entry["file"]).stem)
    for k in keys:
        if k in criticality:
            return criticality[k]
    return None


def rank_by_benefit(results: list[dict], criticality: dict[str, float] | None = None) -> list[dict]:
    """`results` (already ranked by [`jaxstiction.rank`][]) with the sticky loops
    reordered by priority: the predicted benefit of a repair in % of the loop's PV
    range (`whatif.benefit_percent_of_range`) times the criticality weight of its tag
    (1 when no table is given, or when the table does not name it: its `whatif`
    then says so). Sticky loops without a benefit follow, in their order; the other
    loops keep their places after them. Sets `whatif.criticality` and
    `whatif.priority`."""
    sticky = [r for r in results if r.get("verdict") == "stiction" and isinstance(r.get("whatif"), dict)]
    for r in sticky:
        w = r["whatif"]
        weight = _weight(r, criticality) if criticality else None
        if criticality and weight is None:
            w["note"] = "; ".join(n for n in (w.get("note", ""), "the criticality table does not name this loop: "
                                              "weight 1") if n)
        w["criticality"] = 1.0 if weight is None else weight
        b = w.get("benefit_percent_of_range")
        w["priority"] = None if b is None else round(b * w["criticality"], 4)
    ranked = sorted(sticky, key=lambda r: (r["whatif"]["priority"] is None, -(r["whatif"]["priority"] or 0.0)))
    keep = iter(ranked)
    return [next(keep) if (r.get("verdict") == "stiction" and isinstance(r.get("whatif"), dict)) else r
            for r in results]
