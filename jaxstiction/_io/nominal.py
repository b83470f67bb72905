r"""The nominal-model file: a JSON description of a [`jaxstiction.LoopModel`][].

A nominal model is the process a loop is believed to have, around its operating
point, with the valve in front of it:

$$PV_{sim}(t) = \text{pv\_offset} + \frac{B(q)}{A(q)} q^{-\text{delay}}
\big(\text{valve}(OP(t)) - \text{op\_offset}\big),$$

stored as a JSON object:

    {"Ts": 1.0,
     "process": {"b": [0.0, 1.0, 0.5], "a": [1.0, -1.5, 0.7], "delay": 0},
     "op_offset": 50.0, "pv_offset": 0.0,
     "valve": {"model": "linear"}}

- [`jaxstiction.read_nominal`][] reads and validates it into a
  [`jaxstiction.LoopModel`][] (simulate it with `LoopModel.simulate`);
- [`jaxstiction.nominal_ts`][] reads its sampling time `Ts`;
- [`jaxstiction.nominal_to_dict`][] writes a `LoopModel` back to that layout.

Every problem with a file is a [`jaxstiction.LoopDataError`][] with a one-line
message.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._blocks import AbstractBlock, block_name, BLOCKS, make_block
from .._checks import LoopDataError
from .._models import LinearProcess, LoopModel
from .columns import _short


_VALVE_MODELS = ("linear", "kano", "choudhury", "he", "deadband")

# Stochastic blocks (those with a `key` field): the key is written as a list of
# unsigned integers.
_KEYED = frozenset(name for name, cls in BLOCKS.items() if "key" in {f.name for f in dataclasses.fields(cls)})

# Admissible values of block parameters: (block, parameter) -> (test, wording).
_LIMITS = {
    ("kano", "S"): (lambda x: x >= 0, "≥ 0"),
    ("kano", "J"): (lambda x: x >= 0, "≥ 0"),
    ("choudhury", "S"): (lambda x: x >= 0, "≥ 0"),
    ("choudhury", "J"): (lambda x: x >= 0, "≥ 0"),
    ("he", "S"): (lambda x: x >= 0, "≥ 0"),
    ("he", "J"): (lambda x: x >= 0, "≥ 0"),
    ("deadband", "width"): (lambda x: x >= 0, "≥ 0"),
    ("actuator_lag", "a"): (lambda x: 0 <= x < 1, "in [0, 1)"),
    ("rate_limit", "max_rate"): (lambda x: x > 0, "> 0"),
    ("equal_percentage", "R"): (lambda x: x > 0, "> 0"),
    ("sinusoid", "period"): (lambda x: x > 0, "> 0"),
    ("drift", "step_std"): (lambda x: x >= 0, "≥ 0"),
    ("narrow_band", "rms"): (lambda x: x >= 0, "≥ 0"),
    ("narrow_band", "period"): (lambda x: x > 2, "> 2"),
    ("narrow_band", "r"): (lambda x: 0 <= x < 1, "in [0, 1)"),
    ("quantiser", "step_size"): (lambda x: x > 0, "> 0"),
}


# ---------------------------------------------------------------------------- reading


def _num(value: object, what: str, loc: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LoopDataError(f"{what} must be a number{loc}, got {_short(value)!r}")
    x = float(value)
    if not math.isfinite(x):
        raise LoopDataError(f"{what} must be finite{loc}, got {x}")
    return x


def _whole(value: object, what: str, loc: str) -> int:
    """A whole number ≥ 0 (an integral float such as 2.0 is accepted)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LoopDataError(f"{what} must be a whole number of samples{loc}, got {_short(value)!r}")
    if not (math.isfinite(value) and float(value).is_integer()):
        raise LoopDataError(f"{what} must be a whole number of samples{loc}, got {value}")
    k = int(value)
    if k < 0:
        raise LoopDataError(f"{what} must be ≥ 0{loc}, got {k}")
    return k


