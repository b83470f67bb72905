r"""Screening a fleet: read and check every loop, fit and judge them in batches
(`batch`), name the causes of the others (`causes`), and rank them:
[`jaxstiction.screen`][], [`jaxstiction.screen_loops`][], [`jaxstiction.rank`][]
and [`jaxstiction.ScreenReport`][]."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._checks import error_line, LoopDataError, LoopDataWarning, one_line
from .._estimate.report import checked
from .._io.read import find_loop_files, list_loops, loop_name, read_loop
from .._loop import decimate as decimated, decimation_factor, Loop, window_length, window_name, windows
from .._misc import warn_without_float64
from .batch import _dask_client, _error, _run
from .causes import _to_diagnose, diagnose_causes
from .settings import ScreenSettings


def _unique_name(name: str, path: Path, taken: set) -> str:
    """`name`, or when another loop has it already, `folder/name` (then `name#k`):
    every entry, note and diagnosis is keyed by name."""
    for candidate in (name, f"{path.parent.name}/{name}"):
        if candidate not in taken:
            return candidate
    k = 2
    while f"{name}#{k}" in taken:
        k += 1
    return f"{name}#{k}"


def read_items(paths, *, ts: float | None = None, settings: ScreenSettings = ScreenSettings(),
               recursive: bool = False, decimate: int = 1, window: int | None = None):
    """Read and check every loop under `paths` (files and folders, their subfolders
    too with `recursive`; a `.mat` file, or a CSV file with tagged columns, may hold
    several loops: see [`jaxstiction.list_loops`][]). Returns `(items,
    errors, warned)`: `(name, file, op, pv, ts, sp)` tuples ready to fit (`sp` `None`
    without a recorded setpoint), error entries
    (one line each) for the loops that cannot be, and the
    [`jaxstiction.LoopDataWarning`][] messages of the readable ones by name. Names
    are unique: a name met again gets its folder in front (`unit2/FC101`). Every
    record is decimated by `decimate` (see [`jaxstiction.decimate`][]) before it is
    checked; with `window`, a record longer than `window` samples (after that) is
    cut into the fewest windows of equal length holding at most `window` each, each
    one item named `NAME@START-STOP` (its samples, counted from 0, stop excluded)."""
    items, errors, warned = [], [], {}
    taken: set[str] = set()
    for path in find_loop_files(paths, recursive=recursive):
        try:
            names: list[str | None] = list(list_loops(path)) or [None]
        except Exception as e:  # noqa: BLE001 - a bad file is that file's error
            name = _unique_name(path.stem, path, taken)
            taken.add(name)
            errors.append(_error(name, str(path), _message(e)))
            continue
        for sub in names:
            name = _unique_name(loop_name(path) if not sub else f"{path.stem}:{sub}", path, taken)
            taken.add(name)
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", LoopDataWarning)
                    loop = decimated(read_loop(path, ts=ts, name=sub), decimate)
                parts = [(0, None, loop)] if window is None else windows(loop, window)
                said = [str(w.message) for w in caught if issubclass(w.category, LoopDataWarning)]
                for a, b, part in parts:
                    part_name = name if len(parts) == 1 else window_name(name, a, b)
                    taken.add(part_name)
                    try:
                        op, pv = checked(np.asarray(part.op), np.asarray(part.pv), part_name, settings.estimate)
                    except ValueError as e:  # one window's bad data is that window's error
                        errors.append(_error(part_name, str(path), _message(e)))
                        continue
                    items.append((part_name, str(path), op, pv, float(part.ts), _setpoint(part)))
                    if said:
                        warned[part_name] = "; ".join(said)
                for w in caught:  # any other warning goes on as it would have
                    if not issubclass(w.category, LoopDataWarning):
                        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
            except Exception as e:  # noqa: BLE001
                errors.append(_error(name, str(path), _message(e)))
    return items, errors, warned


def _message(e: BaseException) -> str:
    if isinstance(e, (LoopDataError, ValueError, OSError)):
        return one_line(e)[:300]
    return f"unreadable: {error_line(e, 300)}"


_FLOAT32 = ("its verdict was calibrated on float64 evidence, and float32 changes the fits it reports (the band, "
            "S and J) and the model-based test that decides under setpoint moves")


def screen_loops(loops: Mapping[str, Loop] | Sequence[tuple], settings: ScreenSettings = ScreenSettings(), *,
                 progress: Callable[[int], Any] | None = None, scheduler: Any = None,
                 pictures: bool = False) -> list[dict]:
    """Screen loops already in memory. `loops`: a mapping name → [`jaxstiction.Loop`][]
    (real samples only), or `(name, file, op, pv, ts[, sp])` items as from `read_items`.
    Returns one entry per loop, in input order (see [`jaxstiction.screen`][]).
    Warns when JAX runs in float32, as `screen` does."""
    warn_without_float64("screen_loops", _FLOAT32)
    if isinstance(loops, Mapping):
        items, errors = [], []
        for name, lp in loops.items():
            try:
                op, pv = _checked_loop(lp, name, settings)
                items.append((name, None, op, pv, float(np.asarray(lp.ts)), _setpoint(lp)))
            except ValueError as e:
                errors.append(_error(name, None, _message(e)))
    else:
        items, errors = list(loops), []
    order = {it[0]: i for i, it in enumerate(items)}
    results = errors + _run(items, settings, progress, scheduler, pictures)
    return sorted(results, key=lambda r: order.get(r["name"], -1))


def _setpoint(lp: Loop):
    """The real samples of the loop's setpoint as a NumPy array, or `None`."""
    if lp.sp is None:
        return None
    return np.asarray(lp.sp)[np.asarray(lp.mask) > 0]


