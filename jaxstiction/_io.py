"""Reading loop data and nominal models (DESIGN §6).

- [`jaxstiction.read_loop`][] reads one loop (OP, PV, optional SP and time) from a CSV
  file, a MATLAB `.mat` file in the International Stiction Database (ISDB) layout, a
  pandas DataFrame or a mapping, into a [`jaxstiction.LoopData`][].
- [`jaxstiction.find_loop_files`][] expands files and folders for batch screening.
- [`jaxstiction.read_nominal`][] reads the nominal model JSON into a
  [`jaxstiction.NominalModel`][]; [`jaxstiction.simulate_nominal`][] drives it with OP.

Only NumPy is needed at import time. SciPy is imported when a `.mat` file is read;
pandas is never imported for CSV files (a DataFrame passed in is used as is).
Every failure is a [`jaxstiction.LoopDataError`][] with a one-line message.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._checks import _as_column, _nonfinite_message, check_loop, LoopDataError


__all__ = [
    "LoopData",
    "NominalModel",
    "find_loop_files",
    "list_mat_loops",
    "read_loop",
    "read_nominal",
    "simulate_nominal",
]

_CSV_SUFFIXES = (".csv", ".tsv", ".txt")
_MAT_SUFFIXES = (".mat",)
_VALVE_MODELS = ("linear", "kano", "choudhury")
_COLUMN = {"op": "OP", "pv": "PV", "sp": "SP", "t": "t"}


# --------------------------------------------------------------------------- LoopData


def _opt_array(values: object, column: str) -> np.ndarray | None:
    if values is None:
        return None
    return _as_column(values, column, "")


@dataclasses.dataclass(frozen=True, eq=False)
class LoopData:
    """One control loop's record.

    **Fields:**

    - `op`: controller output (% of span), float64 array of length N.
    - `pv`: process variable (engineering units), float64 array of length N.
    - `sp`: setpoint, float64 array of length N, or `None`.
    - `t`: sample times in seconds, float64 array of length N, or `None`.
    - `ts`: sampling time in seconds (> 0).
    - `name`: a label for reports (by default the file stem).

    The arrays are converted to one-dimensional float64 on construction; the
    constructor checks that all arrays have the same length and `ts` is positive, but
    not the values (see [`jaxstiction.check_loop`][]).
    """

    op: np.ndarray
    pv: np.ndarray
    sp: np.ndarray | None = None
    t: np.ndarray | None = None
    ts: float = 1.0
    name: str = "loop"

    def __post_init__(self) -> None:
        op = _as_column(self.op, "OP", "")
        pv = _as_column(self.pv, "PV", "")
        sp = _opt_array(self.sp, "SP")
        t = _opt_array(self.t, "t")
        n = op.shape[0]
        for arr, column in ((pv, "PV"), (sp, "SP"), (t, "t")):
            if arr is not None and arr.shape[0] != n:
                raise LoopDataError(
                    f"{self.name}: `OP` has {n} samples "
                    f"but `{column}` has {arr.shape[0]}"
                )
        ts = float(self.ts)
        if not (math.isfinite(ts) and ts > 0):
            raise LoopDataError(
                f"{self.name}: sampling time must be positive, got {ts:g}"
            )
        object.__setattr__(self, "op", op)
        object.__setattr__(self, "pv", pv)
        object.__setattr__(self, "sp", sp)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "ts", ts)
        object.__setattr__(self, "name", str(self.name))

    def __len__(self) -> int:
        return int(self.op.shape[0])

    def __repr__(self) -> str:
        extra = "".join(
            f", {k}=<{len(self)}>" for k in ("sp", "t") if getattr(self, k) is not None
        )
        return f"LoopData(name={self.name!r}, n={len(self)}, ts={self.ts:g}{extra})"

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self)

    @property
    def time(self) -> np.ndarray:
        """Sample times in seconds: `t` when recorded, else `ts · (0, 1, …, N−1)`."""
        if self.t is not None:
            return self.t
        return np.arange(len(self), dtype=np.float64) * self.ts

    def _slice(self, sl: slice) -> LoopData:
        return LoopData(
            op=self.op[sl],
            pv=self.pv[sl],
            sp=None if self.sp is None else self.sp[sl],
            t=None if self.t is None else self.t[sl],
            ts=self.ts,
            name=self.name,
        )

    def split(self, fraction: float) -> tuple[LoopData, LoopData]:
        """Split into `(estimation, validation)`, holding out the last `fraction`.

        `fraction = 0` returns the whole record twice (validation on the estimation
        data, as the paper did for its industrial loop). Otherwise
        `round(fraction · N)` samples (at least one, leaving at least one) form the
        validation part. `fraction` must be in `[0, 1)`.
        """
        f = float(fraction)
        if not (math.isfinite(f) and 0.0 <= f < 1.0):
            raise LoopDataError(
                f"validation fraction must be in [0, 1), got {fraction!r}"
            )
        n = len(self)
        if f == 0.0:
            return self, self
        if n < 2:
            raise LoopDataError(
                f"{self.name}: cannot hold out a validation part of a {n}-sample record"
            )
        n_val = min(max(int(round(f * n)), 1), n - 1)
        cut = n - n_val
        return self._slice(slice(0, cut)), self._slice(slice(cut, n))


# ------------------------------------------------------------------------- helpers


def _norm(key: object) -> str:
    return "".join(str(key).split()).lower()


def _short(text: object, limit: int = 30) -> str:
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _found(keys: Iterable[object], limit: int = 12) -> str:
    keys = [_short(k) for k in keys]
    shown = ", ".join(keys[:limit])
    if len(keys) > limit:
        shown += f", ... ({len(keys) - limit} more)"
    return shown or "none"


def _match_columns(keys: Iterable[object], where: str) -> dict[str, object]:
    """Map the canonical names `op, pv, sp, t` to the original keys present in `keys`.

    Matching is case-insensitive after stripping spaces; `time` is accepted for `t`.
    Raises when `OP` or `PV` is missing or a name matches twice.
    """
    keys = list(keys)
    aliases = {"op": "op", "pv": "pv", "sp": "sp", "t": "t", "time": "t"}
    out: dict[str, object] = {}
    for key in keys:
        canon = aliases.get(_norm(key))
        if canon is None:
            continue
        if canon in out:
            raise LoopDataError(
                f"ambiguous columns {_short(out[canon])!r} and {_short(key)!r} "
                f"in {where} (both read as `{_COLUMN[canon]}`)"
            )
        out[canon] = key
    for canon in ("op", "pv"):
        if canon not in out:
            raise LoopDataError(
                f"`{canon.upper()}` column missing in {where} (found: {_found(keys)})"
            )
    return out


def _positive_ts(value: object, what: str, where: str) -> float:
    try:
        ts = float(np.asarray(value, dtype=np.float64).reshape(-1)[0])
    except (TypeError, ValueError, IndexError):
        raise LoopDataError(
            f"{what} in {where} is not a number: {_short(value)!r}"
        ) from None
    if not (math.isfinite(ts) and ts > 0):
        raise LoopDataError(f"{what} in {where} must be positive, got {ts:g}")
    return ts


def _ts_from_t(t: np.ndarray, where: str) -> float | None:
    if t.shape[0] < 2:
        return None
    # rounded to 12 significant digits so that 0.2 recorded as decimals reads 0.2
    step = float(f"{float(np.median(np.diff(t))):.12g}")
    if not step > 0:
        raise LoopDataError(
            f"`t` is not increasing in {where} (median time step {step:g} s); "
            "fix the time column or give the sampling time explicitly (ts)"
        )
    return step


def _finish(
    cols: Mapping[str, np.ndarray | None],
    *,
    where: str,
    check_name: str,
    ts: float | None,
    file_ts: object,
    name: str,
) -> LoopData:
    """Shared tail of all readers: checks, sampling-time precedence, `LoopData`."""
    op, pv = check_loop(
        cols["op"], cols["pv"], min_length=1, name=check_name, require_variation=False
    )
    n = op.shape[0]
    extra: dict[str, np.ndarray | None] = {}
    for canon, column in (("sp", "SP"), ("t", "t")):
        arr = cols.get(canon)
        if arr is None:
            extra[canon] = None
            continue
        arr = _as_column(arr, column, f"{check_name}: ")
        if arr.shape[0] != n:
            raise LoopDataError(
                f"{check_name}: `OP` has {n} samples but `{column}` has {arr.shape[0]}"
            )
        if canon == "sp":
            msg = _nonfinite_message(arr, "SP")
            if msg is not None:
                raise LoopDataError(f"{check_name}: {msg}")
        extra[canon] = arr
    if extra["t"] is not None:
        msg = _nonfinite_message(extra["t"], "t")
        if msg is not None:
            raise LoopDataError(f"{check_name}: {msg}")
    if ts is not None:
        ts_val = _positive_ts(ts, "the sampling time `ts`", where)
    else:
        ts_val = None
        if extra["t"] is not None:
            ts_val = _ts_from_t(extra["t"], where)
        if ts_val is None and file_ts is not None:
            ts_val = _positive_ts(file_ts, "`Ts`", where)
        if ts_val is None:
            ts_val = 1.0
    return LoopData(op=op, pv=pv, sp=extra["sp"], t=extra["t"], ts=ts_val, name=name)


# ----------------------------------------------------------------------------- CSV


def _parse_number(cell: str) -> float:
    cell = cell.strip()
    if cell == "":
        return math.nan
    return float(cell)


def _read_csv(path: Path, where: str) -> dict[str, np.ndarray | None]:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise LoopDataError(f"cannot read {where}: {exc.strerror or exc}") from None
    if not raw.strip():
        raise LoopDataError(f"{where} is empty")
    controls = sum(raw.count(bytes([c])) for c in (*range(0, 9), *range(14, 32)))
    if controls > 0.01 * len(raw):
        raise LoopDataError(f"{where} is not a text CSV file (binary content)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    header_line = next(ln for ln in text.splitlines() if ln.strip())
    counts = {d: header_line.count(d) for d in (",", ";", "\t")}
    delimiter = max(counts, key=lambda d: counts[d]) if any(counts.values()) else ","
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    try:
        header: list[str] | None = None
        for row in reader:
            if any(cell.strip() for cell in row):
                header = row
                break
        assert header is not None
        columns = _match_columns(header, where)
        index = {canon: header.index(key) for canon, key in columns.items()}  # type: ignore[arg-type]
        data: dict[str, list[float]] = {canon: [] for canon in index}
        need = max(index.values()) + 1
        for row in reader:
            if not any(cell.strip() for cell in row):
                continue
            if len(row) < need:
                raise LoopDataError(
                    f"line {reader.line_num} of {where} has {len(row)} fields, "
                    f"expected {len(header)} as in the header"
                )
            for canon, j in index.items():
                try:
                    data[canon].append(_parse_number(row[j]))
                except ValueError:
                    column = _COLUMN[canon]
                    raise LoopDataError(
                        f"non-numeric value {_short(row[j])!r} in column `{column}` "
                        f"at line {reader.line_num} of {where}"
                    ) from None
    except csv.Error as exc:
        raise LoopDataError(f"{where} is not a readable CSV file ({exc})") from None
    if not data["op"]:
        raise LoopDataError(f"{where} has a header but no data rows")
    out: dict[str, np.ndarray | None] = {"sp": None, "t": None}
    for canon, values in data.items():
        out[canon] = np.asarray(values, dtype=np.float64)
    return out


# ----------------------------------------------------------------------------- MAT


def _is_struct(obj: object) -> bool:
    return hasattr(obj, "_fieldnames")


def _fields(obj: object) -> dict[str, object]:
    return {f: getattr(obj, f) for f in obj._fieldnames}  # type: ignore[attr-defined]


def _is_loop(fields: Mapping[str, object]) -> bool:
    keys = {_norm(k) for k in fields}
    return "op" in keys and "pv" in keys


def _walk(
    obj: object, path: str, out: list[tuple[str, dict[str, object]]], depth: int
) -> None:
    if depth > 12:
        return
    if _is_struct(obj):
        fields = _fields(obj)
        if _is_loop(fields):
            out.append((path, fields))
            return
        for key, value in fields.items():
            _walk(value, f"{path}.{key}" if path else key, out, depth + 1)
    elif isinstance(obj, np.ndarray) and obj.dtype == object:
        for i, value in enumerate(obj.flat):
            _walk(value, f"{path}[{i}]", out, depth + 1)


def _load_mat(path: Path, where: str) -> list[tuple[str, dict[str, object]]]:
    try:
        from scipy.io import loadmat
    except ImportError:
        raise LoopDataError(
            f"reading {where} needs scipy (pip install scipy)"
        ) from None
    try:
        contents = loadmat(str(path), squeeze_me=True, struct_as_record=False)
    except NotImplementedError:
        raise LoopDataError(
            f"{where} is a MATLAB v7.3 (HDF5) file, which is not supported; "
            "save it with -v7 in MATLAB"
        ) from None
    except OSError as exc:
        raise LoopDataError(f"cannot read {where}: {exc.strerror or exc}") from None
    except Exception as exc:  # scipy raises many types on garbage
        raise LoopDataError(
            f"{where} is not a readable MATLAB file "
            f"({type(exc).__name__}: {_short(exc, 60)})"
        ) from None
    variables = {k: v for k, v in contents.items() if not k.startswith("__")}
    if _is_loop(variables):
        return [("", variables)]
    loops: list[tuple[str, dict[str, object]]] = []
    for key, value in variables.items():
        _walk(value, key, loops, 0)
    if not loops:
        raise LoopDataError(
            f"no loop (a struct with fields OP and PV) found in {where} "
            f"(variables: {_found(variables)})"
        )
    return loops


def list_mat_loops(path: str | os.PathLike) -> list[str]:
    """Names of the loops inside a MATLAB `.mat` file in the ISDB layout.

    A loop is any struct with fields `OP` and `PV`, found by walking nested structs;
    its name is the dotted path, e.g. `cdata.chemicals.loop23`. A file whose top-level
    variables are themselves `OP` and `PV` holds one loop named `""`. Any of these
    names (or its last part, e.g. `loop23`) can be passed as `name` to
    [`jaxstiction.read_loop`][].
    """
    p = Path(path)
    where = f"'{path}'"
    if not p.is_file():
        raise LoopDataError(f"file not found: {where}")
    return [loop_path for loop_path, _ in _load_mat(p, where)]


def _select_loop(
    loops: list[tuple[str, dict[str, object]]], name: str | None, where: str
) -> tuple[str, dict[str, object]]:
    if name is not None:
        key = name.strip().lower()
        hits = [
            (p, f)
            for p, f in loops
            if p.lower() == key or p.lower().endswith("." + key)
        ]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise LoopDataError(
                f"name {name!r} matches {len(hits)} loops in {where} "
                f"({_found(p for p, _ in hits)}); give the full dotted name"
            )
    if len(loops) == 1:
        return loops[0]
    available = _found((p for p, _ in loops), limit=20)
    if name is None:
        raise LoopDataError(
            f"{where} holds {len(loops)} loops; choose one with name "
            f"(available: {available})"
        )
    raise LoopDataError(f"no loop named {name!r} in {where} (available: {available})")


def _read_mat(
    path: Path, where: str, name: str | None
) -> tuple[dict[str, np.ndarray | None], object]:
    loops = _load_mat(path, where)
    loop_path, fields = _select_loop(loops, name, where)
    by_norm: dict[str, object] = {}
    for key, value in fields.items():
        by_norm.setdefault(_norm(key), value)
    columns = _match_columns(
        fields.keys(), where + (f" ({loop_path})" if loop_path else "")
    )
    cols: dict[str, np.ndarray | None] = {
        canon: np.atleast_1d(np.asarray(fields[key])) for canon, key in columns.items()
    }
    cols.setdefault("sp", None)
    cols.setdefault("t", None)
    return cols, by_norm.get("ts")


# ------------------------------------------------------------------- DataFrame/dict


def _is_dataframe(obj: object) -> bool:
    return (
        type(obj).__module__.split(".")[0] == "pandas"
        and hasattr(obj, "columns")
        and hasattr(obj, "index")
    )


def _frame_column(df: Any, key: object, column: str, where: str) -> np.ndarray:
    series = df[key]
    if getattr(series, "ndim", 1) != 1:
        raise LoopDataError(f"ambiguous column `{column}` in {where} (appears twice)")
    try:
        return np.asarray(series.to_numpy(dtype=np.float64, na_value=np.nan))
    except (TypeError, ValueError):
        return _as_column(series.to_numpy(dtype=object), column, f"{where}: ")


def _frame_time(df: Any) -> np.ndarray | None:
    """Seconds from a DatetimeIndex/TimedeltaIndex, else `None`."""
    idx = df.index
    kind = getattr(getattr(idx, "dtype", None), "kind", "")
    if kind not in ("M", "m") or len(idx) == 0:
        return None
    try:
        if kind == "M":
            idx = idx - idx[0]
        return np.asarray(idx.total_seconds(), dtype=np.float64)
    except (AttributeError, TypeError, ValueError):
        return None


def _read_frame(df: Any, where: str) -> dict[str, np.ndarray | None]:
    columns = _match_columns(list(df.columns), where)
    out: dict[str, np.ndarray | None] = {"sp": None, "t": None}
    for canon, key in columns.items():
        column = _COLUMN[canon]
        out[canon] = _frame_column(df, key, column, where)
    if out["t"] is None:
        out["t"] = _frame_time(df)
    return out


def _read_mapping(
    m: Mapping, where: str
) -> tuple[dict[str, np.ndarray | None], object]:
    columns = _match_columns(list(m.keys()), where)
    out: dict[str, np.ndarray | None] = {"sp": None, "t": None}
    for canon, key in columns.items():
        column = _COLUMN[canon]
        out[canon] = _as_column(m[key], column, f"{where}: ")
    file_ts = None
    for key, value in m.items():
        if _norm(key) == "ts":
            file_ts = value
            break
    return out, file_ts


# --------------------------------------------------------------------------- public


def read_loop(
    source: str | os.PathLike | Mapping[str, Any] | Any,
    *,
    ts: float | None = None,
    name: str | None = None,
) -> LoopData:
    """Read one control loop into a [`jaxstiction.LoopData`][].

    **Arguments:**

    - `source`: one of
        - a path (`str` or `Path`) to a **CSV** file (`.csv`, also `.tsv`/`.txt`)
          with a header: columns `OP` and `PV` required, `t` (seconds; `time` is
          accepted too) and `SP` optional, other columns ignored; names match
          case-insensitively after stripping spaces; comma, semicolon or tab
          separated. Empty cells read as NaN (and are then reported).
        - a path to a MATLAB **`.mat`** file in the ISDB layout: a struct with fields
          `OP`, `PV`, `Ts` (and optionally `SP`), possibly nested, e.g.
          `cdata.chemicals.loop23`; or top-level variables `OP`, `PV`, `Ts`. When the
          file holds several loops, `name` picks one: the dotted path or its last
          part (see [`jaxstiction.list_mat_loops`][]). Needs SciPy.
        - a pandas **DataFrame** with such columns (a DatetimeIndex or
          TimedeltaIndex counts as `t` when there is no `t` column).
        - a **mapping** (e.g. `dict`) with keys `OP`, `PV`, optionally `t`, `SP`, `Ts`.
    - `ts`: sampling time in seconds. Precedence: this argument; else the median
      step of `t`; else the file's `Ts` (`.mat`, mapping); else 1.0.
    - `name`: label of the loop (default: the file stem, the chosen `.mat` loop's
      last name part, or `"loop"`); for a `.mat` file with several loops, which one.

    **Returns:** a [`jaxstiction.LoopData`][].

    **Raises:** [`jaxstiction.LoopDataError`][] (a `ValueError`) with a one-line
    message naming the file and the problem: file not found, unreadable or not CSV,
    unknown extension, missing column, non-numeric value (column and line),
    mismatched lengths, NaN/inf, empty record, non-increasing `t`. A constant OP or PV
    is *not* rejected here; the estimators check that with
    [`jaxstiction.check_loop`][].
    """
    file_ts: object = None
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        where = f"'{os.fspath(source)}'"
        if not path.exists():
            raise LoopDataError(f"file not found: {where}")
        if path.is_dir():
            raise LoopDataError(f"{where} is a folder, not a loop file")
        suffix = path.suffix.lower()
        label = name
        if suffix in _CSV_SUFFIXES:
            cols = _read_csv(path, where)
        elif suffix in _MAT_SUFFIXES:
            cols, file_ts = _read_mat(path, where, name)
        else:
            raise LoopDataError(
                f"unknown file type {path.suffix or '(no extension)'!r} for {where}; "
                "expected .csv or .mat"
            )
        label = path.stem if label is None else label
        check_name = path.name
    elif _is_dataframe(source):
        label = "loop" if name is None else name
        where = f"DataFrame {label!r}"
        cols = _read_frame(source, where)
        check_name = label
    elif isinstance(source, Mapping):
        label = "loop" if name is None else name
        where = f"mapping {label!r}"
        cols, file_ts = _read_mapping(source, where)
        check_name = label
    else:
        raise LoopDataError(
            f"cannot read loop data from a {type(source).__name__}; pass a path to a "
            ".csv or .mat file, a pandas DataFrame or a dict with OP and PV"
        )
    return _finish(
        cols, where=where, check_name=check_name, ts=ts, file_ts=file_ts, name=label
    )


def find_loop_files(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
) -> list[Path]:
    """Expand files and folders into a list of loop files for batch screening.

    Files are kept as given (in the given order, duplicates dropped); a folder is
    replaced by its `*.csv` and `*.mat` files (not recursive, case-insensitive
    extension, hidden files skipped), sorted by name.

    **Raises:** [`jaxstiction.LoopDataError`][] for a path that does not exist or a
    folder without any `.csv`/`.mat` file.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    out: list[Path] = []
    seen: set[Path] = set()

    def add(p: Path) -> None:
        if p not in seen:
            seen.add(p)
            out.append(p)

    for item in paths:
        p = Path(item)
        if p.is_dir():
            found = sorted(
                (
                    c
                    for c in p.iterdir()
                    if c.is_file()
                    and not c.name.startswith(".")
                    and c.suffix.lower() in (".csv", ".mat")
                ),
                key=lambda c: c.name,
            )
            if not found:
                raise LoopDataError(
                    f"no .csv or .mat files in folder '{os.fspath(item)}'"
                )
            for c in found:
                add(c)
        elif p.exists():
            add(p)
        else:
            raise LoopDataError(f"file not found: '{os.fspath(item)}'")
    return out


