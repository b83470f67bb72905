"""The cause of every fitted loop that the screen does not call sticky, from the full
diagnosis (`screen --diagnose`): in this process, or one Dask task per loop."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

from .._checks import error_line
from .._diagnose.diagnose import diagnose
from .._diagnose.settings import DiagnoseSettings
from .._loop import make_loop
from .._misc import release_freed_memory
from .batch import _dask_client


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
        return _noted(r, "diagnose names stiction, which the screen's verdict did not; cause from the screen")
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
    `accepted`). A diagnosis that names stiction where the screen's verdict did not
    leaves the screen's cause and says so in the `note`; a diagnosis that fails
    (or whose Dask task is lost) leaves it too, with the one-line error in the `note`.

    `results`: entries of `screen_loops`; `items`: the `(name, file, op, pv, ts)`
    tuples they came from; `settings`: `DiagnoseSettings`; `progress`: called with 1
    after each diagnosis; `scheduler`: a Dask scheduler address or
    `dask.distributed.Client`, to run one task per loop on the cluster. Returns new
    entries, in the same order."""
    settings = DiagnoseSettings() if settings is None else settings
    by_name = {it[0]: it for it in items}
    out = list(results)
    todo = [i for i, r in enumerate(out) if _to_diagnose(r) and r["name"] in by_name]
    todo.sort(key=lambda i: by_name[out[i]["name"]][2].shape[0])  # see `diagnose_entry`
    if scheduler is None:
        for i in todo:
            _, _, op, pv, ts = by_name[out[i]["name"]][:5]
            out[i] = diagnose_entry(out[i], op, pv, ts, settings)
            if progress is not None:
                progress(1)
        return out
    x64 = bool(jax.config.jax_enable_x64)
    with _dask_client(scheduler) as (client, as_completed):
        futures = {client.submit(diagnose_entry, out[i], *by_name[out[i]["name"]][2:5], settings, enable_x64=x64,
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
