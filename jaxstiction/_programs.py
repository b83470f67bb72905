"""Exported programs on disk, so that a new process need not trace them again.

JAX's persistent compilation cache (which the command line turns on) skips XLA's
compilation, but a new process still traces and lowers a program first: 9.2–9.7 s for
the screen's what-if of a 751-sample loop on a 2-core CPU, against 1.9 s to load it
from the compilation cache. `exported_call` keeps such a program, exported with
`jax.export` for one set of argument shapes, in the folder the application named
(`use_folder`; the command line names one next to its compilation cache); a later
process deserialises it (milliseconds) and the compilation cache supplies the
compiled program. Without a folder the exported programs are kept in memory only.

An entry is keyed by the package's own source, the JAX and jaxlib versions, the
float64 switch, the program's name and what the caller says its function closes over
(`static`), and the structure, static parts and shapes of its arguments; anything
that fails to load is rebuilt, and anything that fails to export runs as the plain
jitted function: a missed speed-up, never another answer.

`jaxstiction._estimate.programs` keeps `estimate` this way, in four programs run
side by side; it uses the helpers here.
"""

from __future__ import annotations

import collections
import functools
import hashlib
import os
import pathlib
import pickle
import tempfile
import threading

import equinox as eqx
import jax


_where: pathlib.Path | None = None
_loaded: collections.OrderedDict = collections.OrderedDict()  # key -> (runner, skeleton), most recent last
_lock = threading.Lock()
_KEEP = 4  # programs kept in memory: a process running many shapes must not grow without bound


def use_folder(path: str | os.PathLike | None):
    """Keep exported programs in folder `path` (`None`: in memory only)."""
    global _where
    _where = None if path is None else pathlib.Path(path)


def folder() -> pathlib.Path | None:
    """The folder `use_folder` named, if any."""
    return _where


@functools.cache
def source_hash(exclude: tuple[str, ...] = ()) -> str:
    """A hash of every source file of the package, its subpackages' too, but those
    in `exclude` (paths relative to the package, e.g. `"_verdict/calibration.py"`)."""
    package = pathlib.Path(__file__).parent
    h = hashlib.sha256()
    for f in sorted(package.rglob("*.py")):
        if f.relative_to(package).as_posix() in exclude:
            continue
        h.update(f.relative_to(package).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def is_struct(x) -> bool:
    return isinstance(x, jax.ShapeDtypeStruct)


def shapes(tree):
    """`tree` with its arrays replaced by their shapes (the rest kept)."""
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype) if eqx.is_array(x) else x, tree)


def arrays(tree) -> list:
    """The arrays of `tree`, in its leaves' order."""
    return jax.tree.leaves(eqx.filter(tree, eqx.is_array))


def rebuild(skeleton, leaves):
    """The tree of `skeleton` (from `shapes`) with `leaves` for its arrays."""
    dynamic, static = eqx.partition(skeleton, is_struct, is_leaf=is_struct)
    return eqx.combine(jax.tree.unflatten(jax.tree.structure(dynamic, is_leaf=is_struct), leaves), static)


def versions() -> list[str]:
    """What a compiled program depends on besides its own inputs."""
    import jaxlib

    return [source_hash(), jax.__version__, jaxlib.__version__, str(jax.config.jax_enable_x64)]


def _export(fn, args, skeleton):
    """`((exported,), skeleton)`: `fn(*args)` exported on the flat list of its
    arguments' arrays, and the skeleton that rebuilds its result."""
    leaves = arrays(args)
    out = {}

    def flat(*lv):
        result = fn(*rebuild(skeleton, lv))
        out["skeleton"] = shapes(result)
        return arrays(result)

    exported = jax.export.export(jax.jit(flat))(*[jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves])
    return (exported,), out["skeleton"]


def _save(path: pathlib.Path, programs, skeleton):
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = pickle.dumps(([None if e is None else bytes(e.serialize()) for e in programs], skeleton))
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "wb") as f:
        f.write(blob)
    os.replace(tmp, path)


def _load(path: pathlib.Path):
    blobs, skeleton = pickle.loads(path.read_bytes())
    return tuple(None if b is None else jax.export.deserialize(bytearray(b)) for b in blobs), skeleton


def recall(table: collections.OrderedDict, key: str):
    """`table[key]`, marked most recently used, or `None`."""
    with _lock:  # the screen runs chunks, and `fit` callers loops, on several threads
        hit = table.get(key)
        if hit is not None:
            table.move_to_end(key)
    return hit


def remember(table: collections.OrderedDict, key: str, value, keep: int):
    """`table[key] = value`, keeping only the `keep` most recently used entries."""
    with _lock:
        table[key] = value
        while len(table) > keep:  # the least recently used goes
            table.popitem(last=False)


def load_or_export(filename: str, export):
    """`(programs, skeleton)`: read from `filename` in the `use_folder` folder when it
    is there and loads, else `export()` (a tuple of `jax.export.Exported`, or `None`
    for a program not needed, and what rebuilds the results), saved there when a
    folder is named. A file that fails to load is rebuilt; one that fails to save is
    only a missed speed-up. An error of `export()` reaches the caller, whose plain
    call then gives the same answer."""
    path = None if _where is None else _where / filename
    if path is not None and path.exists():
        try:
            return _load(path)
        except Exception:  # stale or corrupt: rebuilt below
            pass
    entry = export()
    if path is not None:
        try:
            _save(path, *entry)
        except Exception:  # e.g. a read-only folder or no `flatbuffers`: not saved
            pass
    return entry


def exported_call(name: str, fn, *args, static: str = ""):
    """`fn(*args)`, run from `fn` exported for these argument shapes (see the module
    notes). `fn` is pure and jitted; `static` names everything it closes over (e.g.
    `repr(settings)`). The same result as `fn(*args)`."""
    skeleton = shapes(args)
    parts = versions() + [name, static, str(jax.tree.structure(skeleton, is_leaf=is_struct)),
                          repr(eqx.filter(skeleton, is_struct, inverse=True, is_leaf=is_struct)),
                          repr([(x.shape, str(x.dtype)) for x in jax.tree.leaves(skeleton, is_leaf=is_struct)
                                if is_struct(x)])]
    key = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]
    hit = recall(_loaded, key)
    if hit is None:
        try:
            (exported,), out_skeleton = load_or_export(f"{name}-{key}.jaxexport", lambda: _export(fn, args, skeleton))
        except Exception:  # e.g. an unexportable JAX build: no speed-up, same answer
            return fn(*args)
        hit = (jax.jit(exported.call), out_skeleton)
        remember(_loaded, key, hit, _KEEP)
    runner, out_skeleton = hit
    return rebuild(out_skeleton, runner(*arrays(args)))
