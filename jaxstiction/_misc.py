"""Small shared helpers with no better home."""

import math
import os
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp


def json_number(v, nd: int = 3):
    """`v` as a JSON number rounded to `nd` decimals; `None` for `None`, NaN or inf."""
    if v is None:
        return None
    v = float(v)
    return round(v, nd) if math.isfinite(v) else None


def warn_without_float64(caller: str, why: str) -> None:
    """Warn when JAX runs in float32, as from the user's line that led to host API
    `caller` (the first frame outside the package: `valve_trend` calls `fit`, the
    screen's cause diagnosis `diagnose`); `why` says what float32 changes there.
    The library never turns float64 on itself."""
    if not jax.config.jax_enable_x64:
        warnings.warn(f"jaxstiction.{caller} runs in float32 (jax_enable_x64 is off), but {why}. Call "
                      "jax.config.update('jax_enable_x64', True) before creating any array.", UserWarning,
                      stacklevel=_levels_inside_package() + 1)


def _levels_inside_package() -> int:
    """How many frames, from its caller outwards, run this package's code."""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, levels = sys._getframe(1), 0
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, levels = frame.f_back, levels + 1
    return levels


def release_freed_memory() -> bool:
    """Hand the memory that this process has freed back to the operating system
    (glibc's `malloc_trim`); returns whether it could. A no-op where there is no glibc.

    XLA's compiler frees what it used when it is done, but glibc keeps those pages
    in the process, and the compiled program's buffers are then mapped on top of
    them, so a long record's peak is the compilation's memory plus the run's:
    `jaxstiction fit PAP5.csv` (18000 samples, compiling) peaked at 1.88 GB, and at
    1.46 GB with this call between compiling and running."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        return False
    return True


def release_programs_near_map_limit(share: float = 0.5) -> bool:
    """Clear JAX's in-memory compiled programs (`jax.clear_caches()`) when this
    process holds more than `share` of the kernel's memory-map limit; returns whether
    it did. Linux only (elsewhere a no-op).

    Every compiled XLA CPU program keeps its own memory maps, and `diagnose`
    compiles several thousand maps' worth per record length (measured: 6500-8200).
    With the default `vm.max_map_count` of 65530, about ten lengths in one process
    make LLVM fail with "Cannot allocate memory" and abort the process. Clearing
    the caches releases the maps (measured: back to ~540); the cost is recompiling
    programs used again."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read())
        with open(f"/proc/{os.getpid()}/maps") as f:
            count = sum(1 for _ in f)
    except (OSError, ValueError):
        return False
    if count <= share * limit:
        return False
    jax.clear_caches()
    return True


# Calls in flight by default: one per CPU core, at most this many (each holds its own
# buffers, so memory grows with them)
MAX_THREADS = 8


def default_threads(threads: int = 0) -> int:
    """`threads`, or for 0 one per CPU core up to `MAX_THREADS`."""
    return threads or max(1, min(os.cpu_count() or 1, MAX_THREADS))


def thread_map(f, items, threads: int = 0) -> list:
    """`[f(x) for x in items]`, the first call alone (it compiles what the others
    reuse), the rest `threads` at a time (0: `default_threads`). XLA's CPU backend
    runs one call's work on one core at a time, so a second call in flight uses a
    second core. `f` must be safe to call from several threads (a JAX function
    is)."""
    items = list(items)
    if not items:
        return []
    first = f(items[0])
    with ThreadPoolExecutor(default_threads(threads)) as pool:
        return [first, *pool.map(f, items[1:])]


def chunked_vmap(f, args, chunk: int):
    """`jax.vmap(f)(*args)` evaluated `chunk` members at a time (`lax.map` over
    chunks), so a large grid never materialises all its intermediates at once.
    Memory is that of one chunk; the result equals the plain `vmap`."""
    n = jax.tree.leaves(args)[0].shape[0]
    if n <= chunk:
        return jax.vmap(f)(*args)
    k = -(-n // chunk)
    pad = k * chunk - n

    def prep(x):
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape((k, chunk) + x.shape[1:])

    out = jax.lax.map(lambda a: jax.vmap(f)(*a), jax.tree.map(prep, args))
    return jax.tree.map(lambda y: y.reshape((k * chunk,) + y.shape[2:])[:n], out)


def coarse(x):
    """`x` as a selection compares it: float64 rounded to float32 (24 bits), other
    dtypes unchanged.

    A batched call's kernels depend on the batch size (XLA blocks its sums
    differently), so the same loop's losses can differ in their last bits between a
    chunk of 2 and one of 64. Two candidates whose float64 losses tie to 7
    significant digits are then ordered by those bits, and the choice, and all
    that follows it, would depend on the chunk. Compared at 24 bits, they tie
    exactly and the first candidate wins (`argmin` and the stable `argsort` keep
    the lowest index), whatever the batch. Candidates that close fit the data
    equally well."""
    x = jnp.asarray(x)
    return x.astype(jnp.float32) if x.dtype == jnp.float64 else x


def first_min(x, axis=None):
    """`jnp.argmin(x, axis)` on `coarse(x)`: the index of the least value, the first
    of those tied to 7 significant digits in float64."""
    return jnp.argmin(coarse(x), axis=axis)


def stack_trees(*trees):
    """The pytrees `trees` (one structure) stacked leaf by leaf along a new leading
    axis: a batch for `vmap`."""
    return jax.tree.map(lambda *t: jnp.stack(t), *trees)