def _poly(value: object, what: str, loc: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)):
        raise LoopDataError(f"{what} must be a list of numbers{loc}, got {_short(value)!r}")
    if len(value) == 0:
        raise LoopDataError(f"{what} is empty{loc}")
    return np.asarray([_num(x, f"{what}[{i}]", loc) for i, x in enumerate(value)])


def _format_pole(p: complex) -> str:
    if abs(p.imag) <= 1e-12 * max(1.0, abs(p)):
        return f"{p.real:.4g}"
    sign = "+" if p.imag >= 0 else "-"
    return f"{p.real:.4g}{sign}{abs(p.imag):.4g}j (modulus {abs(p):.4g})"


def _load(source: object) -> tuple[Mapping[str, Any], str]:
    """The JSON object of `source` (path or mapping) and the location suffix used in
    messages (`" in '<path>'"`, or `""` for a mapping)."""
    if isinstance(source, Mapping):
        data: Any = source
        where, loc = "the nominal model", ""
    elif isinstance(source, (str, os.PathLike)):
        path = Path(source)
        where = f"'{os.fspath(source)}'"
        loc = f" in {where}"
        if not path.is_file():
            raise LoopDataError(f"file not found: {where}" if not path.exists() else f"{where} is not a file")
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
                f"{where} is not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})"
            ) from None
    else:
        raise LoopDataError(
            f"cannot read a nominal model from a {type(source).__name__}; pass a path to a JSON file or a dict"
        )
    if not isinstance(data, Mapping):
        raise LoopDataError(f"{where} must hold a JSON object, got {type(data).__name__}")
    return data, loc


def _ts(data: Mapping[str, Any], loc: str) -> float:
    if "Ts" not in data:
        raise LoopDataError(f"missing key 'Ts'{loc}")
    ts = _num(data["Ts"], "Ts", loc)
    if ts <= 0:
        raise LoopDataError(f"Ts must be positive{loc}, got {ts:g}")
    return ts


def _check_limit(name: str, param: str, x: float, what: str, loc: str) -> None:
    limit = _LIMITS.get((name, param))
    if limit is not None and not limit[0](x):
        raise LoopDataError(f"{what} must be {limit[1]}{loc}, got {x:g}")


def _param(name: str, param: str, value: object, what: str, loc: str) -> Any:
    """One block parameter from JSON, checked, in the form its block takes."""
    if name == "dead_time" and param == "k":
        return _whole(value, what, loc)
    if name in _KEYED and param == "key":
        if not (
            isinstance(value, (list, tuple))
            and value
            and all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**32 for v in value)
        ):
            raise LoopDataError(f"{what} must be a list of integers in [0, 2**32){loc}, got {_short(value)!r}")
        return jnp.asarray(np.asarray(value, dtype=np.uint32))
    x = _num(value, what, loc)
    _check_limit(name, param, x, what, loc)
    return x


