"""A nominal loop model read from JSON, and its NumPy simulation.

The model is PV = pv_offset + B(q⁻¹)/A(q⁻¹) q^−delay (valve(OP) − op_offset), stored
as a JSON object with the sampling time `Ts`, the process polynomials
`process.b`, `process.a` (monic) and `process.delay`, the operating point
`op_offset`, `pv_offset`, and the valve (`linear`, `kano` or `choudhury` with
stiction parameters `S`, `J`).

- [`jaxstiction.read_nominal`][] reads and validates it into a
  [`jaxstiction.NominalModel`][]; [`jaxstiction.simulate_nominal`][] drives it with OP.

Only NumPy is needed. Every failure is a [`jaxstiction.LoopDataError`][] with a
one-line message.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._checks import _as_column, LoopDataError
from ._read import _short


__all__ = ["NominalModel", "read_nominal", "simulate_nominal"]

_VALVE_MODELS = ("linear", "kano", "choudhury")


@dataclasses.dataclass(frozen=True, eq=False)
class NominalModel:
    """A nominal loop model, as read by [`jaxstiction.read_nominal`][].

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
        """The model as a JSON-ready dict in the layout `read_nominal` reads."""
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
    """Read and validate a nominal model from a JSON file or a dict.

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