def _checked_loop(lp: Loop, name, settings):
    m = np.asarray(lp.mask) > 0
    return checked(np.asarray(lp.op)[m], np.asarray(lp.pv)[m], name, settings.estimate)


def rank(results: Iterable[dict]) -> list[dict]:
    """Loops ranked by how likely and how severe stiction is: sticky loops first, by
    probability times band (a likely valve with a wide band is the worst; band in %
    of OP, at least 0.1 so a tiny band cannot hide a likely valve), then the
    inconclusive loops, then the loops without stiction, each by probability, then
    the loops that could not be fitted."""
    order = {"stiction": 0, "inconclusive": 1, "no_stiction": 2}

    def key(r):
        ok = r["status"] == "ok"
        p = r.get("stiction_probability")
        p = -1.0 if p is None else p
        band = max(r.get("band_percent") or 0.0, 0.1)
        severity = p * band if r.get("stiction_detected") else p
        return (not ok, order.get(r.get("verdict"), 1), -severity)

    return sorted(results, key=key)


@dataclasses.dataclass(frozen=True)
class ScreenReport:
    """Result of [`jaxstiction.screen`][]: `loops`, ranked (see `rank`), and counts;
    with `by_valve`, `valves`: one verdict per valve tag (`valve_verdicts`)."""

    loops: list
    valves: list | None = None

    @property
    def counts(self) -> dict:
        ok = sum(r["status"] == "ok" for r in self.loops)
        return {"loops": len(self.loops), "ok": ok, "errors": len(self.loops) - ok,
                "sticky": sum(bool(r["stiction_detected"]) for r in self.loops)}

    def summary_line(self) -> str:
        c = self.counts
        line = (f"screen: {c['loops']} loops: {c['ok']} ok, {c['errors']} error{'s' * (c['errors'] != 1)}, "
                f"{c['sticky']} sticky")
        if self.valves is not None:
            sticky = sum(v["verdict"] == "stiction" for v in self.valves)
            line += f"; {len(self.valves)} valve{'s' * (len(self.valves) != 1)}: {sticky} sticky"
        return line

    def to_json(self) -> dict:
        loops = [{k: v for k, v in r.items() if k not in ("figure", "whatif_figure")} for r in self.loops]
        return {"loops": loops, "summary": self.counts, **({} if self.valves is None else {"valves": self.valves})}


@contextlib.contextmanager
def _progress_bar(show: bool, total: int, desc: str):
    """A tqdm bar on stderr counting loops (its `update`), or `None` when not shown."""
    if not (show and total):
        yield None
        return
    from tqdm import tqdm

    bar = tqdm(total=total, unit="loop", desc=desc, file=sys.stderr)
    try:
        yield bar.update
    finally:
        bar.close()