# ------------------------------------------------------------------- nominal model


@dataclasses.dataclass(frozen=True, eq=False)
class NominalModel:
    """A nominal loop model (DESIGN §6), as read by [`jaxstiction.read_nominal`][].

    PV_sim = `pv_offset` + G(q) q^−`delay` (valve(OP) − `op_offset`), with
    G(q) = B(q⁻¹)/A(q⁻¹), B = b₀ + b₁q⁻¹ + …, A = 1 + a₁q⁻¹ + … .

    **Fields:**

    - `ts`: sampling time of the model in seconds.
    - `b`: numerator coefficients from q⁰ (float64 array, non-empty).
    - `a`: denominator coefficients from q⁰, `a[0] == 1` (float64 array).
    - `delay`: extra input delay in samples (≥ 0).
    - `op_offset`, `pv_offset`: operating point of the valve input and of PV.
    - `valve`: `"linear"`, `"kano"` or `"choudhury"`.
    - `S`, `J`: stiction parameters (% of span) for `kano`/`choudhury`, else `None`.
    """

    ts: float
    b: np.ndarray
    a: np.ndarray
    delay: int = 0
    op_offset: float = 0.0
    pv_offset: float = 0.0
    valve: str = "linear"
    S: float | None = None
    J: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "b", np.atleast_1d(np.asarray(self.b, dtype=np.float64))
        )
        object.__setattr__(
            self, "a", np.atleast_1d(np.asarray(self.a, dtype=np.float64))
        )
        object.__setattr__(self, "ts", float(self.ts))
        object.__setattr__(self, "delay", int(self.delay))
        object.__setattr__(self, "op_offset", float(self.op_offset))
        object.__setattr__(self, "pv_offset", float(self.pv_offset))

    def to_dict(self) -> dict[str, Any]:
        """The model as a JSON-ready dict in the layout of DESIGN §6."""
        valve: dict[str, Any] = {"model": self.valve}
        if self.S is not None:
            valve["S"] = self.S
        if self.J is not None:
            valve["J"] = self.J
        return {
            "Ts": self.ts,
            "process": {
                "b": [float(x) for x in self.b],
                "a": [float(x) for x in self.a],
                "delay": self.delay,
            },
            "op_offset": self.op_offset,
            "pv_offset": self.pv_offset,
            "valve": valve,
        }