def _block(entry: object, what: str, side: str, loc: str) -> AbstractBlock:
    """One block of an extended-form `chain`/`output` list."""
    if not isinstance(entry, Mapping) or "block" not in entry:
        raise LoopDataError(f"{what} must be an object with 'block' and its parameters{loc}, got {_short(entry)!r}")
    name = str(entry["block"]).strip().lower()
    cls = BLOCKS.get(name)
    if cls is None:
        raise LoopDataError(
            f"unknown block {_short(entry['block'])!r} in {what}{loc} (expected one of: {', '.join(BLOCKS)})"
        )
    if cls.side != side:
        home = "chain" if cls.side == "input" else "output"
        raise LoopDataError(f"block '{name}' in {what} acts on the process {cls.side}; list it under '{home}'{loc}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    params: dict[str, Any] = {}
    for key, value in entry.items():
        if key == "block":
            continue
        if key not in fields:
            raise LoopDataError(
                f"block '{name}' in {what} has no parameter {_short(key)!r}{loc} (parameters: {', '.join(fields)})"
            )
        params[key] = _param(name, key, value, f"{what}.{key}", loc)
    for f in fields.values():
        if f.name not in params and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise LoopDataError(f"block '{name}' in {what} needs '{f.name}'{loc}")
    if name == "travel_limits" and params.get("lo", -math.inf) > params.get("hi", math.inf):
        raise LoopDataError(f"{what}: lo must be ≤ hi{loc}, got lo={params['lo']:g}, hi={params['hi']:g}")
    try:
        return make_block(name, **params)
    except ValueError as exc:
        raise LoopDataError(f"{what}: {exc}{loc}") from None


def _blocks(value: object, key: str, side: str, loc: str) -> tuple[AbstractBlock, ...]:
    if not isinstance(value, (list, tuple)):
        raise LoopDataError(f"'{key}' must be a list of blocks{loc}, got {_short(value)!r}")
    return tuple(_block(entry, f"{key}[{i}]", side, loc) for i, entry in enumerate(value))


def _valve(valve_raw: object, loc: str) -> tuple[AbstractBlock, ...]:
    """The input chain of the plain `valve` form."""
    if isinstance(valve_raw, str):
        valve_raw = {"model": valve_raw}
    if not isinstance(valve_raw, Mapping):
        raise LoopDataError(f"'valve' must be an object with 'model'{loc}")
    model = str(valve_raw.get("model", "linear")).strip().lower()
    if model not in _VALVE_MODELS:
        raise LoopDataError(
            f"unknown valve.model {_short(valve_raw.get('model'))!r}{loc} (expected one of: {', '.join(_VALVE_MODELS)})"
        )
    if model == "linear":
        return ()
    if model == "deadband":
        if "width" not in valve_raw:
            raise LoopDataError(f"valve model 'deadband' needs 'valve.width'{loc}")
        width = _num(valve_raw["width"], "valve.width", loc)
        _check_limit("deadband", "width", width, "valve.width", loc)
        return (make_block("deadband", width=width),)
    for key in ("S", "J"):
        if key not in valve_raw:
            raise LoopDataError(f"valve model '{model}' needs 'valve.{key}'{loc}")
    S = _num(valve_raw["S"], "valve.S", loc)
    J = _num(valve_raw["J"], "valve.J", loc)
    if S < 0 or J < 0:
        raise LoopDataError(f"valve.S and valve.J must be ≥ 0{loc}, got S={S:g}, J={J:g}")
    return (make_block(model, S=S, J=J),)


def read_nominal(source: str | os.PathLike | Mapping[str, Any]) -> LoopModel:
    """Read and validate a nominal model from a JSON file or a dict.

    **Layout** (polynomials in q⁻¹ from q⁰; the process input is the valve position
    minus `op_offset`):

        {"Ts": 1.0,
         "process": {"b": [b0, b1, ...], "a": [1, a1, ...], "delay": 0},
         "op_offset": 50.0, "pv_offset": 0.0,
         "valve": {"model": "linear"}}

    `Ts`, `process.b` and `process.a` are required (`a[0]` must be 1); `delay`
    (whole samples), `op_offset` and `pv_offset` default to 0 and `valve` to linear.
    `valve.model` (case-insensitive; `"valve": "linear"` is short for the object) is
    one of

    - `linear`: valve position = OP (an empty chain);
    - `kano`, `choudhury`, `he`: stiction with `S ≥ 0`, `J ≥ 0` (% of span), as
      [`jaxstiction.Kano`][], [`jaxstiction.Choudhury`][], [`jaxstiction.He`][];
    - `deadband`: backlash of total `width ≥ 0`, as [`jaxstiction.Deadband`][].

    **Extended form.** Instead of `valve`, an input chain of any input-side blocks of
    [`jaxstiction.BLOCKS`][], in order from OP to the process input, and optionally
    output-side blocks acting on PV:

        "chain": [{"block": "actuator_lag", "a": 0.8},
                  {"block": "kano", "S": 3.0, "J": 1.0},
                  {"block": "dead_time", "k": 2}],
        "output": [{"block": "sinusoid", "amplitude": 1.0, "period": 50}]

    Each entry names its block and gives its parameters (the block's fields; those
    with a default may be left out, e.g. `travel_limits` `lo`/`hi`). `valve` and
    `chain` cannot both be given. Unknown top-level keys are ignored; unknown block
    parameters are errors. `Ts` is not part of the returned model: see
    [`jaxstiction.nominal_ts`][].

    **Returns:** a [`jaxstiction.LoopModel`][] with the valve as its `chain`,
    `process = LinearProcess(b, a, delay)`, the default (white, unit-variance)
    noise model, the offsets and the `output` blocks. `LoopModel.simulate(op)` gives
    PV_sim, starting at rest at the first OP.

    **Raises:** [`jaxstiction.LoopDataError`][] with a one-line message for an
    unreadable file or invalid JSON, a missing key, a non-numeric value, `a[0] ≠ 1`,
    an empty `b` or `a`, a negative or non-integer delay, an unknown valve model or
    block, a missing or out-of-range parameter, or an unstable process (a root of
    z^na + a₁z^(na−1) + … with modulus ≥ 1: `nominal model is unstable: pole at 1.05`;
    a pole at exactly 1, an integrating process, is named as such).
    """
    data, loc = _load(source)
    _ts(data, loc)
    if "process" not in data:
        raise LoopDataError(f"missing key 'process'{loc}")
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
            f"process.a[0] must be 1 (monic A polynomial){loc}, got {a[0]:g}; divide a and b by a[0]"
        )
    delay = _whole(proc.get("delay", 0), "process.delay", loc)
    op_offset = _num(data.get("op_offset", 0.0), "op_offset", loc)
    pv_offset = _num(data.get("pv_offset", 0.0), "pv_offset", loc)
    if "chain" in data:
        if "valve" in data:
            raise LoopDataError(f"give either 'valve' or 'chain', not both{loc}")
        chain = _blocks(data["chain"], "chain", "input", loc)
    else:
        chain = _valve(data.get("valve", {"model": "linear"}), loc)
    output = _blocks(data["output"], "output", "output", loc) if "output" in data else ()
    if a.shape[0] > 1:
        poles = np.roots(a)
        if poles.size:
            worst = poles[int(np.argmax(np.abs(poles)))]
            if abs(worst - 1.0) < 1e-9:
                raise LoopDataError(
                    f"nominal model is integrating (pole at 1, as a level loop): its simulation from OP drifts "
                    f"without bound, so it cannot be the reference of a diagnosis; poles must lie inside the "
                    f"unit circle{loc}"
                )
            if abs(worst) >= 1.0 - 1e-9:
                raise LoopDataError(
                    f"nominal model is unstable: pole at {_format_pole(complex(worst))} "
                    f"(a pole must lie inside the unit circle){loc}"
                )
    return LoopModel(
        chain=chain,
        process=LinearProcess(b=tuple(float(x) for x in b), a=tuple(float(x) for x in a), delay=delay),
        op_offset=op_offset,
        pv_offset=pv_offset,
        output=output,
    )


