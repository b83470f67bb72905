r"""Fleet screening: many loops through one batched, jitted estimate and verdict.

Loops are bucketed by length (a ladder of lengths ~√2 apart), padded and masked
inside a bucket, and fitted in chunks of a fixed size by one compiled call of
`vmap(estimate + verdict)`, so compilation is paid once per bucket, and never per
loop. Nothing loops over loops in Python inside a chunk. A loop with bad data is
stopped on the host with a one-line message before it reaches a chunk; a loop
whose fit fails inside a chunk gets its own result code; a chunk that fails as a
whole (an XLA error, memory) is re-run one loop at a time, so only the loop that
caused it loses its result.

Chunks run in this process, on every local JAX device in turn, or as tasks on a
Dask cluster (`scheduler=`), each task one batched fit; with `diagnose`, each
loop's diagnosis is one more task.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
import os
import sys
import threading
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ._checks import check_counts, error_line, one_line
from ._estimate.estimate import estimate
from ._estimate.result import delay_note, held_out_note, KINDS, RESULTS
from ._estimate.settings import SCREEN_ESTIMATE, Settings
from ._loop import Loop, make_loop, stack
from ._misc import json_number as _r, release_freed_memory, thread_map
from ._verdict.settings import VerdictSettings
from ._verdict.verdict import CAUSES, usable, verdict


class ScreenSettings(eqx.Module):
    """Settings of [`jaxstiction.screen`][].

    - `estimate`: [`jaxstiction.Settings`][] of every fit (default: the screen's
      lighter profile, Kano valve and nulls only; `Settings()` for the full
      estimator); `verdict`: [`jaxstiction.VerdictSettings`][].
    - `chunk`: at most this many loops per batched call; `samples_per_call`: fewer
      when `chunk` × bucket length would exceed it (memory grows with both).
    - `threads`: batched calls run at once, each on its own thread (0: one per CPU
      core, at most 8). XLA's CPU backend runs one call's work on one core at a time, so a
      second call in flight uses a second core; memory grows with the calls in
      flight. (Without a Dask scheduler.)
    """

    estimate: Settings = SCREEN_ESTIMATE
    verdict: VerdictSettings = VerdictSettings()
    chunk: int = eqx.field(static=True, default=2)
    samples_per_call: int = eqx.field(static=True, default=8000)
    threads: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        check_counts(self, positive=("chunk", "samples_per_call"), nonnegative=("threads",))


def bucket_length(n: int) -> int:
    """The padded length of a bucket holding `n`-sample loops: the first of 500,
    800, 1000, 1500, 2000, 2900, 4000, … (500 × √2^k rounded up to 100) that is
    at least `n`."""
    k = 0
    while True:
        b = int(math.ceil(500 * 2 ** (k / 2) / 100) * 100)
        if b >= n:
            return b
        k += 1


def chunk_size(length: int, settings: ScreenSettings) -> int:
    """Loops per batched call for a bucket of `length` samples."""
    return max(1, min(settings.chunk, settings.samples_per_call // max(length, 1)))


@eqx.filter_jit
def _verdicts(fits, loops: Loop, vset: VerdictSettings):
    return eqx.filter_vmap(lambda f, lp: verdict(f, lp, vset))(fits, loops)


def _batch(loops: Loop, settings: Settings, vset: VerdictSettings):
    # `filter_vmap` of the jitted `estimate` (the documented batched contract): its
    # compiled batch is shared with any other such call of the same shapes.
    fits = eqx.filter_vmap(lambda lp: estimate(lp, settings))(loops)
    return fits, _verdicts(fits, loops, vset)


def _record(name, file, op, pv, ts, fit, ver, settings: Settings, pictures: bool) -> dict:
    """One loop's screen entry (JSON-ready, plus a `figure` of NumPy arrays when
    `pictures`) from its unbatched host-side fit and verdict."""
    converged = bool(fit.result == RESULTS.successful)
    ok = bool(usable(fit.result)) and math.isfinite(float(fit.fitness_physical))
    cause = CAUSES[int(ver.cause)]
    notes = [RESULTS[fit.result] if not converged else "", delay_note(fit.delay, fit.kind, settings) if ok else "",
             held_out_note(fit.fitness, fit.fitness_estimation, fit.n_validation) if ok else "",
             (f"the Kano valve leaves the linear fit's oscillation (period {float(ver.period):.0f} samples) in "
              "its residual: a disturbance from elsewhere, not the valve's cycle") if ok and bool(ver.line_persists)
             else ""]
    rec = {
        "name": name,
        "file": file,
        "status": "ok" if ok else RESULTS[fit.result],
        "converged": converged,
        "note": "; ".join(n for n in notes if n),
        "samples": int(op.shape[0]),
        "Ts": float(ts),
        "stiction_detected": bool(ver.stiction_detected),
        "cause": cause if ok else None,
        "slip_identified": bool(ver.slip_identified) if ok else None,
        # the Kano fit's band, which the verdict judges, whichever family `estimate`
        # chose (the linear valve's band is 0)
        "band_percent": _r(fit.S if math.isfinite(float(fit.S)) else fit.band_percent),
        "fitness": _r(fit.fitness),
        "S": _r(fit.S),
        "J": _r(fit.J),
        "evidence": _r(ver.evidence),
        "evidence_estimation": _r(ver.evidence_estimation),
        "evidence_prediction": _r(ver.evidence_prediction),
        "evidence_prediction_estimation": _r(ver.evidence_prediction_estimation),
        "slip_evidence": _r(ver.slip_evidence),
        "slip_evidence_estimation": _r(ver.slip_evidence_estimation),
        "band_fraction": _r(ver.band_fraction, 4),
        "fitness_kano": _r(fit.fitness_physical),
        "fitness_linear": _r(fit.fitness_linear),
        "fitness_deadband": _r(fit.fitness_deadband),
        "oscillation": _r(ver.oscillation),
        "period_samples": _r(ver.period, 1),
        "oscillation_kano": _r(ver.oscillation_kano),
        "model": KINDS[int(fit.kind)],
        "delay": int(fit.delay),
    }
    if pictures and ok:
        from ._estimate.report import report

        jfit = jax.tree.map(jax.numpy.asarray, fit)
        r = report(jfit, op, pv, name=name, ts=ts, settings=settings)
        rec["figure"] = dict(op=r.op, pv=r.pv, pv_sim=r.pv_sim, valve_u=r.valve_u, valve_up=r.valve_up,
                             valve_down=r.valve_down, n_estimation=r.n_estimation, kind=r.model_kind)
    return rec


def run_chunk(items: Sequence[tuple], length: int, size: int, settings: ScreenSettings = ScreenSettings(),
              *, pictures: bool = False, enable_x64: bool = False, device=None) -> list[dict]:
    """Fit one chunk of loops in one batched call and return their entries.

    `items`: `(name, file, op, pv, ts)` tuples (NumPy arrays, already checked),
    padded to `length` samples and, with repeats of the first loop that are then
    dropped, to `size` loops, so every chunk of a bucket has one shape. A top-level
    function of plain arguments, so a Dask worker can run it; `enable_x64` turns on
    float64 in that worker (the application's choice, as the CLI's).
    """
    if enable_x64:
        jax.config.update("jax_enable_x64", True)
    items = list(items)
    loops = [make_loop(op, pv, ts) for (_, _, op, pv, ts) in items]
    loops += [loops[0]] * (size - len(loops))
    try:
        batch = stack(loops, length)
        if device is not None:
            batch = jax.device_put(batch, device)
        fits, vers = _batch(batch, settings.estimate, settings.verdict)
        fits, vers = jax.tree.map(np.asarray, (fits, vers))
    except Exception as e:  # noqa: BLE001 - an XLA failure must cost only its own loops
        if len(items) > 1:
            out = []
            for it in items:
                out += run_chunk([it], length, 1, settings, pictures=pictures)
            return out
        name, file, op, pv, ts = items[0]
        return [_error(name, file, f"fit failed: {error_line(e, 300)}", op.shape[0], ts)]
    out = []
    for i, (name, file, op, pv, ts) in enumerate(items):
        fit, ver = jax.tree.map(lambda x: np.asarray(x[i]), (fits, vers))
        try:
            out.append(_record(name, file, op, pv, ts, fit, ver, settings.estimate, pictures))
        except Exception as e:  # noqa: BLE001
            out.append(_error(name, file, f"report failed: {error_line(e, 300)}", op.shape[0], ts))
    return out


def _error(name, file, message, samples=None, ts=None) -> dict:
    return {"name": name, "file": file, "status": message, "samples": samples, "Ts": ts,
            "stiction_detected": False, "cause": None, "band_percent": None, "fitness": None}


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
               recursive: bool = False, decimate: int = 1):
    """Read and check every loop under `paths` (files and folders, their subfolders
    too with `recursive`; a `.mat` file, or a CSV file with tagged columns, may hold
    several loops: see [`jaxstiction.list_loops`][]). Returns `(items,
    errors, warned)`: `(name, file, op, pv, ts)` tuples ready to fit, error entries
    (one line each) for the loops that cannot be, and the
    [`jaxstiction.LoopDataWarning`][] messages of the readable ones by name. Names
    are unique: a name met again gets its folder in front (`unit2/FC101`). Every
    record is decimated by `decimate` (see [`jaxstiction.decimate`][]) before it is
    checked."""
    from ._checks import LoopDataWarning
    from ._estimate.report import checked
    from ._io.read import find_loop_files, list_loops, loop_name, read_loop
    from ._loop import decimate as decimated

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
                op, pv = checked(np.asarray(loop.op), np.asarray(loop.pv), name, settings.estimate)
                items.append((name, str(path), op, pv, float(loop.ts)))
                said = [str(w.message) for w in caught if issubclass(w.category, LoopDataWarning)]
                if said:
                    warned[name] = "; ".join(said)
                for w in caught:  # any other warning goes on as it would have
                    if not issubclass(w.category, LoopDataWarning):
                        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
            except Exception as e:  # noqa: BLE001
                errors.append(_error(name, str(path), _message(e)))
    return items, errors, warned


def _message(e: BaseException) -> str:
    from ._checks import LoopDataError

    if isinstance(e, (LoopDataError, ValueError, OSError)):
        return one_line(e)[:300]
    return f"unreadable: {error_line(e, 300)}"


def _chunks(items, settings: ScreenSettings):
    """`(length, size, members)` for every chunk: bucketed by length, in order."""
    buckets: dict[int, list] = {}
    for it in items:
        buckets.setdefault(bucket_length(it[2].shape[0]), []).append(it)
    for length in sorted(buckets):
        size = chunk_size(length, settings)
        members = buckets[length]
        for i in range(0, len(members), size):
            yield length, size, members[i : i + size]


def screen_loops(loops: Mapping[str, Loop] | Sequence[tuple], settings: ScreenSettings = ScreenSettings(), *,
                 progress: Callable[[int], Any] | None = None, scheduler: Any = None,
                 pictures: bool = False) -> list[dict]:
    """Screen loops already in memory. `loops`: a mapping name → [`jaxstiction.Loop`][]
    (real samples only), or `(name, file, op, pv, ts)` items as from `read_items`.
    Returns one entry per loop, in input order (see [`jaxstiction.screen`][])."""
    if isinstance(loops, Mapping):
        items, errors = [], []
        for name, lp in loops.items():
            try:
                op, pv = _checked_loop(lp, name, settings)
                items.append((name, None, op, pv, float(np.asarray(lp.ts))))
            except ValueError as e:
                errors.append(_error(name, None, _message(e)))
    else:
        items, errors = list(loops), []
    order = {it[0]: i for i, it in enumerate(items)}
    results = errors + _run(items, settings, progress, scheduler, pictures)
    return sorted(results, key=lambda r: order.get(r["name"], -1))


def _checked_loop(lp: Loop, name, settings):
    from ._estimate.report import checked

    m = np.asarray(lp.mask) > 0
    return checked(np.asarray(lp.op)[m], np.asarray(lp.pv)[m], name, settings.estimate)


def _run(items, settings, progress, scheduler, pictures) -> list[dict]:
    chunks = list(_chunks(items, settings))
    if scheduler is not None:
        return _run_dask(chunks, settings, progress, scheduler, pictures)
    devices = jax.local_devices()
    lock = threading.Lock()

    def one(indexed):
        k, (length, size, members) = indexed
        dev = devices[k % len(devices)] if len(devices) > 1 else None
        out = run_chunk(members, length, size, settings, pictures=pictures, device=dev)
        if progress is not None:
            with lock:
                progress(len(members))
        return out

    # bucket by bucket: its first chunk alone (the call compiles the bucket's
    # program once), the others `settings.threads` at a time
    out = []
    for _, bucket in itertools.groupby(enumerate(chunks), key=lambda kc: kc[1][:2]):
        out += [r for part in thread_map(one, bucket, settings.threads) for r in part]
    return out


@contextlib.contextmanager
def _dask_client(scheduler):
    """`(client, as_completed)` for a Dask scheduler address or `Client`; a client
    opened here from an address is closed on exit."""
    try:
        from dask.distributed import as_completed, Client
    except ImportError as e:  # pragma: no cover - depends on the install
        raise ValueError("--scheduler needs dask.distributed: pip install 'jaxstiction[dask]'") from e
    if isinstance(scheduler, Client):
        yield scheduler, as_completed
        return
    with Client(scheduler) as client:
        yield client, as_completed


def _run_dask(chunks, settings, progress, scheduler, pictures) -> list[dict]:
    x64 = bool(jax.config.jax_enable_x64)
    with _dask_client(scheduler) as (client, as_completed):
        futures = {client.submit(run_chunk, members, length, size, settings, pictures=pictures, enable_x64=x64,
                                 pure=False): members for length, size, members in chunks}
        out = []
        for fut in as_completed(futures):
            members = futures[fut]
            try:
                out += fut.result()
            except Exception as e:  # noqa: BLE001 - a lost worker costs only its chunk
                out += [_error(m[0], m[1], f"task failed: {error_line(e, 300)}", m[2].shape[0], m[4]) for m in members]
            if progress is not None:
                progress(len(members))
        return out


def rank(results: Iterable[dict]) -> list[dict]:
    """Loops ranked by stiction evidence and severity: sticky loops first (largest
    held-out gain of the Kano valve over a linear one, in simulation or in
    short-horizon prediction, then widest band), then the other fitted loops by the
    same evidence, then the loops that failed."""

    def key(r):
        ok = r["status"] == "ok"
        gains = [g for g in (r.get("evidence"), r.get("evidence_prediction")) if g is not None]
        ev = max(gains) if gains else -1e9
        return (not ok, not r["stiction_detected"], -ev, -(r.get("band_percent") or 0.0))

    return sorted(results, key=key)


@dataclasses.dataclass(frozen=True)
class ScreenReport:
    """Result of [`jaxstiction.screen`][]: `loops`, ranked (see `rank`), and counts."""

    loops: list

    @property
    def counts(self) -> dict:
        ok = sum(r["status"] == "ok" for r in self.loops)
        return {"loops": len(self.loops), "ok": ok, "errors": len(self.loops) - ok,
                "sticky": sum(bool(r["stiction_detected"]) for r in self.loops)}

    def summary_line(self) -> str:
        c = self.counts
        return (f"screen: {c['loops']} loops: {c['ok']} ok, {c['errors']} error{'s' * (c['errors'] != 1)}, "
                f"{c['sticky']} sticky")

    def to_json(self) -> dict:
        loops = [{k: v for k, v in r.items() if k != "figure"} for r in self.loops]
        return {"loops": loops, "summary": self.counts}


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


def _to_diagnose(r: dict) -> bool:
    """Whether `diagnose_causes` diagnoses this entry: fitted, not called sticky."""
    return r["status"] == "ok" and not r["stiction_detected"]


_DIAGNOSED_LENGTH = [None]  # the record length whose compiled diagnosis programs this process holds


def diagnose_entry(entry: dict, op, pv, ts, settings, *, enable_x64: bool = False) -> dict:
    """One screen entry with its `cause` from the full diagnosis (see
    `diagnose_causes`); a new dict. A top-level function of plain arguments, so a
    Dask worker can run it; `enable_x64` turns on float64 there.

    A diagnosis compiles hundreds of MB of programs per record length (14 ISDB
    loops: 3.9 GB kept over 7 lengths), so a process drops them when the length
    changes: callers send loops in order of length."""
    from ._diagnose.diagnose import diagnose

    if enable_x64:
        jax.config.update("jax_enable_x64", True)
    n = int(np.shape(op)[0])
    if _DIAGNOSED_LENGTH[0] not in (None, n):
        jax.clear_caches()
        release_freed_memory()
    _DIAGNOSED_LENGTH[0] = n
    r = dict(entry)
    try:
        d = diagnose(make_loop(op, pv, ts), None, settings, name=str(r.get("name", "loop")))
    except Exception as e:  # noqa: BLE001 - a failed diagnosis costs only this loop's cause
        return _noted(r, f"diagnose failed, cause from the screen: {error_line(e, 300)}")
    r["diagnosis"] = {"verdict": d.verdict, "runner_up": d.runner_up, "accepted": list(d.accepted)}
    if d.verdict == "stiction":
        return _noted(r, "diagnose names stiction, which the screen's held-out test did not confirm; "
                         "cause from the screen")
    r["cause"] = d.verdict
    return r


def _noted(r: dict, said: str) -> dict:
    r["note"] = "; ".join(n for n in (r.get("note", ""), said) if n)
    return r


def diagnose_causes(results: Sequence[dict], items: Sequence[tuple], settings: Any = None, *,
                    progress: Callable[[int], Any] | None = None, scheduler: Any = None) -> list[dict]:
    """The `cause` of every fitted loop that is not called sticky, from the full
    mismatch diagnosis ([`jaxstiction.diagnose`][], no nominal model) instead of the
    screen's own residual-line test: its whole vocabulary (`deadband`, `dead_time`,
    `saturation`, `external_oscillation`, `drift`, `quantization`, `none`, ...), at
    ~10-80 s per loop. Each such entry gains `diagnosis` (`verdict`, `runner_up`,
    `accepted`). A diagnosis that names stiction where the screen's held-out test did
    not leaves the screen's cause and says so in the `note`; a diagnosis that fails
    (or whose Dask task is lost) leaves it too, with the one-line error in the `note`.

    `results`: entries of `screen_loops`; `items`: the `(name, file, op, pv, ts)`
    tuples they came from; `settings`: `DiagnoseSettings`; `progress`: called with 1
    after each diagnosis; `scheduler`: a Dask scheduler address or
    `dask.distributed.Client`, to run one task per loop on the cluster. Returns new
    entries, in the same order."""
    from ._diagnose.settings import DiagnoseSettings

    settings = DiagnoseSettings() if settings is None else settings
    by_name = {it[0]: it for it in items}
    out = list(results)
    todo = [i for i, r in enumerate(out) if _to_diagnose(r) and r["name"] in by_name]
    todo.sort(key=lambda i: by_name[out[i]["name"]][2].shape[0])  # see `diagnose_entry`
    if scheduler is None:
        for i in todo:
            _, _, op, pv, ts = by_name[out[i]["name"]]
            out[i] = diagnose_entry(out[i], op, pv, ts, settings)
            if progress is not None:
                progress(1)
        return out
    x64 = bool(jax.config.jax_enable_x64)
    with _dask_client(scheduler) as (client, as_completed):
        futures = {client.submit(diagnose_entry, out[i], *by_name[out[i]["name"]][2:], settings, enable_x64=x64,
                                 pure=False): i for i in todo}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                out[i] = fut.result()
            except Exception as e:  # noqa: BLE001 - a lost worker costs only this loop's cause
                out[i] = _noted(dict(out[i]),
                                f"diagnose failed, cause from the screen: task failed: {error_line(e, 300)}")
            if progress is not None:
                progress(1)
    return out


def screen(paths: str | os.PathLike | Iterable[str | os.PathLike], settings: ScreenSettings = ScreenSettings(), *,
           ts: float | None = None, progress: bool = False, scheduler: Any = None,
           pictures: bool = False, diagnose: bool = False, recursive: bool = False,
           decimate: int = 1) -> ScreenReport:
    """Screen every loop under `paths` (CSV files, ISDB `.mat` files, folders of them)
    for sticky valves, and name the cause of the others.

    Each loop gets [`jaxstiction.estimate`][] (batched with the other loops of its
    length bucket) and [`jaxstiction.verdict`][]: `stiction_detected` when Kano's
    valve beats a linear valve on held-out data, `slip_identified` when its slip
    jump is seen, and a `cause` (`stiction`, `external_oscillation`, `none`; with
    `diagnose`, the diagnosis verdict of a loop not called sticky). A loop that cannot be read or fitted
    gets `status` with a one-line error; the others are unaffected.

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
    - `diagnose`: name the cause of the loops not called sticky by the full
      diagnosis (`diagnose_causes`).

    **Returns:** a [`jaxstiction.ScreenReport`][].

    **Raises:** `ValueError` when a path does not exist or a folder has no loop files.
    """
    from ._loop import decimation_factor

    decimate = decimation_factor(decimate)  # a bad factor fails before any file is read
    items, errors, warned = read_items(paths, ts=ts, settings=settings, recursive=recursive, decimate=decimate)
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
    return ScreenReport(loops=rank(errors + results))


def write_screen_outputs(report: ScreenReport, out_dir: str | os.PathLike) -> list[Path]:
    """Write `summary.csv`, one picture per loop (`loops/NAME.png`) and a static
    `report.html` (ranked loops with verdict, band and thumbnails) into `out_dir`."""
    from ._plots import write_screen_loop_figure
    from ._screen_html import write_html, write_summary_csv

    out = Path(out_dir)
    (out / "loops").mkdir(parents=True, exist_ok=True)
    written = [write_summary_csv(report.loops, out / "summary.csv")]
    for r in report.loops:
        if "figure" in r:
            r["picture"] = f"loops/{_safe(r['name'])}.png"
            written.append(write_screen_loop_figure(r, out / r["picture"]))
    written.append(write_html(report, out / "report.html"))
    return written


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