def _num(value: object, what: str, loc: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LoopDataError(f"{what} must be a number{loc}, got {_short(value)!r}")
    x = float(value)
    if not math.isfinite(x):
        raise LoopDataError(f"{what} must be finite{loc}, got {x}")
    return x


def _poly(value: object, what: str, loc: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)):
        raise LoopDataError(
            f"{what} must be a list of numbers{loc}, got {_short(value)!r}"
        )
    if len(value) == 0:
        raise LoopDataError(f"{what} is empty{loc}")
    return np.asarray([_num(x, f"{what}[{i}]", loc) for i, x in enumerate(value)])


def _format_pole(p: complex) -> str:
    if abs(p.imag) <= 1e-12 * max(1.0, abs(p)):
        return f"{p.real:.4g}"
    sign = "+" if p.imag >= 0 else "-"
    return f"{p.real:.4g}{sign}{abs(p.imag):.4g}j (modulus {abs(p):.4g})"


def read_nominal(source: str | os.PathLike | Mapping[str, Any]) -> NominalModel:
    """Read and validate a nominal model (DESIGN §6) from a JSON file or a dict.

    Layout: `{"Ts": 1.0, "process": {"b": [...], "a": [1, ...], "delay": 0},
    "op_offset": 50.0, "pv_offset": 0.0, "valve": {"model": "linear"}}`.
    `Ts` and `process.b`, `process.a` are required; `delay`, `op_offset`,
    `pv_offset` default to 0 and `valve` to linear. `valve.model` may be `linear`,
    `kano` or `choudhury`; the latter two need `S ≥ 0` and `J ≥ 0`. Unknown keys
    are ignored.

    **Raises:** [`jaxstiction.LoopDataError`][] with a one-line message for an
    unreadable file or invalid JSON, a missing key, `a[0] ≠ 1`, an empty `b`, a
    negative or non-integer delay, a bad valve, or an unstable process (a root of
    z^na + a₁z^(na−1) + … with modulus ≥ 1: `nominal model is unstable: pole at 1.05`).
    """
    if isinstance(source, Mapping):
        data: Any = source
        where, loc = "the nominal model", ""
    elif isinstance(source, (str, os.PathLike)):
        path = Path(source)
        where = f"'{os.fspath(source)}'"
        loc = f" in {where}"
        if not path.is_file():
            raise LoopDataError(
                f"file not found: {where}"
                if not path.exists()
                else f"{where} is not a file"
            )
        try:
            text = path.read_text(encoding="utf-8-sig")
        except OSError as exc:
            raise LoopDataError(f"cannot read {where}: {exc.strerror or exc}") from None
        except UnicodeDecodeError:
            raise LoopDataError(f"{where} is not a JSON text file") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise LoopDataError(
                f"{where} is not valid JSON ({exc.msg} at line {exc.lineno}, "
                f"column {exc.colno})"
            ) from None
    else:
        raise LoopDataError(
            f"cannot read a nominal model from a {type(source).__name__}; "
            "pass a path to a JSON file or a dict"
        )
    if not isinstance(data, Mapping):
        raise LoopDataError(
            f"{where} must hold a JSON object, got {type(data).__name__}"
        )
    for key in ("Ts", "process"):
        if key not in data:
            raise LoopDataError(f"missing key '{key}'{loc}")
    ts = _num(data["Ts"], "Ts", loc)
    if ts <= 0:
        raise LoopDataError(f"Ts must be positive{loc}, got {ts:g}")
    proc = data["process"]
    if not isinstance(proc, Mapping):
        raise LoopDataError(f"'process' must be an object with b, a, delay{loc}")
    for key in ("b", "a"):
        if key not in proc:
            raise LoopDataError(f"missing key 'process.{key}'{loc}")
    b = _poly(proc["b"], "process.b", loc)
    a = _poly(proc["a"], "process.a", loc)
    if a[0] != 1.0:
        raise LoopDataError(
            f"process.a[0] must be 1 (monic A polynomial){loc}, got {a[0]:g}; "
            "divide a and b by a[0]"
        )
    delay_raw = proc.get("delay", 0)
    if isinstance(delay_raw, bool) or not isinstance(delay_raw, (int, float)):
        raise LoopDataError(
            f"process.delay must be a whole number of samples{loc}, "
            f"got {_short(delay_raw)!r}"
        )
    if not (math.isfinite(delay_raw) and float(delay_raw).is_integer()):
        raise LoopDataError(
            f"process.delay must be a whole number of samples{loc}, got {delay_raw}"
        )
    delay = int(delay_raw)
    if delay < 0:
        raise LoopDataError(f"process.delay must be ≥ 0{loc}, got {delay}")
    op_offset = _num(data.get("op_offset", 0.0), "op_offset", loc)
    pv_offset = _num(data.get("pv_offset", 0.0), "pv_offset", loc)
    valve_raw = data.get("valve", {"model": "linear"})
    if isinstance(valve_raw, str):
        valve_raw = {"model": valve_raw}
    if not isinstance(valve_raw, Mapping):
        raise LoopDataError(f"'valve' must be an object with 'model'{loc}")
    model = str(valve_raw.get("model", "linear")).strip().lower()
    if model not in _VALVE_MODELS:
        raise LoopDataError(
            f"unknown valve.model {_short(valve_raw.get('model'))!r}{loc} "
            f"(expected one of: {', '.join(_VALVE_MODELS)})"
        )
    S = J = None
    if model != "linear":
        for key in ("S", "J"):
            if key not in valve_raw:
                raise LoopDataError(f"valve model '{model}' needs 'valve.{key}'{loc}")
        S = _num(valve_raw["S"], "valve.S", loc)
        J = _num(valve_raw["J"], "valve.J", loc)
        if S < 0 or J < 0:
            raise LoopDataError(
                f"valve.S and valve.J must be ≥ 0{loc}, got S={S:g}, J={J:g}"
            )
    if a.shape[0] > 1:
        poles = np.roots(a)
        if poles.size:
            worst = poles[int(np.argmax(np.abs(poles)))]
            if abs(worst) >= 1.0 - 1e-9:
                raise LoopDataError(
                    "nominal model is unstable: pole at "
                    f"{_format_pole(complex(worst))} "
                    f"(a pole must lie inside the unit circle){loc}"
                )
    return NominalModel(
        ts=ts,
        b=b,
        a=a,
        delay=delay,
        op_offset=op_offset,
        pv_offset=pv_offset,
        valve=model,
        S=S,
        J=J,
    )


