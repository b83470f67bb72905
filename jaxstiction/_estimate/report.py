"""Host-side report of a [`jaxstiction.LoopFit`][]: engineering units, valve curves,
step response, JSON and text. NumPy only; nothing here is traced."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._blocks import Kano
from .._checks import check_loop, LoopDataError
from .._criteria import simulate_scored
from .._filters import step_response
from .._loop import make_loop
from .._misc import json_number as _r, warn_without_float64
from .._spline import scale_input, valve_curves
from .estimate import min_length
from .programs import estimate_cached, simulations_of
from .result import delay_note, held_out_note, KINDS, LoopFit, RESULTS
from .settings import Settings


RULES = ("literal", "robust")


@dataclasses.dataclass(frozen=True)
class FitReport:
    """A [`jaxstiction.LoopFit`][] read out for people: NumPy arrays and floats in
    engineering units, the curves the pictures draw, and `to_json()` (the `fit` JSON
    object). `fit` is the underlying `LoopFit` (use it for `predict`). `notes`: what a
    reader should know before trusting the model (a fitted delay that is the longest
    tried; a model that simulates the held-out part worse than the data's mean)."""

    name: str
    ts: float
    fit: LoopFit
    n_estimation: int
    n_validation: int
    model_kind: str
    fitness: float
    fitness_estimation: float
    fitness_paper: float
    fitness_spline: float
    fitness_physical: float | None
    direction_rule: str
    num_knots: int
    order: int
    delay: int
    notes: tuple[str, ...]
    arx_order: int
    band_percent: float
    S: float | None
    J: float | None
    S_interval: tuple | None
    J_interval: tuple | None
    converged: bool
    status: str
    relax_steps: int
    candidates: dict
    op: np.ndarray
    pv: np.ndarray
    pv_sim: np.ndarray
    pv_sim_paper: np.ndarray
    valve_u: np.ndarray
    valve_up: np.ndarray
    valve_down: np.ndarray
    step: np.ndarray
    process_b: np.ndarray
    process_a: np.ndarray

    def predict(self, op, pv=None, *, k: int | None = None, which: str = "model") -> np.ndarray:
        """Simulate (or predict `k` steps ahead) on a new record, as
        [`jaxstiction.LoopFit.predict`][]; `which="paper"` uses the paper's model."""
        if which not in ("model", "paper"):
            raise ValueError(f"`which` must be 'model' or 'paper', got {which!r}")
        model = self.fit.model if which == "model" else self.fit.paper
        op = jnp.asarray(np.asarray(op, float))
        if pv is None:
            return np.asarray(model.simulate(op))
        pv = jnp.asarray(np.asarray(pv, float))
        if k is None:
            return np.asarray(simulate_scored(model, op, pv, jnp.ones_like(op))[0])
        return np.asarray(model.predict(op, pv, k))

    def to_json(self) -> dict:
        """The `fit` object of the JSON contract."""
        stiction = {"band_percent": _r(self.band_percent)}
        if self.S is not None:
            stiction.update(S=_r(self.S), J=_r(self.J), S_interval=[_r(v) for v in self.S_interval],
                            J_interval=[_r(v) for v in self.J_interval])
        return {
            "name": self.name,
            "fitness": _r(self.fitness),
            "fitness_estimation": _r(self.fitness_estimation),
            "fitness_paper_method": _r(self.fitness_paper),
            "model": {
                "kind": self.model_kind,
                "direction": self.direction_rule,
                "knots": self.num_knots,
                "order": self.order,
                "delay": self.delay,
                "arx_order": self.arx_order,
                "b": [_r(v, 6) for v in self.process_b],
                "a": [_r(v, 6) for v in self.process_a],
            },
            "stiction": stiction,
            "converged": bool(self.converged),
            "status": self.status,
            "note": "; ".join(self.notes),
            "samples": {"estimation": self.n_estimation, "validation": self.n_validation},
            "Ts": self.ts,
        }


@eqx.filter_jit
def _kano_path(S, J, op):
    return Kano(S, J)(op)


@eqx.filter_jit  # one cached program instead of ~25 small ones compiled op by op
def _spline_curves(valve, ug, lo, hi):
    return valve_curves(valve.beta, scale_input(ug, lo, hi), valve.knots, valve.knot_mask)


def _valve_picture(fit: LoopFit, settings: Settings):
    """Valve curves in % of OP and the process in PV units per % of valve travel."""
    lo, hi = (float(v) for v in np.asarray(fit.op_range))
    ug = np.linspace(lo, hi, 400)
    b = np.asarray(fit.model.process.b)
    a = np.asarray(fit.model.process.a)
    if int(fit.kind) >= 1:
        # Kano's own loop (the linear valve: S = J = 0): a triangular OP sweep
        # hi -> lo -> hi -> lo (the first leg settles the valve state); ascent and
        # descent legs read off.
        sweep = np.concatenate([ug[::-1], ug, ug[::-1]])
        S, J = (fit.S, fit.J) if int(fit.kind) == 1 else (0.0, 0.0)
        xk = np.asarray(_kano_path(S, J, jnp.asarray(sweep)))
        n_u = ug.shape[0]
        up, down = xk[n_u : 2 * n_u], xk[2 * n_u :][::-1]
        # x_hat = 2 (valve - lo) / (hi - lo) - 1
        return ug, up, down, b * 2.0 / (hi - lo), a
    valve = fit.model.chain[1]
    upc, dnc = (np.asarray(c) for c in _spline_curves(valve, jnp.asarray(ug), lo, hi))
    gain = b.sum() / a.sum()
    if gain < 0:  # show the valve opening with OP; the sign sits in the process
        upc, dnc, b = -upc, -dnc, -b
    span = max(upc.max(), dnc.max()) - min(upc.min(), dnc.min())
    scale = (hi - lo) / span if span > 0 else 1.0
    lvl = min(upc.min(), dnc.min())
    return ug, lo + (upc - lvl) * scale, lo + (dnc - lvl) * scale, b / scale, a


def report(fit: LoopFit, op, pv, *, name: str = "loop", ts: float = 1.0, settings: Settings = Settings(),
           simulations=None) -> FitReport:
    """Read a single (unbatched) [`jaxstiction.LoopFit`][] out for people, with the
    record `op`, `pv` it was fitted on (real samples only); `simulations`, the chosen
    and the paper's model simulated over it, when already computed."""
    op = np.asarray(op, float)
    pv = np.asarray(pv, float)
    if simulations is None:
        opj, pvj = jnp.asarray(op), jnp.asarray(pv)
        simulations = simulations_of(fit, opj, pvj, jnp.ones_like(opj), settings.score)
    pv_sim, pv_sim_paper = (np.asarray(v) for v in simulations)
    ug, up, down, pb, pa = _valve_picture(fit, settings)
    step = np.asarray(step_response(jnp.asarray(pb), jnp.asarray(pa), 60))
    kind = KINDS[int(fit.kind)]
    physical = settings.use_physical
    code = fit.result
    status = "ok" if bool(code == RESULTS.successful) else RESULTS[code]
    sset = settings.spline
    foe = np.asarray(fit.foe)
    cands = {
        "foe": {RULES[r]: [_r(v, 6) for v in foe[r]] for r in range(2)},
        "knot_counts": list(sset.knot_counts),
        "fitness": {RULES[r]: [_r(v) for v in np.asarray(fit.candidate_fitness)[r]] for r in range(2)},
        # the choice between the families (lower BIC wins; FOE for reference)
        "families": {k: {"foe": _r(getattr(fit, f"foe_{k}"), 6), "bic": _r(getattr(fit, f"bic_{k}"), 3)}
                     for k in ("spline", "physical", "linear")},
    }
    return FitReport(
        name=name,
        ts=float(ts),
        fit=fit,
        n_estimation=int(fit.n_estimation),
        n_validation=int(fit.n_validation),
        model_kind=kind,
        fitness=float(fit.fitness),
        fitness_estimation=float(fit.fitness_estimation),
        fitness_paper=float(fit.fitness_paper),
        fitness_spline=float(fit.fitness_spline),
        fitness_physical=float(fit.fitness_physical) if physical else None,
        direction_rule=RULES[int(fit.direction_rule)],
        num_knots=int(fit.num_knots),
        order=int(fit.order),
        delay=int(fit.delay),
        notes=tuple(n for n in (delay_note(fit.delay, fit.kind, settings),
                                held_out_note(fit.fitness, fit.fitness_estimation, fit.n_validation)) if n),
        arx_order=sset.arx_order,
        band_percent=float(fit.band_percent),
        S=float(fit.S) if physical else None,
        J=float(fit.J) if physical else None,
        S_interval=tuple(float(v) for v in np.asarray(fit.S_interval)) if physical else None,
        J_interval=tuple(float(v) for v in np.asarray(fit.J_interval)) if physical else None,
        converged=status == "ok",
        status=status,
        relax_steps=int(fit.relax_steps),
        candidates=cands,
        op=op,
        pv=pv,
        pv_sim=pv_sim,
        pv_sim_paper=pv_sim_paper,
        valve_u=ug,
        valve_up=up,
        valve_down=down,
        step=step,
        process_b=pb,
        process_a=pa,
    )


def checked(op, pv, name: str, settings: Settings) -> tuple[np.ndarray, np.ndarray]:
    """`(op, pv)` as float64 arrays once they pass [`jaxstiction.check_loop`][] for
    `estimate` with `settings`: the whole record for structure and NaN, its
    estimation part for length and variation. Raises a one-line `LoopDataError`."""
    op, pv = check_loop(op, pv, name=name, min_length=1, require_variation=False)
    n = op.shape[0]
    n_est = n - int(round(settings.validate * n))
    need = int(min_length(settings))
    if n_est < need and n_est < n:
        hint = "; a validate fraction of 0 holds none out" if n >= need else ""
        raise LoopDataError(
            f"{name}: needs at least {need} estimation samples for the chosen orders and delays, got {n_est} "
            f"({n} in the record, {n - n_est} held out for validation{hint})")
    part = "samples" if n_est == n else f"estimation samples, the first of {n}"
    check_loop(op[:n_est], pv[:n_est], name=name, min_length=need, samples=part)
    return op, pv


def fit(op, pv, *, ts: float = 1.0, validate: float = 1 / 3, name: str = "loop",
        settings: Settings | None = None) -> FitReport:
    """Identify the valve and the process of one loop from OP and PV (host API).

    Checks the data (one-line `ValueError` for bad input), runs
    [`jaxstiction.estimate`][] and returns a [`jaxstiction.FitReport`][].

    **Arguments:**

    - `op`, `pv`: controller output (% of span) and process variable, same length.
    - `ts`: sampling time (s), for reporting.
    - `validate`: fraction held out at the end and scored; 0 scores on the estimation
      data (as the paper did for its industrial loop).
    - `settings`: [`jaxstiction.Settings`][] (its `validate` is replaced by the
      argument).

    **Raises:** `ValueError` (a `LoopDataError`) for bad data: mismatched lengths,
    NaN/inf, constant OP or PV, or a record too short for the chosen orders and delays.
    Warns when JAX runs in float32 (enable float64 with
    `jax.config.update("jax_enable_x64", True)`; the command line does).
    """
    warn_without_float64("fit", "its solvers were developed and tested in float64: on five real records float32 "
                                "stops the Gauss-Newton at its step limit on four (one in float64) and moves J by up "
                                "to 0.5 % of span")
    settings = Settings() if settings is None else settings
    if not 0.0 <= validate < 1.0:
        raise ValueError(f"`validate` must be in [0, 1), got {validate}")
    settings = dataclasses.replace(settings, validate=float(validate)) if settings.validate != validate else settings
    op, pv = checked(op, pv, name, settings)
    result, simulations = estimate_cached(make_loop(op, pv, ts), settings)
    return report(result, op, pv, name=name, ts=ts, settings=settings, simulations=simulations)