def nominal_ts(source: str | os.PathLike | Mapping[str, Any]) -> float:
    """The sampling time `Ts` (seconds) of a nominal model file or dict.

    Only the container and `Ts` are checked here (the rest is checked by
    [`jaxstiction.read_nominal`][]).

    **Raises:** [`jaxstiction.LoopDataError`][] (one line) for an unreadable file or
    invalid JSON, a missing `Ts`, or a `Ts` that is not a positive number.
    """
    data, loc = _load(source)
    return _ts(data, loc)


# ---------------------------------------------------------------------------- writing


def _scalar(value: object, what: str) -> float:
    """A scalar parameter as a Python float (shortest repr of its own precision)."""
    arr = np.asarray(value)
    if arr.ndim != 0:
        raise ValueError(f"{what} must be a scalar, got shape {arr.shape} (a batched model?)")
    x = float(str(arr[()]))
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite to be written as JSON, got {x}")
    return x


def _floats(value: object, what: str) -> list[float]:
    arr = np.asarray(value)
    if arr.ndim != 1:
        raise ValueError(f"{what} must be a 1-D array, got shape {arr.shape} (a batched model?)")
    return [_scalar(v, f"{what}[{i}]") for i, v in enumerate(arr)]


def _block_params(blk: AbstractBlock, what: str) -> dict[str, Any]:
    name = block_name(blk)
    if BLOCKS.get(name) is not type(blk):
        raise ValueError(
            f"{what}: a {type(blk).__name__} cannot be written to a nominal model; "
            f"only the blocks of jaxstiction.BLOCKS can ({', '.join(BLOCKS)})"
        )
    out: dict[str, Any] = {}
    for f in dataclasses.fields(blk):
        value = getattr(blk, f.name)
        if name == "dead_time" and f.name == "k":
            out["k"] = int(value)
        elif name in _KEYED and f.name == "key":
            out["key"] = [int(v) for v in np.asarray(value).ravel()]
        elif name == "travel_limits" and float(np.asarray(value)) == (-math.inf if f.name == "lo" else math.inf):
            continue  # the default: no limit on that side
        else:
            out[f.name] = _scalar(value, f"{what}.{f.name}")
    return out


