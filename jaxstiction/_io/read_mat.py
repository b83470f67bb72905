"""Reading MATLAB `.mat` files in the International Stiction Database layout.

Such a file holds one or more loops. A loop is a struct with (at least) the fields
`OP` (controller output), `PV` (process variable) and usually `Ts` (sampling time,
seconds), optionally `SP` and `t`; structs may be nested, e.g.
`cdata.chemicals.loop23`, and arrays of structs are walked too. A file whose
top-level variables are themselves `OP`, `PV` (and `Ts`) holds a single loop.

[`jaxstiction.list_mat_loops`][] lists the loops of a file;
[`jaxstiction.read_loop`][] reads one of them (chosen with `name`). SciPy is
imported only when a file is actually read; MATLAB v7.3 (HDF5) files are not
supported.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .._checks import LoopDataError
from .columns import _found, _match_columns, _norm, _short


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

