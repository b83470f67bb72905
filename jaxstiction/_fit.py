"""One loop, end to end: scale, fit every spline candidate and the physical model,
choose, validate, and package a readable result. I/O-free; NumPy at the edges."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._blocks import kano
from ._checks import check_loop
from ._filters import fitness, step_response
from ._hammerstein import candidate_knots, fit_spline_candidates, SplineSettings
from ._physical import fit_physical, physical_valve, PhysicalSettings
from ._spline import direction, hysteresis_regressors, noise_threshold, scale_input, valve_curves


class FitSettings(eqx.Module):
    """Settings of [`jaxstiction.fit`][].

    - `spline`: [`jaxstiction.SplineSettings`][] (orders, knot candidates).
    - `physical`: [`jaxstiction.PhysicalSettings`][]; `use_physical=False` skips it.
    - `robust_factor`: the robust direction threshold is this many OP noise standard
      deviations ([`jaxstiction.noise_threshold`][]).
    """

    spline: SplineSettings = SplineSettings()
    physical: PhysicalSettings = PhysicalSettings()
    use_physical: bool = eqx.field(static=True, default=True)
    robust_factor: float = 3.0


RULES = ("literal", "robust")


def min_length(settings: FitSettings) -> int:
    """Fewest estimation samples the chosen orders can be fitted from."""
    s = settings.spline
    p = 2 * (max(s.knot_counts) + 2)
    # the relaxation's lagged regressor matrix has n (p + 1) columns
    return max(s.arx_order * (p + 1) + 50, 2 * s.welch_segment)


@dataclasses.dataclass(frozen=True)
class LoopFit:
    """Result of [`jaxstiction.fit`][], in engineering units (NumPy arrays).

    `fitness` is the simulation fitness (34) on the validation part (on the estimation
    data when `validate == 0`); `fitness_paper` is the paper's literal method scored
    the same way. `band_percent` is the apparent stiction band in % of OP.
    """

    name: str
    ts: float
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
    arx_order: int
    band_percent: float
    S: float | None
    J: float | None
    S_interval: tuple | None
    J_interval: tuple | None
    converged: bool
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
    _predict: object = dataclasses.field(repr=False, compare=False)

    def predict(self, op, pv0: float | None = None, *, which: str = "model") -> np.ndarray:
        """Simulate the fitted model on a new OP record, starting at rest.

        `pv0` (the record's first PV sample) sets the physical model's initial valve
        position (steady state); without it the valve starts at the first OP value.
        `which="paper"` simulates the paper's literal-method model instead.
        """
        if which not in ("model", "paper"):
            raise ValueError(f"`which` must be 'model' or 'paper', got {which!r}")
        op = np.asarray(op, float)
        if pv0 is None:
            pv0 = float("nan")
        return self._predict(op, pv0, which)

    def to_json(self) -> dict:
        """The `fit` object of the JSON contract (DESIGN §6)."""
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
            "samples": {"estimation": self.n_estimation, "validation": self.n_validation},
            "Ts": self.ts,
        }


def _r(v, nd=3):
    return None if v is None else round(float(v), nd)


def crossing(u, f, level):
    """OP at which curve `f(u)` crosses `level` (the middle crossing if several)."""
    s = np.sign(f - level)
    idx = np.flatnonzero(np.diff(s) != 0)
    if idx.size == 0:
        return None
    i = idx[len(idx) // 2]
    t = (level - f[i]) / (f[i + 1] - f[i])
    return u[i] + t * (u[i + 1] - u[i])


def _band(u, up, down):
    """Horizontal width of the hysteresis loop at mid-height (% of OP)."""
    mid = 0.5 * (min(up.min(), down.min()) + max(up.max(), down.max()))
    a, d = crossing(u, up, mid), crossing(u, down, mid)
    if a is None or d is None:
        return float("nan")
    return float(abs(a - d))


def fit(op, pv, *, ts: float = 1.0, validate: float = 0.0, name: str = "loop",
        settings: FitSettings = FitSettings()) -> LoopFit:
    """Identify the valve and the process of one loop from OP and PV.

    **Arguments:**

    - `op`, `pv`: controller output (% of span) and process variable, same length.
    - `ts`: sampling time (s), for reporting.
    - `validate`: fraction held out at the end for validation; 0 validates on the
      estimation data (as the paper did for its industrial loop).
    - `settings`: [`jaxstiction.FitSettings`][].

    **Returns:** a [`jaxstiction.LoopFit`][].

    **Raises:** `ValueError` (a `LoopDataError`) for bad data: mismatched lengths,
    NaN/inf, constant OP or PV, or a record too short for the chosen orders.

    !!! info
        Enable float64 (`jax.config.update("jax_enable_x64", True)`) for
        identification; the library never changes that setting itself.
    """
    if not 0.0 <= validate < 1.0:
        raise ValueError(f"`validate` must be in [0, 1), got {validate}")
    op, pv = check_loop(op, pv, name=name, min_length=1, require_variation=False)
    N = op.shape[0]
    n_est = N - int(round(validate * N))
    check_loop(op[:n_est], pv[:n_est], name=name, min_length=min_length(settings))
    return _fit_arrays(op, pv, n_est, ts, name, settings)


def _fit_arrays(op, pv, n_est, ts, name, settings: FitSettings) -> LoopFit:
    N = op.shape[0]
    dtype = jnp.result_type(float)
    w = (np.arange(N) < n_est).astype(float)
    lo, hi = float(op[:n_est].min()), float(op[:n_est].max())
    mu, sd = float(pv[:n_est].mean()), float(pv[:n_est].std())
    opj = jnp.asarray(op, dtype)
    y = jnp.asarray((pv - mu) / sd, dtype)
    wj = jnp.asarray(w, dtype)
    u = scale_input(opj, lo, hi)
    thr = float(noise_threshold(u[:n_est], factor=settings.robust_factor))
    H = jnp.stack([direction(u), direction(u, threshold=thr)])
    sset = settings.spline
    cand = fit_spline_candidates(y, u, H, wj, sset)
    foe = np.asarray(cand.foe)
    foe = np.where(np.isfinite(foe), foe, np.inf)
    ri, ki = np.unravel_index(np.argmin(foe), foe.shape)
    pick = jax.tree.map(lambda t: t[ri, ki], cand)
    knots, masks, counts = candidate_knots(sset, dtype)
    phi = hysteresis_regressors(u, H[ri], knots[ki], masks[ki])
    D = sset.max_delay
    ys_spline = np.asarray(pick.model.simulate(phi, D)) * sd + mu
    # the paper's literal method: literal rule, its own FOE choice, no polish
    # (its FOE uses its own, unpolished output-error loss)
    dof_paper = 2 * sset.arx_order + np.asarray(counts)
    foe_paper = (n_est + dof_paper) / (n_est - dof_paper) * np.asarray(cand.v_oe_paper)[0]
    lit = int(np.argmin(np.where(np.isfinite(foe_paper), foe_paper, np.inf)))
    plit = jax.tree.map(lambda t: t[0, lit], cand)
    phil = hysteresis_regressors(u, H[0], knots[lit], masks[lit])
    ys_lit = np.asarray(plit.paper.simulate(phil, D, initial_state=False)) * sd + mu

    est = slice(0, n_est)
    val = slice(n_est, N) if n_est < N else slice(0, N)

    def fit_on(ys, part):
        return float(fitness(jnp.asarray(pv[part]), jnp.asarray(ys[part])))

    # Physical model and the choice between the two, by FOE on the estimation data
    # with each model's own number of free parameters (no peeking at validation).
    count = float(n_est)
    order = int(pick.model.linear.mask.sum())
    dof_spline = 2 * (int(counts[ki]) + 2) + 2 * order - 1
    foe_spline = (count + dof_spline) / (count - dof_spline) * float(pick.v_oe)
    phys = None
    kind, ys_best = "spline", ys_spline
    if settings.use_physical:
        # lo/hi as arrays: Python floats would be static and constant-folded by XLA.
        phys = fit_physical(opj, y, wj, jnp.asarray(lo, dtype), jnp.asarray(hi, dtype), settings.physical)
        xs = physical_valve(opj, phys.S, phys.J, phys.model, y[0], lo, hi, settings.physical.max_delay)
        ys_phys = np.asarray(phys.model.simulate(xs, settings.physical.max_delay)) * sd + mu
        dof_phys = 2 + 2 * settings.physical.order + 1
        foe_phys = (count + dof_phys) / (count - dof_phys) * float(phys.v_oe)
        if foe_phys < foe_spline:
            kind, ys_best = "physical", ys_phys

    # valve curves in % of OP: x_hat mapped so that its range matches the OP range
    ug = np.linspace(lo, hi, 400)
    upc, dnc = valve_curves(pick.model.beta, scale_input(jnp.asarray(ug, dtype), lo, hi), knots[ki], masks[ki])
    upc, dnc = np.asarray(upc), np.asarray(dnc)
    b_full, a_full = (np.asarray(t) for t in pick.model.linear.polynomials(D))
    gain = b_full.sum() / a_full.sum()
    if gain < 0:  # show the valve opening with OP; the sign sits in the process
        upc, dnc, b_full, gain = -upc, -dnc, -b_full, -gain
    span = max(upc.max(), dnc.max()) - min(upc.min(), dnc.min())
    scale = (hi - lo) / span if span > 0 else 1.0
    lvl = min(upc.min(), dnc.min())
    valve_up = lo + (upc - lvl) * scale
    valve_down = lo + (dnc - lvl) * scale
    band = _band(ug, valve_up, valve_down)
    # the process in PV units per % of valve travel (x_model = (valve - lo)/scale + lvl)
    proc_b = b_full * sd / scale
    step = np.asarray(step_response(jnp.asarray(proc_b), jnp.asarray(a_full), 60))

    if kind == "physical":
        # the chosen model's own process: x_scaled = 2 (valve% - lo) / (hi - lo) - 1
        pb, pa = (np.asarray(t) for t in phys.model.linear.polynomials(settings.physical.max_delay))
        proc_b, a_full = pb * sd * 2.0 / (hi - lo), pa
        step = np.asarray(step_response(jnp.asarray(proc_b), jnp.asarray(a_full), 60))
        band = float(phys.S)
        # the valve picture is Kano's own loop: a triangular OP sweep hi -> lo -> hi -> lo
        # (the first leg settles the valve state), ascent and descent legs read off.
        sweep = np.concatenate([ug[::-1], ug, ug[::-1]])
        xk = np.asarray(kano(jnp.asarray(sweep, dtype), phys.S, phys.J))
        n_u = ug.shape[0]
        valve_up, valve_down = xk[n_u : 2 * n_u], xk[2 * n_u :][::-1]
        converged = bool(phys.result == optx.RESULTS.successful)
    else:
        converged = bool(pick.relaxation.result == optx.RESULTS.successful)
    relax_steps = int(pick.relaxation.num_steps)

    def predict(op_new, pv0, which):
        opn = jnp.asarray(op_new, dtype)
        un = scale_input(opn, lo, hi)
        if which == "model" and kind == "physical":
            if np.isnan(pv0):
                xs = scale_input(kano(opn, phys.S, phys.J), lo, hi)
            else:
                y0 = jnp.asarray((pv0 - mu) / sd, dtype)
                xs = physical_valve(opn, phys.S, phys.J, phys.model, y0, lo, hi, settings.physical.max_delay)
            return np.asarray(phys.model.simulate(xs, settings.physical.max_delay, initial_state=False)) * sd + mu
        if which == "paper":
            h = direction(un)
            ph = hysteresis_regressors(un, h, knots[lit], masks[lit])
            return np.asarray(plit.paper.simulate(ph, D, initial_state=False)) * sd + mu
        h = direction(un, threshold=thr if ri == 1 else 0.0)
        ph = hysteresis_regressors(un, h, knots[ki], masks[ki])
        return np.asarray(pick.model.simulate(ph, D, initial_state=False)) * sd + mu

    cands = {
        "foe": {RULES[r]: [None if not np.isfinite(v) else round(float(v), 6) for v in foe[r]] for r in range(2)},
        "knot_counts": list(sset.knot_counts),
        "fitness": {RULES[r]: [round(float(v), 3) for v in np.asarray(cand.fitness)[r]] for r in range(2)},
    }
    return LoopFit(
        name=name,
        ts=float(ts),
        n_estimation=int(n_est),
        n_validation=int(N - n_est),
        model_kind=kind,
        fitness=fit_on(ys_best, val),
        fitness_estimation=fit_on(ys_best, est),
        fitness_paper=fit_on(ys_lit, val),
        fitness_spline=fit_on(ys_spline, val),
        fitness_physical=None if phys is None else fit_on(ys_phys, val),
        direction_rule=RULES[ri],
        num_knots=int(counts[ki]),
        order=settings.physical.order if kind == "physical" else order,
        delay=int(phys.delay) if kind == "physical" else int(pick.model.linear.delay),
        arx_order=sset.arx_order,
        band_percent=band,
        S=None if phys is None else float(phys.S),
        J=None if phys is None else float(phys.J),
        S_interval=None if phys is None else tuple(float(v) for v in np.asarray(phys.S_interval)),
        J_interval=None if phys is None else tuple(float(v) for v in np.asarray(phys.J_interval)),
        converged=converged,
        relax_steps=relax_steps,
        candidates=cands,
        op=op,
        pv=pv,
        pv_sim=ys_best,
        pv_sim_paper=ys_lit,
        valve_u=ug,
        valve_up=valve_up,
        valve_down=valve_down,
        step=step,
        process_b=proc_b,
        process_a=a_full,
        _predict=predict,
    )