def simulate_nominal(
    model: NominalModel,
    op: object,
    *,
    valve_fn: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Simulate the nominal model driven by the recorded OP (NumPy, no SciPy).

    PV_sim = `pv_offset` + G(q) q^−`delay` (valve(OP) − `op_offset`), with zero
    initial conditions for the deviation variables (before the first sample the
    valve sits at `op_offset` and PV at `pv_offset`).

    **Arguments:**

    - `model`: a [`jaxstiction.NominalModel`][].
    - `op`: controller output, array-like of length N.
    - `valve_fn`: optional map from OP (array) to valve position (array, same
      length); overrides `model.valve`. Without it only the linear valve
      (position = OP) is available here: `kano`/`choudhury` raise
      `NotImplementedError` (their simulation is provided by the JAX valve blocks).

    **Returns:** PV_sim as a float64 array of length N.
    """
    u = _as_column(op, "OP", "simulate_nominal: ")
    if valve_fn is not None:
        x = _as_column(valve_fn(u), "valve position", "simulate_nominal: ")
        if x.shape != u.shape:
            raise LoopDataError(
                f"simulate_nominal: valve_fn returned {x.shape[0]} samples for "
                f"{u.shape[0]} OP samples"
            )
    elif model.valve == "linear":
        x = u
    else:
        raise NotImplementedError(
            "simulate_nominal handles the linear valve only; "
            f"the '{model.valve}' valve "
            "is provided elsewhere (the JAX valve blocks); pass valve_fn= to use it"
        )
    n = u.shape[0]
    dev = x - model.op_offset
    d = int(model.delay)
    shifted = np.zeros(n)
    if d < n:
        shifted[d:] = dev[: n - d]
    b = np.asarray(model.b, dtype=np.float64)
    a = np.asarray(model.a, dtype=np.float64)
    y = np.convolve(shifted, b)[:n] / a[0]
    na = a.shape[0] - 1
    if na > 0:
        ar = a[1:] / a[0]
        for k in range(1, n):
            m = min(na, k)
            y[k] -= ar[:m] @ y[k - 1 :: -1][:m]
    return y + model.pv_offset