def nominal_to_dict(model: LoopModel, ts: float = 1.0) -> dict[str, Any]:
    """A [`jaxstiction.LoopModel`][] in the layout [`jaxstiction.read_nominal`][]
    reads (JSON-ready: Python floats, ints and lists).

    The valve is written in the plain `valve` form when the chain is empty
    (`{"model": "linear"}`) or a single stiction or deadband block
    (`{"model": "kano", "S": ..., "J": ...}`, `{"model": "deadband", "width": ...}`),
    otherwise as a `chain` list; output-side blocks go to an `output` list. The noise
    model is not part of the format and is left out. `read_nominal(nominal_to_dict(m))`
    rebuilds `m` (with the default noise model).

    **Arguments:** `model`; `ts`: the sampling time to record (seconds, > 0).

    **Raises:** `TypeError` if `model` is not a `LoopModel`; `ValueError` (one line)
    for a bad `ts`, a block that is not in [`jaxstiction.BLOCKS`][], or a batched or
    non-finite parameter.
    """
    if not isinstance(model, LoopModel):
        raise TypeError(f"nominal_to_dict needs a LoopModel, got {type(model).__name__}")
    ts = _scalar(ts, "ts")
    if ts <= 0:
        raise ValueError(f"ts must be positive, got {ts:g}")
    proc = model.process
    out: dict[str, Any] = {
        "Ts": ts,
        "process": {
            "b": _floats(proc.b, "process.b"),
            "a": _floats(proc.a, "process.a"),
            "delay": int(proc.delay),
        },
        "op_offset": _scalar(model.op_offset, "op_offset"),
        "pv_offset": _scalar(model.pv_offset, "pv_offset"),
    }
    chain = tuple(model.chain)
    if not chain:
        out["valve"] = {"model": "linear"}
    elif len(chain) == 1 and type(chain[0]) in tuple(BLOCKS[n] for n in _VALVE_MODELS if n != "linear"):
        out["valve"] = {"model": block_name(chain[0]), **_block_params(chain[0], "valve")}
    else:
        out["chain"] = [{"block": block_name(b), **_block_params(b, f"chain[{i}]")} for i, b in enumerate(chain)]
    if model.output:
        out["output"] = [
            {"block": block_name(b), **_block_params(b, f"output[{i}]")} for i, b in enumerate(model.output)
        ]
    return out