def screen(paths: str | os.PathLike | Iterable[str | os.PathLike], settings: ScreenSettings = ScreenSettings(), *,
           ts: float | None = None, progress: bool = False, scheduler: Any = None,
           pictures: bool = False, diagnose: bool = False, recursive: bool = False,
           decimate: int = 1, criticality: Mapping[str, float] | None = None,
           window: int | None = None, by_valve: bool | Mapping[str, str] = False) -> ScreenReport:
    """Screen every loop under `paths` (CSV files, ISDB `.mat` files, folders of them)
    for sticky valves, and name the cause of the others.

    Each loop gets [`jaxstiction.estimate`][] (batched with the other loops of its
    length bucket) and [`jaxstiction.verdict`][]: a `verdict` (`stiction`,
    `no_stiction` or `inconclusive`, with the data-quality gate's reason) from the
    calibrated `stiction_probability` (and, under setpoint moves, the model-based
    test), `stiction_detected` when the verdict is `stiction`, `slip_identified`
    when the valve's slip jump is seen, and a `cause` (`stiction`,
    `external_oscillation`, `none`; with `diagnose`, the diagnosis verdict of a loop
    not called sticky). A loop that cannot be read or fitted gets `status` with a
    one-line error and the verdict `inconclusive`; the others are unaffected.

    **Arguments:**

    - `settings`: [`jaxstiction.ScreenSettings`][].
    - `ts`: sampling time for files without a `t` column.
    - `progress`: show a progress bar (tqdm) on stderr.
    - `scheduler`: a Dask scheduler address (or a `dask.distributed.Client`): each
      chunk becomes one task on the cluster (with `diagnose`, each diagnosis too).
    - `pictures`: keep the arrays each loop's picture needs (`figure`).
    - `recursive`: also the loop files in the folders' subfolders.
    - `decimate`: screen every record at a `decimate` times longer sampling time
      (the means of that many samples; [`jaxstiction.decimate`][]), for records
      sampled much faster than their loops move.
    - `window`: screen a record longer than `window` samples (after `decimate`)
      as the fewest consecutive windows of equal length that hold at most `window`
      samples each, one entry per window named `NAME@START-STOP` (its samples,
      counted from 0, stop excluded). Over days of data a slow cycle can hide a
      limit cycle from the oscillation indicators; a window of a few thousand
      samples does not hold it.
    - `diagnose`: name the cause of the loops not called sticky by the full
      diagnosis (`diagnose_causes`).
    - `criticality`: weights per tag for the maintenance ranking (with
      `settings.whatif`): the sticky loops are ranked by the predicted benefit of a
      repair in % of their PV range times their weight (`rank_by_benefit`).
    - `by_valve`: also one verdict per valve (`ScreenReport.valves`), the
      recordings grouped by tag: `True` takes a file's `tag` column, else its name
      up to the last `_` or `-`; a mapping (recording name or file stem → tag,
      e.g. from `read_tags`) is asked first.

    **Returns:** a [`jaxstiction.ScreenReport`][]. A `UserWarning` says so when JAX
    runs in float32: the verdict was calibrated on float64 evidence, and float32
    changes the fits (enable float64 with `jax.config.update("jax_enable_x64", True)`;
    the command line does).

    **Raises:** `ValueError` when a path does not exist, a folder has no loop files,
    or `decimate` or `window` is not a positive integer.
    """
    warn_without_float64("screen", _FLOAT32)
    decimate = decimation_factor(decimate)  # a bad factor fails before any file is read
    window = None if window is None else window_length(window)  # as `decimate`: before any file is read
    items, errors, warned = read_items(paths, ts=ts, settings=settings, recursive=recursive, decimate=decimate,
                                       window=window)
    with contextlib.ExitStack() as client_scope:
        if scheduler is not None:  # one client for both stages
            scheduler = client_scope.enter_context(_dask_client(scheduler))[0]
        with _progress_bar(progress, len(items), "screen") as update:
            results = _run(items, settings, update, scheduler, pictures)
        if diagnose:
            with _progress_bar(progress, sum(map(_to_diagnose, results)), "diagnose") as update:
                results = diagnose_causes(results, items, progress=update, scheduler=scheduler)
    for r in results:  # what the reader warned of goes first in the loop's note
        if r["name"] in warned:
            r["note"] = "; ".join(n for n in (warned[r["name"]], r.get("note", "")) if n)
    ranked = rank(errors + results)
    if settings.whatif is not None:
        from .whatif import rank_by_benefit

        ranked = rank_by_benefit(ranked, dict(criticality) if criticality else None)
    valves = None
    if by_valve is not False:
        from .valves import valve_verdicts

        valves = valve_verdicts(ranked, None if by_valve is True else by_valve)
    return ScreenReport(loops=ranked, valves=valves)


