"""Reading one control loop's record from a file, a DataFrame or a mapping.

- [`jaxstiction.read_loop`][] reads one loop into a [`jaxstiction.Loop`][] (OP, PV,
  mask and sampling time). Accepted sources:
    - a delimited text file (`.csv`, `.tsv`, `.txt`): a header row naming the
      columns, then one row per sample; `OP` and `PV` are required, `t` (or `time`,
      `timestamp` or `datetime`: seconds, or ISO 8601 date-times) and `SP` are
      optional, other columns are ignored. Historian exports with tagged columns
      (`FIC101.OP`, `FIC101.PV`, `FIC102.OP`, ...) hold one loop per tag. Comma,
      semicolon and tab separators are recognised from the header line; beside
      semicolons and tabs, decimal commas are read too.
    - a MATLAB `.mat` file holding one or more structs with fields `OP`, `PV` and
      `Ts` (see `jaxstiction._io.read_mat`).
    - a pandas DataFrame or a mapping with such columns or keys.
- [`jaxstiction.list_loops`][] names the loops of a file that holds several.
- [`jaxstiction.find_loop_files`][] expands files and folders for batch screening.
- [`jaxstiction.loop_name`][] gives the label of a loop read from a path.

Only NumPy is needed here; pandas is never imported (a DataFrame passed in is used
as is) and SciPy only when a `.mat` file is read. Every failure is a
[`jaxstiction.LoopDataError`][] with a one-line message.
"""

from __future__ import annotations

import csv
import datetime
import io
import math
import os
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._checks import _as_column, _nonfinite_message, check_loop, LoopDataError, LoopDataWarning
from .._loop import Loop, make_loop
from .columns import _COLUMN, _match_columns, _norm, _short, _tagged_loops
from .read_mat import _read_mat, list_mat_loops


_CSV_SUFFIXES = (".csv", ".tsv", ".txt")
_MAT_SUFFIXES = (".mat",)


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
    # Gaps (missing samples), repeated or reversed stamps: the estimators take the
    # samples as equally spaced, so say so. Jitter within half a step is not reported.
    steps = np.diff(t)
    off = np.abs(steps - step) > 0.5 * step
    if off.any():
        first = int(np.argmax(off)) + 1
        warnings.warn(LoopDataWarning(
            f"`t` in {where} is not evenly spaced: {int(off.sum())} of {steps.shape[0]} time steps differ from "
            f"the median {step:g} s by more than half of it (from {float(steps.min()):g} to "
            f"{float(steps.max()):g} s; the first at sample {first}); the samples are taken as equally spaced"
        ), stacklevel=4)
    return step


def _finish(
    cols: Mapping[str, np.ndarray | None],
    *,
    where: str,
    check_name: str,
    ts: float | None,
    file_ts: object,
) -> Loop:
    """Shared tail of all readers: checks, sampling-time precedence, the `Loop`.

    SP and t are checked (length, NaN/inf); SP is kept, t only gives the sampling
    time.
    """
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
    return make_loop(op, pv, ts_val, sp=extra["sp"])


# ----------------------------------------------------------------------------- CSV


def _parse_number(cell: str, decimal_comma: bool = False) -> float:
    cell = cell.strip()
    if cell == "":
        return math.nan
    try:
        return float(cell)
    except ValueError:
        # a decimal comma (European exports, separated by semicolons or tabs)
        if decimal_comma and cell.count(",") == 1 and "." not in cell:
            return float(cell.replace(",", "."))
        raise


def _cell_number(text: str, column: str, line: int, where: str, decimal_comma: bool) -> float:
    """One CSV cell as a number, or a `LoopDataError` naming its column and line."""
    try:
        return _parse_number(text, decimal_comma)
    except ValueError:
        raise LoopDataError(
            f"non-numeric value {_short(text)!r} in column `{column}` at line {line} of {where}"
        ) from None


def _parse_times(cells: list[tuple[int, str]], column: str, where: str, decimal_comma: bool) -> np.ndarray:
    """The `t` column in seconds: numbers as they are, or ISO 8601 date-times
    (`2024-03-01 12:00:00`, `2024-03-01T12:00:00.5+01:00`, ...) as seconds after the
    first. `cells`: (line number, text) per sample."""
    first = next((text.strip() for _, text in cells if text.strip()), "")
    try:
        _parse_number(first, decimal_comma)
        numeric = True
    except ValueError:
        numeric = False
    if numeric:
        return np.array([_cell_number(text, column, line, where, decimal_comma) for line, text in cells])
    stamps = []
    for line, text in cells:
        try:
            stamps.append(datetime.datetime.fromisoformat(text.strip()))
        except ValueError:
            raise LoopDataError(
                f"`{column}` value {_short(text)!r} at line {line} of {where} is neither a number "
                "(seconds) nor an ISO 8601 date-time"
            ) from None
    aware = {s.tzinfo is not None for s in stamps}
    if len(aware) > 1:
        raise LoopDataError(f"`{column}` in {where} mixes date-times with and without a time zone")
    return np.array([(s - stamps[0]).total_seconds() for s in stamps])


