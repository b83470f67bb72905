r"""Fleet screening in batches: many loops through one batched, jitted estimate and verdict.

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
import functools
import itertools
import math
import threading
from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np

from .._checks import error_line
from .._estimate.estimate import estimate
from .._estimate.report import report
from .._estimate.result import delay_note, held_out_note, KINDS, RESULTS
from .._estimate.settings import Settings
from .._loop import bucket_length, Loop, make_loop, stack
from .._misc import json_number as _r, release_programs_near_map_limit, thread_map
from .._programs import exported_call
from .._verdict.gate import gate_reason, GATES
from .._verdict.settings import VerdictSettings
from .._verdict.verdict import CAUSES, FEATURES, runaway, usable, verdict, verdict_reason, VERDICTS
from .settings import ScreenSettings


# Bytes of device memory one loop-sample of the screen's batched estimate holds at its
# peak (the verdict, a separate call, needs less): XLA's memory analysis of the
# compiled call on a CPU, 1500-sample loops, 197 MB of temporaries for one loop and
# 637 MB for four, so (637 - 197) / 3 / 1500 = 98 kB per loop-sample (the Kano
# search's two polish starts hold twice the final Box-Jenkins fits of one: 100 and
# 325 MB, 50 kB, with one).
SCREEN_BYTES_PER_SAMPLE = 98_000
CPU_CHUNK, CPU_SAMPLES_PER_CALL = 2, 8000
MAX_CHUNK = 1024


def auto_batch(length: int, device=None) -> tuple[int, int]:
    """`(chunk, samples_per_call)` for a bucket of `length` samples on `device`
    (default: the first local JAX device): on a CPU, `CPU_CHUNK` loops and
    `CPU_SAMPLES_PER_CALL` samples; on an accelerator, as many loops as a quarter of
    its memory holds at `SCREEN_BYTES_PER_SAMPLE` bytes per loop-sample (16 GB taken
    when the device does not say), between 1 and `MAX_CHUNK`."""
    device = device or jax.local_devices()[0]
    if device.platform == "cpu":
        return CPU_CHUNK, CPU_SAMPLES_PER_CALL
    try:
        memory = int((device.memory_stats() or {}).get("bytes_limit", 0)) or 16 * 2**30
    except Exception:  # noqa: BLE001 - a backend without memory statistics
        memory = 16 * 2**30
    chunk = int(min(MAX_CHUNK, max(1, memory // 4 // (SCREEN_BYTES_PER_SAMPLE * max(length, 1)))))
    return chunk, chunk * max(length, 1)


def chunk_size(length: int, settings: ScreenSettings) -> int:
    """Loops per batched call for a bucket of `length` samples: `settings.chunk`
    when it is given (cut by `samples_per_call` only when that is given too), else
    `auto_batch`'s."""
    chunk, budget = settings.chunk, settings.samples_per_call
    if not chunk:
        chunk, auto_budget = auto_batch(length)
        budget = budget or auto_budget
    if not budget:
        return chunk
    return max(1, min(chunk, budget // max(length, 1)))


@eqx.filter_jit
def _verdicts(fits, loops: Loop, vset: VerdictSettings):
    return eqx.filter_vmap(lambda f, lp: verdict(f, lp, vset))(fits, loops)


def _batch(loops: Loop, settings: Settings, vset: VerdictSettings):
    # `filter_vmap` of the jitted `estimate` (the documented batched contract): its
    # compiled batch is shared with any other such call of the same shapes (the
    # setpoint is the verdict's alone, so `estimate` sees loops without it).
    fits = eqx.filter_vmap(lambda lp: estimate(lp, settings))(dataclasses.replace(loops, sp=None))
    return fits, _verdicts(fits, loops, vset)


def _record(name, file, op, pv, ts, fit, ver, settings: Settings, pictures: bool,
            vset: VerdictSettings = VerdictSettings()) -> dict:
    """One loop's screen entry (JSON-ready, plus a `figure` of NumPy arrays when
    `pictures`) from its unbatched host-side fit and verdict."""
    converged = bool(fit.result == RESULTS.successful)
    ok = bool(usable(fit.result))
    ran_away = bool(runaway(fit, vset))
    cause = CAUSES[int(ver.cause)]
    notes = [RESULTS[fit.result] if not converged else "", delay_note(fit.delay, fit.kind, settings) if ok else "",
             held_out_note(fit.fitness, fit.fitness_estimation, fit.n_validation) if ok and not ran_away else "",
             "the fitted models' simulation runs away (an unstable fit): the verdict rests on the indicators, the "
             "cross-validation and the band" if ok and ran_away else "",
             (f"the Kano valve leaves the linear fit's oscillation (period {float(ver.period):.0f} samples) in "
              "its residual: a disturbance from elsewhere, not the valve's cycle") if ok and bool(ver.line_persists)
             else ""]
    ind, g, lc = ver.indicators, ver.gate_measures, ver.limit_cycle

    def sim(v):
        # a simulation that ran away: its fitness is rounding (1e30 at one chunk size,
        # an overflow at another), and so is any evidence that compares it, so both
        # are reported as null, as an overflow is
        return _r(v) if abs(float(v)) <= -vset.runaway_fitness else None

    def gain(v):
        return None if ran_away else sim(v)

    gate = GATES[int(ver.gate)]
    reason = verdict_reason(ver, vset)
    which = VERDICTS[int(ver.verdict)]
    if not ok:
        reason = RESULTS[fit.result]
    elif which == "stiction" and reason and float(ver.probability) < vset.threshold:
        notes.append(f"called sticky by the model-based test although {reason}: the Kano model simulates the "
                     f"held-out PV with a fitness of {float(fit.fitness_physical):.0f} % and beats the linear valve "
                     f"(probability {float(ver.probability):.2f})")
    elif which == "stiction" and reason:
        notes.append(f"called sticky although {reason}")
    rec = {
        "name": name,
        "file": file,
        "status": "ok" if ok else RESULTS[fit.result],
        "converged": converged,
        "note": "; ".join(n for n in notes if n),
        "samples": int(op.shape[0]),
        "Ts": float(ts),
        "verdict": which,
        "stiction_detected": bool(ver.stiction_detected),
        "stiction_probability": _r(ver.probability),
        "gate": gate,
        "reason": reason if which == "inconclusive" else "",
        "cause": cause if ok else None,
        "band_seen": bool(ver.stiction_detected),
        "slip_identified": bool(ver.slip_identified) if ok else None,
        "model_wins": bool(ver.model_wins),
        "indicators": {"period_samples": _r(ind.period, 1), "regularity": _r(ind.regularity),
                       "oscillation_share": _r(ind.share), "periods": _r(ind.periods, 1), "horch": _r(ind.horch),
                       "shape_op": _r(ind.shape_op), "shape_pv": _r(ind.shape_pv), "ngi": _r(ind.ngi, 4),
                       "nli": _r(ind.nli, 4), "stuck_pv": _r(ind.stuck_pv), "stuck_dpv": _r(ind.stuck_dpv)},
        "crossval": [_r(v, 2) for v in np.asarray(ver.crossval)],
        "features": {k: _r(v, 4) for k, v in zip(FEATURES, np.asarray(ver.features))},
        "limit_cycle": {"reproduction": _r(lc.reproduction), "amplitude_recorded": _r(lc.amplitude_recorded, 6),
                        "period_recorded": _r(lc.period_recorded, 1), "amplitude_kano": _r(lc.amplitude_kano, 6),
                        "period_kano": _r(lc.period_kano, 1), "amplitude_repaired": _r(lc.amplitude_repaired, 6),
                        "period_repaired": _r(lc.period_repaired, 1), "controller_fit": _r(lc.controller_fit),
                        "stable": bool(lc.stable)},
        "gate_measures": {"saturated": _r(g.saturated), "compressed": _r(g.compressed),
                          "longest_flat": _r(g.longest_flat), "setpoint_share": _r(g.setpoint_share)},
        # the Kano fit's band, which the verdict judges, whichever family `estimate`
        # chose (the linear valve's band is 0)
        "band_percent": _r(fit.S if math.isfinite(float(fit.S)) else fit.band_percent),
        "fitness": sim(fit.fitness),
        "S": _r(fit.S),
        "J": _r(fit.J),
        "evidence": gain(ver.evidence),
        "evidence_estimation": gain(ver.evidence_estimation),
        "evidence_prediction": gain(ver.evidence_prediction),
        "evidence_prediction_estimation": gain(ver.evidence_prediction_estimation),
        "slip_evidence": gain(ver.slip_evidence),
        "slip_evidence_estimation": gain(ver.slip_evidence_estimation),
        "band_fraction": _r(ver.band_fraction, 4),
        "fitness_kano": sim(fit.fitness_physical),
        "fitness_linear": sim(fit.fitness_linear),
        "fitness_deadband": sim(fit.fitness_deadband),
        "oscillation": _r(ver.oscillation),
        "period_samples": _r(ver.period, 1),
        "oscillation_kano": _r(ver.oscillation_kano),
        "model": KINDS[int(fit.kind)],
        "delay": int(fit.delay),
    }
    if pictures and ok and math.isfinite(float(fit.fitness_physical)):
        jfit = jax.tree.map(jax.numpy.asarray, fit)
        r = report(jfit, op, pv, name=name, ts=ts, settings=settings)
        rec["figure"] = dict(op=r.op, pv=r.pv, pv_sim=r.pv_sim, valve_u=r.valve_u, valve_up=r.valve_up,
                             valve_down=r.valve_down, n_estimation=r.n_estimation, kind=r.model_kind)
    return rec


def run_chunk(items: Sequence[tuple], length: int, size: int, settings: ScreenSettings = ScreenSettings(),
              *, pictures: bool = False, enable_x64: bool = False, device=None, release: bool = False) -> list[dict]:
    """Fit one chunk of loops in one batched call and return their entries.

    `items`: `(name, file, op, pv, ts)` tuples (NumPy arrays, already checked),
    padded to `length` samples and, with repeats of the first loop that are then
    dropped, to `size` loops, so every chunk of a bucket has one shape. A top-level
    function of plain arguments, so a Dask worker can run it; `enable_x64` turns on
    float64 in that worker (the application's choice, as the CLI's), and `release`
    first releases the worker's compiled programs when they hold more than half the
    kernel's memory-map limit (`release_programs_near_map_limit`): a long-lived
    worker that meets many length buckets would otherwise exhaust the maps and
    abort. Clearing drops the caches' references only; a program running on another
    of the worker's threads holds its own.
    """
    if enable_x64:
        jax.config.update("jax_enable_x64", True)
    if release:
        release_programs_near_map_limit()
    items = list(items)
    loops = [make_loop(it[2], it[3], it[4], sp=setpoint_of(it)) for it in items]
    loops += [loops[0]] * (size - len(loops))
    try:
        batch = stack(loops, length)
        if device is not None:
            batch = jax.device_put(batch, device)
        # from its exported program: a new process loads it instead of tracing it again
        fits, vers = exported_call("screen", functools.partial(_batch, settings=settings.estimate,
                                                                vset=settings.verdict),
                                   batch, static=repr(settings.estimate) + repr(settings.verdict))
        fits, vers = jax.tree.map(np.asarray, (fits, vers))
    except Exception as e:  # noqa: BLE001 - an XLA failure must cost only its own loops
        if len(items) > 1:
            out = []
            for it in items:
                out += run_chunk([it], length, 1, settings, pictures=pictures)
            return out
        name, file, op, pv, ts = items[0][:5]
        return [_error(name, file, f"fit failed: {error_line(e, 300)}", op.shape[0], ts)]
    out = []
    for i, it in enumerate(items):
        name, file, op, pv, ts = it[:5]
        fit, ver = jax.tree.map(lambda x: np.asarray(x[i]), (fits, vers))
        try:
            out.append(_record(name, file, op, pv, ts, fit, ver, settings.estimate, pictures, settings.verdict))
        except Exception as e:  # noqa: BLE001
            out.append(_error(name, file, f"report failed: {error_line(e, 300)}", op.shape[0], ts))
    if settings.whatif is not None:  # `screen --whatif`: see `whatif.add_whatif`
        from .whatif import add_whatif

        add_whatif(out, fits, batch, settings.whatif, pictures)
    return out


def setpoint_of(item: tuple):
    """The setpoint of a screen item `(name, file, op, pv, ts[, sp])`, or `None`."""
    return item[5] if len(item) > 5 else None


def _error(name, file, message, samples=None, ts=None) -> dict:
    """The entry of a loop that could not be judged: its `status` is the one-line
    reason, and so is the `inconclusive` verdict's `reason`."""
    gate = "frozen_sensor" if "is constant" in message and "`PV`" in message else "data_error"
    return {"name": name, "file": file, "status": message, "samples": samples, "Ts": ts,
            "verdict": "inconclusive", "stiction_detected": False, "stiction_probability": None, "gate": gate,
            "reason": (f"{gate_reason(GATES.index('frozen_sensor'))} ({message})" if gate == "frozen_sensor"
                       else message),
            "cause": None, "band_percent": None, "fitness": None}


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
    # program once), the others `settings.threads` at a time. Each bucket's programs
    # (the fit, the verdict, with `whatif` its replays: ~7000 memory maps) stay in
    # memory; past half the kernel's map limit they are released between buckets,
    # or a fleet of many record lengths aborts in LLVM ("Cannot allocate memory")
    out = []
    for k, (_, bucket) in enumerate(itertools.groupby(enumerate(chunks), key=lambda kc: kc[1][:2])):
        if k:
            release_programs_near_map_limit()
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
                                 release=True, pure=False): members for length, size, members in chunks}
        out = []
        for fut in as_completed(futures):
            members = futures[fut]
            try:
                out += fut.result()
            except Exception as e:  # noqa: BLE001 - a lost worker costs only its chunk
                out += [_error(m[0], m[1], f"task failed: {error_line(e, 300)}", m[2].shape[0], m[4])
                        for m in members]
            if progress is not None:
                progress(len(members))
        return out
