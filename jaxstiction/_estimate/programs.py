"""Exported `estimate` programs on disk, so a new process need not trace it again.

JAX's persistent compilation cache (which the command line turns on) skips XLA's
compilation, but a new process still traces and lowers `estimate` first: ~4.5 s of a
CHEM23 fit. The command line therefore also keeps `estimate`, exported with
`jax.export` for one record shape and one `Settings`, next to that cache. A later
process deserialises it (milliseconds) and the compilation cache supplies the
compiled program. The program also simulates the chosen and the paper's model over
the whole record (what [`jaxstiction.fit`][]'s report shows): traced apart, those
two simulations cost another ~2 s of a new process.

`estimate` is exported as four programs (the prepared record, the spline stage,
the physical stage, the rest), and the two stages, which need only the prepared
record, run at once on two threads: XLA's CPU backend runs one program's
independent work one piece at a time, so a single program keeps one core busy.
The four are also read from the cache two at a time. A second `jaxstiction fit
CHEM23.csv` took 15.2-16.6 s with one program and 10.1-10.8 s with four on the same
day (the same JSON; peak memory 0.89 and 0.80 GB).

An entry is keyed by the package's own source, the JAX and jaxlib versions, the
float64 switch, the settings and the record's shape; anything that fails to load is
rebuilt, and anything that fails to save is only a missed speed-up. The library's
`estimate` never touches the disk: only [`jaxstiction.fit`][] uses this, and it
writes to disk only when the application has called `use_program_cache`. Without
it the four programs are kept in memory (for the four record shapes and settings
used last), so API calls of `fit` also run the two stages side by side (`fit` of
CHEM23 in one process, one run each: first call 38.4 → 32.5 s, later calls
6.9-8.1 → 6.2-6.3 s, peak memory 0.98 → 0.87 GB; the same JSON).
"""

from __future__ import annotations

import collections
import hashlib
import os
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp

from .._criteria import simulate_scored
from .._loop import Loop
from .._misc import release_freed_memory
from .._programs import (
    arrays as _arrays,
    is_struct as _is_struct,
    load_or_export,
    rebuild as _rebuild,
    recall,
    remember,
    shapes as _shapes,
    use_folder,
    versions,
)
from .estimate import _finish, _physical_stage, _prepare, _spline_stage, estimate, estimation_parts
from .result import LoopFit
from .settings import Settings


_loaded: collections.OrderedDict = collections.OrderedDict()  # key -> (compiled, skeletons), most recent last
_KEEP = 4  # programs kept in memory: a process fitting many record lengths must not grow without bound


def use_program_cache(path: str | os.PathLike | None):
    """Keep exported `estimate` programs, and the other programs `exported_call`
    keeps, in folder `path` (`None`: do not)."""
    use_folder(path)


def _key(loop: Loop, settings: Settings) -> str:
    parts = versions() + [repr(settings)]
    parts += [f"{jnp.shape(x)}{jnp.result_type(x)}" for x in (loop.op, loop.pv, loop.mask, loop.ts)]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]


@eqx.filter_jit  # one compiled call (cached across processes) rather than op-by-op dispatch
def simulations_of(fit: LoopFit, op, pv, weights, score):
    """The chosen and the paper's model of `fit` simulated over the record (real
    samples marked by `weights`), as the report shows them: exactly what was scored.
    The estimation part is simulated from an initial state estimated on its opening
    samples; a held-out part restarts from one estimated on its own opening samples
    (`simulate_scored` with `score`, as the fitness was computed)."""
    w_est, w_val = estimation_parts(weights, fit.n_estimation, fit.n_validation)

    def shown(m):
        whole = simulate_scored(m, op, pv, w_est, score)[0]
        # nothing held out: nothing to restart (and no second simulation to run)
        return jax.lax.cond(
            fit.n_validation > 0,
            lambda: jnp.where(w_val > 0, simulate_scored(m, op, pv, w_val, score)[0], whole),
            lambda: whole,
        )

    return tuple(shown(m) for m in (fit.model, fit.paper))