def _time_seconds(values: Any) -> np.ndarray | None:
    """Date-times (as seconds after the first; time zones honoured) or durations as
    seconds, from a NumPy array or a pandas column or index; `None` for anything else."""
    kind = getattr(getattr(values, "dtype", None), "kind", "")
    if kind not in ("M", "m") or np.size(values) == 0:
        return None
    try:
        arr = getattr(values, "array", None)  # pandas: its date-time/duration array
        if arr is None:
            arr = np.asarray(values)
            return (arr - arr.reshape(-1)[0] if kind == "M" else arr) / np.timedelta64(1, "s")
        return np.asarray((arr - arr[0] if kind == "M" else arr).total_seconds(), dtype=np.float64)
    except (AttributeError, TypeError, ValueError):
        return None


def _csv_reader(path: Path, where: str):
    """`(reader, header, delimiter)`: a `csv.reader` past the header row of a text
    file, the header's cells and the separator found in it."""
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
        header = next(row for row in reader if any(cell.strip() for cell in row))
    except csv.Error as exc:
        raise LoopDataError(f"{where} is not a readable CSV file ({exc})") from None
    return reader, header, delimiter


def _read_csv(path: Path, where: str, name: str | None = None) -> dict[str, np.ndarray | None]:
    reader, header, delimiter = _csv_reader(path, where)
    try:
        columns = _match_columns(header, where, name)
        index = {canon: header.index(key) for canon, key in columns.items()}  # type: ignore[arg-type]
        decimal_comma = delimiter != ","
        data: dict[str, list[float]] = {canon: [] for canon in index if canon != "t"}
        times: list[tuple[int, str]] = []
        need = max(index.values()) + 1
        for row in reader:
            if not any(cell.strip() for cell in row):
                continue
            if len(row) < need:
                raise LoopDataError(
                    f"line {reader.line_num} of {where} has {len(row)} fields, "
                    f"expected {len(header)} as in the header"
                )
            if "t" in index:
                times.append((reader.line_num, row[index["t"]]))
            for canon, values in data.items():
                values.append(_cell_number(row[index[canon]], _COLUMN[canon], reader.line_num, where, decimal_comma))
    except csv.Error as exc:
        raise LoopDataError(f"{where} is not a readable CSV file ({exc})") from None
    if not data["op"]:
        raise LoopDataError(f"{where} has a header but no data rows")
    out: dict[str, np.ndarray | None] = {"sp": None, "t": None}
    for canon, values in data.items():
        out[canon] = np.asarray(values, dtype=np.float64)
    if "t" in index:
        out["t"] = _parse_times(times, header[index["t"]].strip(), where, decimal_comma)
    return out


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


def _read_frame(df: Any, where: str, name: str | None = None) -> dict[str, np.ndarray | None]:
    columns = _match_columns(list(df.columns), where, name)
    out: dict[str, np.ndarray | None] = {"sp": None, "t": None}
    for canon, key in columns.items():
        column = _COLUMN[canon]
        seconds = _time_seconds(df[key]) if canon == "t" else None
        out[canon] = seconds if seconds is not None else _frame_column(df, key, column, where)
    if out["t"] is None:  # a DatetimeIndex or TimedeltaIndex
        out["t"] = _time_seconds(df.index)
    return out


