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
    """`fn(*args)` exported on the flat list of its arguments' arrays, and the skeleton
    that rebuilds its result."""
    leaves = arrays(args)
    out = {}

    def flat(*lv):
        result = fn(*rebuild(skeleton, lv))
        out["skeleton"] = shapes(result)
        return arrays(result)

    exported = jax.export.export(jax.jit(flat))(*[jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves])
    return exported, out["skeleton"]


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
    with _lock:  # the screen runs chunks on several threads
        hit = _loaded.get(key)
        if hit is not None:
            _loaded.move_to_end(key)
    if hit is None:
        path = None if _where is None else _where / f"{name}-{key}.jaxexport"
        entry = None
        if path is not None and path.exists():
            try:
                entry = _load(path)
            except Exception:  # stale or corrupt: rebuilt below
                entry = None
        if entry is None:
            try:
                entry = _export(fn, args, skeleton)
            except Exception:  # e.g. an unexportable JAX build: no speed-up, same answer
                return fn(*args)
            if path is not None:
                try:
                    _save(path, *entry)
                except Exception:  # e.g. a read-only folder or no `flatbuffers`: not saved
                    pass
        exported, out_skeleton = entry
        hit = (jax.jit(exported.call), out_skeleton)
        with _lock:
            _loaded[key] = hit
            while len(_loaded) > _KEEP:  # the least recently used goes
                _loaded.popitem(last=False)
    runner, out_skeleton = hit
    return rebuild(out_skeleton, runner(*arrays(args)))
