"""The `Loop` record (one control loop's OP and PV) and `stack` for ragged batches."""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import is_count


class Loop(eqx.Module):
    """One control loop's record, as the estimators take it.

    **Fields:**

    - `op`: controller output OP (% of span), shape `(time,)`.
    - `pv`: process variable PV (engineering units), shape `(time,)`.
    - `mask`: 1.0 on real samples, 0.0 on padding (see [`jaxstiction.stack`][]);
      padding always sits at the end of the record.
    - `ts`: sampling time in seconds (a scalar array, so loops with different
      sampling times batch together).
    - `sp`: the setpoint, in PV's units, or `None` when none was recorded. (In a
      batch whose loops differ, a loop without one carries NaN: see `setpoint`.)

    All fields are arrays, so a `Loop` passes through `jit` and `vmap`; a batch of
    loops is a `Loop` whose arrays have a leading batch axis.
    """

    op: Float[Array, " time"]
    pv: Float[Array, " time"]
    mask: Float[Array, " time"]
    ts: Float[Array, ""]
    sp: Float[Array, " time"] | None = None

    @property
    def setpoint(self) -> Float[Array, " time"]:
        """The setpoint, NaN on every sample when none was recorded."""
        return jnp.full_like(self.op, jnp.nan) if self.sp is None else self.sp

    @property
    def length(self) -> int:
        """Number of real (unpadded) samples (host-side; not for traced code)."""
        return int(np.asarray(self.mask).sum())


def make_loop(op, pv, ts=1.0, dtype=None, *, sp=None) -> Loop:
    """A [`jaxstiction.Loop`][] from OP and PV arrays (no padding; `mask` all ones),
    with the setpoint `sp` when one was recorded.

    Values are not checked here; [`jaxstiction.check_loop`][] does that.
    """
    dtype = dtype or jnp.result_type(float)
    op = jnp.asarray(np.asarray(op, float), dtype)
    pv = jnp.asarray(np.asarray(pv, float), dtype)
    if op.ndim != 1 or op.shape != pv.shape:
        raise ValueError(f"`op` and `pv` must be 1-D arrays of one length, got shapes {op.shape} and {pv.shape}")
    if sp is not None:
        sp = jnp.asarray(np.asarray(sp, float), dtype)
        if sp.shape != op.shape:
            raise ValueError(f"`sp` must have the shape of `op`, {op.shape}, got {sp.shape}")
    return Loop(op=op, pv=pv, mask=jnp.ones(op.shape, dtype), ts=jnp.asarray(float(ts), dtype), sp=sp)


def bucket_length(n: int) -> int:
    """The padded length of a screen bucket holding `n`-sample loops: the first of
    500, 800, 1000, 1500, 2000, 2900, 4000, … (500 × √2^k rounded up to 100) that is
    at least `n`. The verdict's spectral indicators read a periodogram on the padded
    record's grid, so a loop judged alone is padded to its bucket too (as `diagnose`
    does), to get the screen's verdict."""
    k = 0
    while True:
        b = int(math.ceil(500 * 2 ** (k / 2) / 100) * 100)
        if b >= n:
            return b
        k += 1


def pad(loop: Loop, length: int) -> Loop:
    """`loop` padded at the end to `length` samples, mask off on the padding.

    Padded samples repeat the last real value (so every stage sees finite, flat data
    there); their mask is 0, so no stage scores them.
    """
    n = loop.op.shape[-1]
    if length < n:
        raise ValueError(f"cannot pad a {n}-sample loop to {length} samples")
    extra = length - n

    def ext(x, value=None):
        fill = x[-1] if value is None else value
        return jnp.concatenate([x, jnp.full((extra,), fill, x.dtype)])

    return Loop(op=ext(loop.op), pv=ext(loop.pv), mask=ext(loop.mask, 0.0), ts=loop.ts,
                sp=None if loop.sp is None else ext(loop.sp))