def _read_mapping(
    m: Mapping, where: str, name: str | None = None
) -> tuple[dict[str, np.ndarray | None], object]:
    columns = _match_columns(list(m.keys()), where, name)
    out: dict[str, np.ndarray | None] = {"sp": None, "t": None}
    for canon, key in columns.items():
        column = _COLUMN[canon]
        seconds = _time_seconds(m[key]) if canon == "t" else None
        out[canon] = _as_column(m[key] if seconds is None else seconds, column, f"{where}: ")
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
) -> Loop:
    """Read one control loop into a [`jaxstiction.Loop`][].

    **Arguments:**

    - `source`: one of
        - a path (`str` or `Path`) to a **CSV** file (`.csv`, also `.tsv`/`.txt`)
          with a header: columns `OP` and `PV` required, `t` (seconds, or ISO 8601
          date-times such as `2024-03-01 12:00:00`, read as seconds after the first;
          `time`, `timestamp` and `datetime` are accepted as its name) and `SP`
          optional, other columns ignored; names match case-insensitively after
          stripping spaces. Without `OP` and `PV` columns, historian-style tagged
          columns are read (`FIC101.OP`, `FIC101.PV`, optionally `FIC101.SP`; the
          separator may also be `_`, `/`, `:`, `-` or a space); a file with several
          tags holds several loops, and `name` picks one;
          comma, semicolon or tab separated (decimal commas are read beside
          semicolons and tabs). Empty cells read as NaN (and are then reported).
        - a path to a MATLAB **`.mat`** file in the International Stiction Database
          layout: a struct with fields `OP`, `PV`, `Ts` (and optionally `SP`),
          possibly nested in other structs, e.g. `cdata.chemicals.loop23`; or
          top-level variables `OP`, `PV`, `Ts`. When the file holds several loops,
          `name` picks one: the dotted path or its last part (see
          [`jaxstiction.list_mat_loops`][]). Needs SciPy.
        - a pandas **DataFrame** with such columns (`t` may hold date-times or
          durations; a DatetimeIndex or TimedeltaIndex counts as `t` when there is
          no `t` column).
        - a **mapping** (e.g. `dict`) with keys `OP`, `PV`, optionally `t`, `SP`, `Ts`.
    - `ts`: sampling time in seconds. Precedence: this argument; else the median
      step of `t`; else the file's `Ts` (`.mat`, mapping); else 1.0.
    - `name`: for a file with several loops, which one (see
      [`jaxstiction.list_loops`][]): a `.mat` file's loop, or the tag of a CSV
      file's tagged columns; for a DataFrame or a mapping, the label used in error
      messages (default `"loop"`), and the tag when its columns are tagged. (To
      label a loop read from a path, use [`jaxstiction.loop_name`][].)

    **Returns:** a [`jaxstiction.Loop`][] with `op`, `pv`, `mask` (all ones), `ts`
    and `sp` (the `SP` column, `None` without one). `SP` and `t` are checked
    (length, NaN/inf); `t` only gives the sampling time.

    **Raises:** [`jaxstiction.LoopDataError`][] (a `ValueError`) with a one-line
    message naming the file and the problem: file not found, unreadable or not CSV,
    unknown extension, missing column, non-numeric value (column and line),
    mismatched lengths, NaN/inf, empty record, non-increasing `t`. A constant OP or PV
    is *not* rejected here; the estimators check that with
    [`jaxstiction.check_loop`][].

    **Warns:** [`jaxstiction.LoopDataWarning`][] when the steps of `t` are uneven
    (a gap, a repeated or reversed stamp: a step off the median by more than half of
    it) and `ts` is not given: the samples are taken as equally spaced at the median
    step.
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
        if suffix in _CSV_SUFFIXES:
            cols = _read_csv(path, where, name)
        elif suffix in _MAT_SUFFIXES:
            cols, file_ts = _read_mat(path, where, name)
        else:
            raise LoopDataError(
                f"unknown file type {path.suffix or '(no extension)'!r} for {where}; "
                "expected .csv or .mat"
            )
        check_name = path.name
    elif _is_dataframe(source):
        check_name = "loop" if name is None else name
        where = f"DataFrame {check_name!r}"
        cols = _read_frame(source, where, name)
    elif isinstance(source, Mapping):
        check_name = "loop" if name is None else name
        where = f"mapping {check_name!r}"
        cols, file_ts = _read_mapping(source, where, name)
    else:
        raise LoopDataError(
            f"cannot read loop data from a {type(source).__name__}; pass a path to a "
            ".csv or .mat file, a pandas DataFrame or a dict with OP and PV"
        )
    return _finish(cols, where=where, check_name=check_name, ts=ts, file_ts=file_ts)


def loop_name(source: object) -> str:
    """A label for a loop read from `source`: the file stem for a path, else `"loop"`.

    `loop_name("data/CHEM23.csv") == "CHEM23"`.
    """
    if isinstance(source, (str, os.PathLike)):
        return Path(source).stem
    return "loop"


def list_loops(path: str | os.PathLike) -> list[str]:
    """Names of the loops in a file that holds several, for `name` of
    [`jaxstiction.read_loop`][]: the loops of a `.mat` file
    ([`jaxstiction.list_mat_loops`][]), or the tags of a CSV file whose columns are
    tagged (`FIC101.OP`, `FIC101.PV`, `FIC102.OP`, ...; tags with both OP and PV, in
    column order). `[]` for a CSV file with plain `OP` and `PV` columns (one loop).

    **Raises:** [`jaxstiction.LoopDataError`][] when the file cannot be read.
    """
    p = Path(path)
    where = f"'{os.fspath(path)}'"
    if p.suffix.lower() in _MAT_SUFFIXES:
        return list_mat_loops(p)
    if not p.is_file():
        raise LoopDataError(f"file not found: {where}")
    header = _csv_reader(p, where)[1]
    if {"op", "pv"} <= {_norm(k) for k in header}:
        return []
    return list(_tagged_loops(header, where))


def find_loop_files(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    recursive: bool = False,
) -> list[Path]:
    """Expand files and folders into a list of loop files for batch screening.

    Files are kept as given (in the given order, duplicates dropped); a folder is
    replaced by its `*.csv` and `*.mat` files (case-insensitive extension, hidden
    files skipped), sorted by path; with `recursive`, also those of its subfolders
    (hidden folders skipped).

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
            candidates = p.rglob("*") if recursive else p.iterdir()
            found = sorted(
                (
                    c
                    for c in candidates
                    if c.is_file()
                    and not any(part.startswith(".") for part in c.relative_to(p).parts)
                    and c.suffix.lower() in (".csv", ".mat")
                ),
                key=lambda c: c.relative_to(p).parts,
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