def _export(loop: Loop, settings: Settings):
    """`estimate` and the report's simulations as four exported programs on flat
    lists of arrays: the prepared record (`_prepare`), the spline stage, the
    physical stage (`None` without the physical family) and the rest (`_finish`,
    then `simulations_of`); with the skeletons that rebuild their results. The two
    stages depend only on the prepared record, so `_run` runs them side by side
    (`estimate` itself orders them in its one program: see its barrier)."""
    sk = {}
    record = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in (loop.op, loop.pv, loop.mask, loop.ts)]

    def export(name, fn, args):
        def flat(*leaves):
            out = fn(*leaves)
            sk[name] = _shapes(out)
            return _arrays(out)

        exported = jax.export.export(jax.jit(flat))(*args)
        return exported, [leaf for leaf in jax.tree.leaves(sk[name], is_leaf=_is_struct) if _is_struct(leaf)]

    def prepare(op, pv, mask, ts):
        return _prepare(Loop(op=op, pv=pv, mask=mask, ts=ts), settings)

    e_prep, p_args = export("prepared", prepare, record)
    e_spline, c_args = export("spline", lambda *p: _spline_stage(_rebuild(sk["prepared"], p), settings), p_args)
    e_phys, h_args = None, []
    if settings.use_physical:
        e_phys, h_args = export("physical", lambda *p: _physical_stage(_rebuild(sk["prepared"], p), settings), p_args)
    n_p, n_c = len(p_args), len(c_args)

    def finish(op, pv, mask, ts, *rest):
        p = _rebuild(sk["prepared"], rest[:n_p])
        cand = _rebuild(sk["spline"], rest[n_p:n_p + n_c])
        phys = _rebuild(sk["physical"], rest[n_p + n_c:]) if settings.use_physical else None
        fit = _finish(p, cand, phys, settings)
        return fit, simulations_of(fit, op, pv, mask, settings.score)

    e_finish, _ = export("finish", finish, record + p_args + c_args + h_args)
    return (e_prep, e_spline, e_phys, e_finish), sk


def _compiled(programs):
    """The exported programs compiled (read from XLA's cache when it holds them),
    two at a time."""
    def compile_(exported):
        if exported is None:
            return None
        args = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals]
        return jax.jit(exported.call).lower(*args).compile()

    with ThreadPoolExecutor(2) as pool:
        return tuple(pool.map(compile_, programs))


def _run(compiled, sk, loop: Loop) -> tuple[LoopFit, tuple]:
    """`estimate` and the report's simulations from the compiled programs, the spline
    and the physical stage at once: XLA runs one program's independent work one
    piece at a time on this CPU backend, so `estimate` leaves a core idle."""
    c_prep, c_spline, c_phys, c_finish = compiled
    record = (loop.op, loop.pv, loop.mask, loop.ts)
    p = c_prep(*record)
    with ThreadPoolExecutor(2) as pool:
        stages = [pool.submit(lambda c=c: jax.block_until_ready(c(*p))) for c in (c_spline, c_phys) if c is not None]
        cand, *phys = (f.result() for f in stages)
    return _rebuild(sk["finish"], c_finish(*record, *p, *cand, *(phys[0] if phys else [])))


def estimate_cached(loop: Loop, settings: Settings = Settings()) -> tuple[LoopFit, tuple | None]:
    """`(fit, simulations)`: [`jaxstiction.estimate`][] and the simulations of its
    chosen and its paper's model over the whole record (`simulate_scored`), from the
    four exported programs (see the module docstring), read from and saved to disk
    when the application has enabled the cache; the same results. Where JAX cannot
    export them, `estimate` itself and no `simulations` (`None`)."""
    key = _key(loop, settings)
    hit = recall(_loaded, key)
    if hit is not None:
        return _run(*hit, loop)
    try:
        entry = load_or_export(f"estimate-{key}.jaxexport", lambda: _export(loop, settings))
    except Exception:  # e.g. an unexportable JAX build: no speed-up, same answer
        return estimate(loop, settings), None
    programs, skeletons = entry
    # compiled apart from the run, so that what the compiler freed can be handed
    # back before the run's buffers are allocated (see `release_freed_memory`)
    compiled = _compiled(programs)
    release_freed_memory()
    remember(_loaded, key, (compiled, skeletons), _KEEP)
    return _run(compiled, skeletons, loop)
