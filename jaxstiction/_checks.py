"""Input checks for loop data (the "Errors" part of the command-line contract) and
for the whole-number fields of the settings Modules.

Every problem with user data is reported as a [`jaxstiction.LoopDataError`][], a
`ValueError` whose message is a single line naming the problem, so that the command
line can print it as is and a batch can store it as the `status` of one loop.

This module needs only NumPy.
"""

from __future__ import annotations

import re

import numpy as np


_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def one_line(message: object) -> str:
    """`message` on one line: every run of whitespace (newlines included) one space."""
    return " ".join(str(message).split())


def error_line(e: BaseException, limit: int) -> str:
    """An exception on one line, its type first, cut at `limit` characters."""
    return one_line(f"{type(e).__name__}: {e}")[:limit]


def _masked_line(message: object) -> str:
    """`message` on one line, its control characters masked."""
    return _CONTROL.sub("?", one_line(message))


class LoopDataError(ValueError):
    """Bad loop data or a bad nominal model file.

    A `ValueError` whose message is always **one line** (any newline or control
    character in the message is collapsed), naming the problem and, where there is
    one, the file. Raised by [`jaxstiction.read_loop`][], [`jaxstiction.check_loop`][],
    [`jaxstiction.read_nominal`][] and [`jaxstiction.find_loop_files`][].
    """

    def __init__(self, message: object) -> None:
        super().__init__(_masked_line(message))


class LoopDataWarning(UserWarning):
    """Loop data that can be used but may mislead, e.g. a time column that is not
    evenly spaced (the samples are then taken as equally spaced). The message is one
    line and names the file. Issued by [`jaxstiction.read_loop`][]; the command line
    prints it as `warning: ...` on stderr, and `screen` adds it to the loop's `note`."""

    def __init__(self, message: object) -> None:
        super().__init__(_masked_line(message))


def is_count(v: object, least: int) -> bool:
    """Whether `v` is a whole number (not a bool) of at least `least`."""
    return not isinstance(v, bool) and isinstance(v, (int, np.integer)) and v >= least


def check_counts(settings: object, *, positive: tuple = (), nonnegative: tuple = ()) -> None:
    """Raise a `ValueError` naming the first field of `settings` in `positive` that is
    not a whole number >= 1, or in `nonnegative` that is not one >= 0 (a settings
    Module's `__check_init__`: a grid of 0 points or a negative step count would
    otherwise fail deep inside a trace, or silently do nothing)."""
    for names, least in ((positive, 1), (nonnegative, 0)):
        for name in names:
            v = getattr(settings, name)
            if not is_count(v, least):
                raise ValueError(f"`{type(settings).__name__}.{name}` must be a whole number >= {least}, got {v!r}")


def _as_column(values: object, column: str, where: str) -> np.ndarray:
    """`values` as a 1-D float64 array, or a `LoopDataError` naming `column`."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        obj = np.asarray(values, dtype=object).ravel()
        for i, item in enumerate(obj):
            try:
                float(item)
            except (TypeError, ValueError):
                shown = repr(item)
                if len(shown) > 40:
                    shown = shown[:37] + "..."
                raise LoopDataError(
                    f"{where}`{column}` has a non-numeric value {shown} at index {i}"
                ) from None
        raise LoopDataError(
            f"{where}`{column}` cannot be converted to numbers"
        ) from None
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.ravel()
    if arr.ndim != 1:
        raise LoopDataError(
            f"{where}`{column}` must be one-dimensional, "
            f"got an array of shape {arr.shape}"
        )
    return arr


def _nonfinite_message(arr: np.ndarray, column: str) -> str | None:
    """A description of the NaN/inf entries of `arr`, or `None` when all are finite."""
    bad = ~np.isfinite(arr)
    if not bad.any():
        return None
    n_nan = int(np.isnan(arr).sum())
    n_inf = int(bad.sum()) - n_nan
    parts = []
    if n_nan:
        parts.append(f"{n_nan} NaN")
    if n_inf:
        parts.append(f"{n_inf} inf")
    plural = "s" if n_nan + n_inf > 1 else ""
    first = int(np.argmax(bad))
    return (
        f"`{column}` has {' and '.join(parts)} value{plural} "
        f"(first at sample index {first}, counting from 0)"
    )


def _is_constant(arr: np.ndarray) -> bool:
    """True when the spread of `arr` is negligible: ptp ≤ 1e-9·(1 + |mean|)."""
    return float(np.ptp(arr)) <= 1e-9 * (1.0 + abs(float(np.mean(arr))))


def check_loop(
    op: object,
    pv: object,
    *,
    min_length: int = 1,
    name: str = "loop",
    require_variation: bool = True,
    samples: str = "samples",
) -> tuple[np.ndarray, np.ndarray]:
    """Check one loop's OP and PV records; return them as float64 arrays.

    Raises a [`jaxstiction.LoopDataError`][] (a `ValueError`) with a one-line message
    prefixed by `name`, for the first problem found, in this order:

    1. a column that is not numeric or not one-dimensional;
    2. mismatched lengths (`` `OP` has 1500 samples but `PV` has 1499 ``);
    3. an empty record;
    4. NaN or inf values (which column, how many, first index);
    5. fewer than `min_length` samples
       (`needs at least {min_length} samples for the chosen orders and delays, got N`);
    6. a constant OP (spread ≤ 1e-9·(1 + |mean|)): stiction cannot be identified
       without valve movement;
    7. a constant PV.

    **Arguments:**

    - `op`, `pv`: controller output and process variable, array-like of equal length.
    - `min_length`: the fewest samples the caller's model orders need.
    - `name`: the loop or file name used as prefix of the message.
    - `require_variation`: run checks 6 and 7. [`jaxstiction.read_loop`][] turns this
      off (it only checks structure, NaN and length); estimators leave it on.
    - `samples`: what the records are, in the messages of checks 6 and 7
      (`"estimation samples"` when they are part of a longer record).

    **Returns:** `(op, pv)` as one-dimensional float64 NumPy arrays.
    """
    where = f"{name}: " if name else ""
    op_arr = _as_column(op, "OP", where)
    pv_arr = _as_column(pv, "PV", where)
    n_op, n_pv = op_arr.shape[0], pv_arr.shape[0]
    if n_op != n_pv:
        raise LoopDataError(f"{where}`OP` has {n_op} samples but `PV` has {n_pv}")
    if n_op == 0:
        raise LoopDataError(f"{where}the record is empty (no samples)")
    for arr, column in ((op_arr, "OP"), (pv_arr, "PV")):
        msg = _nonfinite_message(arr, column)
        if msg is not None:
            raise LoopDataError(where + msg)
    if n_op < min_length:
        raise LoopDataError(
            f"{where}needs at least {int(min_length)} samples for the chosen orders and delays, "
            f"got {n_op}"
        )
    if require_variation:
        if _is_constant(op_arr):
            raise LoopDataError(
                f"{where}`OP` is constant ({float(op_arr[0]):.6g} "
                f"over all {n_op} {samples}); "
                "stiction cannot be identified without valve movement"
            )
        if _is_constant(pv_arr):
            raise LoopDataError(
                f"{where}`PV` is constant ({float(pv_arr[0]):.6g} "
                f"over all {n_pv} {samples}); "
                "the process response cannot be identified"
            )
    return op_arr, pv_arr
