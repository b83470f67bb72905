"""Exported `estimate` programs on disk, so a new process need not trace it again.

JAX's persistent compilation cache (which the command line turns on) skips XLA's
compilation, but a new process still traces and lowers `estimate` first: ~4.5 s of a
CHEM23 fit. The command line therefore also keeps `estimate`, exported with
`jax.export` for one record shape and one `Settings`, next to that cache. A later
process deserialises it (milliseconds) and the compilation cache supplies the
compiled program. The program also simulates the chosen and the paper's model over
the whole record (what [`jaxstiction.fit`][]'s report shows): traced apart, those
two simulations cost another ~2 s of a new process.

An entry is keyed by the package's own source, the JAX and jaxlib versions, the
float64 switch, the settings and the record's shape; anything that fails to load is
rebuilt, and anything that fails to save is only a missed speed-up. The library's
`estimate` never touches the disk: only [`jaxstiction.fit`][] uses this, and only
when the application has called `use_program_cache`.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
import pickle
import tempfile

import equinox as eqx
import jax
import jax.numpy as jnp

from ._criteria import simulate_scored
from ._estimate import _estimate, estimate, estimation_parts, LoopFit, Settings
from ._loop import Loop
from ._misc import release_freed_memory


_where: pathlib.Path | None = None
_loaded: dict = {}  # key -> (jitted call, skeleton), for later calls in this process


def use_program_cache(path: str | os.PathLike | None):
    """Keep exported `estimate` programs in folder `path` (`None`: do not)."""
    global _where
    _where = None if path is None else pathlib.Path(path)


@functools.cache
def _source_hash() -> str:
    h = hashlib.sha256()
    for f in sorted(pathlib.Path(__file__).parent.glob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def _key(loop: Loop, settings: Settings) -> str:
    import jaxlib

    parts = [_source_hash(), jax.__version__, jaxlib.__version__, str(jax.config.jax_enable_x64), repr(settings)]
    parts += [f"{jnp.shape(x)}{jnp.result_type(x)}" for x in (loop.op, loop.pv, loop.mask, loop.ts)]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]


def _is_struct(x):
    return isinstance(x, jax.ShapeDtypeStruct)


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


def _fit_and_simulate(loop: Loop, settings: Settings):
    fit = _estimate(loop, settings)
    return fit, simulations_of(fit, loop.op, loop.pv, loop.mask, settings.score)


def _export(loop: Loop, settings: Settings):
    skeleton = {}

    def flat(op, pv, mask, ts):
        out = _fit_and_simulate(Loop(op=op, pv=pv, mask=mask, ts=ts), settings)
        skeleton["fit"] = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype) if eqx.is_array(x) else x, out)
        return jax.tree.leaves(eqx.filter(out, eqx.is_array))

    args = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in (loop.op, loop.pv, loop.mask, loop.ts)]
    exported = jax.export.export(jax.jit(flat))(*args)
    return exported, skeleton["fit"]


def _call(call, skeleton, loop: Loop) -> tuple[LoopFit, tuple]:
    leaves = call(loop.op, loop.pv, loop.mask, loop.ts)
    dynamic, static = eqx.partition(skeleton, _is_struct, is_leaf=_is_struct)
    return eqx.combine(jax.tree.unflatten(jax.tree.structure(dynamic, is_leaf=_is_struct), leaves), static)


def _save(path: pathlib.Path, exported, skeleton):
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = pickle.dumps((bytes(exported.serialize()), skeleton))
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "wb") as f:
        f.write(blob)
    os.replace(tmp, path)


def _load(path: pathlib.Path):
    blob, skeleton = pickle.loads(path.read_bytes())
    return jax.export.deserialize(bytearray(blob)), skeleton


def estimate_cached(loop: Loop, settings: Settings = Settings()) -> tuple[LoopFit, tuple | None]:
    """`(fit, simulations)`: [`jaxstiction.estimate`][] and the simulations of its
    chosen and its paper's model over the whole record (`simulate_scored`), from an
    exported program on disk when the application has enabled the cache (see the
    module docstring); the same results. Without the cache, `simulations` is `None`."""
    if _where is None:
        return estimate(loop, settings), None
    key = _key(loop, settings)
    if key in _loaded:
        return _call(*_loaded[key], loop)
    path = _where / f"estimate-{key}.jaxexport"
    entry = None
    if path.exists():
        try:
            entry = _load(path)
        except Exception:  # stale or corrupt: rebuilt below
            entry = None
    if entry is None:
        try:
            entry = _export(loop, settings)
        except Exception:  # e.g. an unexportable JAX build: no speed-up, same answer
            return estimate(loop, settings), None
        try:
            _save(path, *entry)
        except Exception:  # e.g. a read-only cache or no `flatbuffers`: not saved
            pass
    exported, skeleton = entry
    # compiled apart from the run, so that what the compiler freed can be handed
    # back before the run's buffers are allocated (see `release_freed_memory`)
    compiled = jax.jit(exported.call).lower(loop.op, loop.pv, loop.mask, loop.ts).compile()
    release_freed_memory()
    _loaded[key] = (compiled, skeleton)
    return _call(*_loaded[key], loop)