def stack(loops: Sequence[Loop], length: int | None = None) -> Loop:
    """One batched [`jaxstiction.Loop`][] from loops of different lengths.

    Every loop is padded at the end to the longest record (or to `length`), with
    `mask` off on the padding, and the fields are stacked on a new leading axis:
    `eqx.filter_vmap(jaxstiction.estimate)(jaxstiction.stack(loops))`.
    """
    loops = list(loops)
    if not loops:
        raise ValueError("`loops` is empty: nothing to stack")
    n = max(lp.op.shape[-1] for lp in loops) if length is None else int(length)
    padded = [pad(lp, n) for lp in loops]
    any_sp = any(lp.sp is not None for lp in padded)  # then every member carries one (NaN: none recorded)
    return Loop(
        op=jnp.stack([lp.op for lp in padded]),
        pv=jnp.stack([lp.pv for lp in padded]),
        mask=jnp.stack([lp.mask for lp in padded]),
        ts=jnp.stack([jnp.asarray(lp.ts) for lp in padded]),
        sp=jnp.stack([lp.setpoint for lp in padded]) if any_sp else None,
    )


def decimation_factor(factor: object) -> int:
    """`factor` as an `int`, or a `ValueError` when it is not a positive integer."""
    if not is_count(factor, 1):
        raise ValueError(f"the decimation factor must be a positive integer, got {factor!r}")
    return int(factor)


def decimate(loop: Loop, factor: int) -> Loop:
    """`loop` at a `factor` times longer sampling time: the means of `factor`
    consecutive samples.

    For a record sampled much faster than its loop moves (the estimators' delays,
    ARX orders and prediction horizons count samples; see the README's *Known
    limitations*). Block means keep OP and PV aligned with each other and average
    the measurement noise down; a valve's slip is kept as a jump spread over at most
    two samples (a low-pass filter before picking every `factor`-th sample would
    smear it over the filter's length). A trailing part shorter than `factor` is
    dropped, and a block that reaches into padding is padding (`mask` 0). `ts` is
    multiplied by `factor`; `factor` 1 returns `loop` itself.

    **Raises:** `ValueError` when `factor` is not a positive integer.
    """
    factor = decimation_factor(factor)
    if factor == 1:
        return loop
    n = loop.op.shape[-1] // factor * factor

    def blocks(x):
        return x[..., :n].reshape(*x.shape[:-1], n // factor, factor)

    return Loop(op=blocks(loop.op).mean(-1), pv=blocks(loop.pv).mean(-1),
                mask=blocks(loop.mask).min(-1), ts=loop.ts * factor,
                sp=None if loop.sp is None else blocks(loop.sp).mean(-1))


def window_length(length: object) -> int:
    """`length` as an `int`, or a `ValueError` when it is not a positive integer."""
    if not is_count(length, 1):
        raise ValueError(f"the window length must be a positive integer, got {length!r}")
    return int(length)


def windows(loop: Loop, length: int) -> list[tuple[int, int, Loop]]:
    """`(start, stop, part)` of one loop's record cut into the fewest consecutive
    windows of equal length (to a sample) that hold at most `length` samples each;
    the whole record as one window when it is no longer than `length`. For a
    record of days, over which a slow cycle (a day's, a shift's) can hide a limit
    cycle from the oscillation indicators (see the limitations page).

    **Raises:** `ValueError` when `length` is not a positive integer.
    """
    n = int(loop.op.shape[-1])
    k = -(-n // window_length(length))
    bounds = [i * n // k for i in range(k + 1)]

    def cut(x, a, b):
        return None if x is None else x[..., a:b]

    return [(a, b, Loop(op=cut(loop.op, a, b), pv=cut(loop.pv, a, b), mask=cut(loop.mask, a, b), ts=loop.ts,
                        sp=cut(loop.sp, a, b)))
            for a, b in zip(bounds[:-1], bounds[1:])]


def window_name(name: str, start: int, stop: int) -> str:
    """The name of samples `start` to `stop` (stop excluded) of recording `name`:
    `NAME@START-STOP`; `recording_of` reads it back."""
    return f"{name}@{start}-{stop}"


def recording_of(name: str) -> str:
    """The recording a window named by `window_name` comes from; any other name as it is."""
    head, at, span = name.rpartition("@")
    start, dash, stop = span.partition("-")
    return head if at and dash and start.isdigit() and stop.isdigit() else name


def unstack(batch: Loop) -> list[Loop]:
    """The members of a batched loop, each cut back to its real samples."""
    out = []
    for i in range(batch.op.shape[0]):
        n = int(np.asarray(batch.mask[i]).sum())
        sp = None if batch.sp is None else batch.sp[i, :n]
        out.append(Loop(op=batch.op[i, :n], pv=batch.pv[i, :n], mask=batch.mask[i, :n], ts=batch.ts[i], sp=sp))
    return out
