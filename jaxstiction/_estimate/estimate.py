r"""`estimate`: one loop, end to end, as one pure jitted function.

Spline candidates (direction rule × knot count: relaxation, reduction, ASYC, polish,
FOE), the physical Kano model, the choice between them and a linear valve by BIC, the paper's literal
method for reference, and the validation scores, all inside one `jit`, with no
host round trip, so `eqx.filter_vmap(estimate)` batches whole loops. Data problems
become [`jaxstiction.RESULTS`][] codes, never exceptions, so one bad loop in a batch
spoils nothing else.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from .._blocks import Kano
from .._criteria import family_criteria, foe, score
from .._loop import Loop
from .._misc import chunked_vmap, first_min, stack_trees
from .._models import LinearProcess, LoopModel, pad_to, scaled_loop_model, SplineValve
from .._spline import direction, hysteresis_regressors, noise_threshold, scale_input, valve_curves
from .hammerstein import candidate_knots, CandidateFit, fit_spline_candidates, HammersteinModel
from .physical import fit_oe, fit_physical, fits_at_once, PhysicalFit, valve_from
from .reduce import fit_noise_model
from .result import LoopFit, RESULTS
from .settings import Settings, SplineSettings


# deadband widths tried, as multiples of the physical fit's S
DEADBAND_WIDTHS = (0.5, 0.7, 0.85, 1.0, 1.2)


def min_length(settings: Settings) -> int:
    """Fewest estimation samples the chosen orders and delays can be fitted from."""
    s = settings.spline
    p = 2 * (max(s.knot_counts) + 2)
    # the relaxation's lagged regressor matrix has n (p + 1) columns; a delay is
    # resolved only from a record many times longer
    return max(s.arx_order * (p + 1) + 50, 2 * s.welch_segment, 20 * max(s.max_delay, settings.physical.max_delay))


def _pad_model(m: LoopModel, nb: int, na: int) -> LoopModel:
    p = m.process
    return eqx.tree_at(lambda t: t.process, m, LinearProcess(b=pad_to(p.b, nb), a=pad_to(p.a, na)))


def _crossing(u, f, level):
    """OP at which `f(u)` crosses `level` (the middle crossing if several; NaN if none)."""
    s = jnp.sign(f - level)
    ch = jnp.diff(s) != 0
    count = jnp.sum(ch)
    k = count // 2
    i = jnp.argmax(jnp.cumsum(ch) > k)
    t = (level - f[i]) / jnp.where(f[i + 1] != f[i], f[i + 1] - f[i], 1.0)
    return jnp.where(count > 0, u[i] + t * (u[i + 1] - u[i]), jnp.nan)


def spline_band(beta, knots, knot_mask, lo, hi, num: int = 400):
    """Horizontal width (% of OP) of the spline hysteresis loop at mid-height."""
    ug = jnp.linspace(lo, hi, num)
    up, down = valve_curves(beta, scale_input(ug, lo, hi), knots, knot_mask)
    mid = 0.5 * (jnp.minimum(up.min(), down.min()) + jnp.maximum(up.max(), down.max()))
    return jnp.abs(_crossing(ug, up, mid) - _crossing(ug, down, mid))


def estimation_parts(mask, n_est, n_val):
    """The weights of the estimation samples (the first `n_est` real ones: the real
    samples of a padded loop come first) and of the held-out ones (the rest; the
    estimation samples again when nothing is held out)."""
    t = jnp.arange(mask.shape[0])
    w_est = mask * (t < n_est)
    return w_est, jnp.where(n_val > 0, mask * (t >= n_est), w_est)


def choose_family(bics, fitness_estimation):
    """The chosen family (`KINDS`: 0 spline, 1 physical, 2 linear): the least BIC among
    the eligible ones. A stiction family is eligible only if its scored simulation
    fitness on the estimation part is at least the linear valve's (or the linear
    valve's is not finite). The linear valve is eligible unless its simulation is
    gross, a negative fitness (further from the data than their mean), while a
    stiction family with a finite BIC scores at least 0. A NaN BIC is never chosen."""
    lin = fitness_estimation[2]
    eligible = (fitness_estimation >= lin) | ~jnp.isfinite(lin)
    sound = jnp.any((fitness_estimation[:2] >= 0) & jnp.isfinite(bics[:2]))
    eligible = eligible.at[2].set(~((lin < 0) & sound))
    return first_min(jnp.where(eligible & ~jnp.isnan(bics), bics, jnp.inf))


class Prepared(eqx.Module):
    """The record as `estimate`'s stages use it (`_prepare`): OP and PV with
    non-finite samples zeroed, the mask, the estimation and held-out weights and
    counts, the OP range and PV scaling, the scaled `y` and `u`, the direction
    threshold and rules `H`, and the data checks."""

    op: Array
    pv: Array
    mask: Array
    bad: Array
    n_est: Array
    n_val: Array
    w_est: Array
    w_val: Array
    count: Array
    lo: Array
    hi: Array
    const_op: Array
    mu: Array
    sd: Array
    const_pv: Array
    too_short: Array
    y: Array
    u: Array
    thr: Array
    H: Array


def _estimate(loop: Loop, settings: Settings = Settings()) -> LoopFit:
    r"""Identify the valve and the process of one loop from OP and PV.

    Pure and jitted end to end: `eqx.filter_vmap(estimate)(jaxstiction.stack(loops))`
    returns a batched [`jaxstiction.LoopFit`][] whose members equal single calls.
    Samples with `loop.mask == 0` (padding) are ignored by every stage; the last
    `settings.validate` fraction of the real samples is held out and scored.

    **Arguments:**

    - `loop`: a [`jaxstiction.Loop`][] (OP in % of span, PV in engineering units).
    - `settings`: [`jaxstiction.Settings`][].

    **Returns:** a [`jaxstiction.LoopFit`][]. It never raises on bad data: a NaN,
    constant OP, too-short record or a solver failure is reported in `result`.

    !!! info
        Enable float64 (`jax.config.update("jax_enable_x64", True)`) for
        identification; the library never changes that setting itself.
    """
    p = _prepare(loop, settings)
    cand = _spline_stage(p, settings)
    phys = None
    if settings.use_physical:
        # Run the physical stage after the spline stage, not beside it: two
        # independent branches of batched LAPACK calls running at once can deadlock
        # XLA's CPU runtime (jaxlib 0.10, 2 cores: ParallelBatchMap waits on a pool
        # whose workers are all blocked). The barrier only orders the work.
        op_p, y_p, _ = jax.lax.optimization_barrier((p.op, p.y, cand.foe))
        phys = _physical_stage(eqx.tree_at(lambda q: (q.op, q.y), p, (op_p, y_p)), settings)
    return _finish(p, cand, phys, settings)


def _prepare(loop: Loop, settings: Settings) -> Prepared:
    """The first stage of `estimate`: the record cleaned, split and scaled, and its
    data checks (arrays by name, for the stages after it)."""
    dtype = jnp.result_type(loop.op.dtype, loop.pv.dtype, jnp.float32)
    op0, pv0 = jnp.asarray(loop.op, dtype), jnp.asarray(loop.pv, dtype)
    mask = jnp.asarray(loop.mask, dtype)
    finite = jnp.isfinite(op0) & jnp.isfinite(pv0)
    bad = jnp.any(~finite & (mask > 0))
    op = jnp.where(finite, op0, 0.0)
    pv = jnp.where(finite, pv0, 0.0)

    n_real = jnp.sum(mask)
    n_val = jnp.round(settings.validate * n_real)
    n_est = n_real - n_val
    w_est, w_val = estimation_parts(mask, n_est, n_val)
    count = jnp.maximum(jnp.sum(w_est), 1.0)
    big = jnp.finfo(dtype).max
    lo = jnp.min(jnp.where(w_est > 0, op, big))
    hi = jnp.max(jnp.where(w_est > 0, op, -big))
    op_mean = jnp.sum(w_est * op) / count
    const_op = (hi - lo) <= 1e-9 * (1 + jnp.abs(op_mean))
    hi = jnp.where(const_op, lo + 1.0, hi)
    mu = jnp.sum(w_est * pv) / count
    sd = jnp.sqrt(jnp.sum(w_est * (pv - mu) ** 2) / count)
    pv_ptp = jnp.max(jnp.where(w_est > 0, pv, -big)) - jnp.min(jnp.where(w_est > 0, pv, big))
    const_pv = pv_ptp <= 1e-9 * (1 + jnp.abs(mu))
    sd = jnp.where(const_pv | ~(sd > 0), 1.0, sd)
    too_short = n_est < min_length(settings)

    y = (pv - mu) / sd
    u = scale_input(op, lo, hi)
    thr = noise_threshold(u, w_est, factor=settings.robust_factor)
    thr = jnp.where(jnp.isfinite(thr) & (thr > 0), thr, 1e-12)
    H = jnp.stack([direction(u), direction(u, threshold=thr)])
    return Prepared(op=op, pv=pv, mask=mask, bad=bad, n_est=n_est, n_val=n_val, w_est=w_est, w_val=w_val,
                    count=count, lo=lo, hi=hi, const_op=const_op, mu=mu, sd=sd, const_pv=const_pv,
                    too_short=too_short, y=y, u=u, thr=thr, H=H)


def _spline_stage(p: Prepared, settings: Settings):
    """The spline candidates of `estimate` (its heaviest stage but one)."""
    sset = settings.spline
    y, u, H, w_est, mask = p.y, p.u, p.H, p.w_est, p.mask
    if settings.use_spline:
        return fit_spline_candidates(y, u, H, w_est, mask, sset)
    # no spline family: a placeholder of the same shapes (NaN criteria, so it is
    # never chosen), computing nothing
    shapes = jax.eval_shape(lambda: fit_spline_candidates(y, u, H, w_est, mask, sset))
    return jax.tree.map(
        lambda t: jnp.full(t.shape, jnp.nan if jnp.issubdtype(t.dtype, jnp.floating) else 0, t.dtype), shapes)


def _physical_stage(p: Prepared, settings: Settings) -> PhysicalFit:
    """The Kano model's search and fits of `estimate` (its heaviest stage)."""
    return fit_physical(p.op, p.y, p.w_est, p.lo, p.hi, settings.physical)


class _SplinePick(NamedTuple):
    """The spline family's chosen candidate (`_pick_spline`)."""

    foe_grid: Array  # every candidate's FOE (rule × knot count), a run-away one's infinite
    rule: Array  # its direction rule (0 literal, 1 robust)
    k: Array  # its knot count's index
    fit: CandidateFit  # the candidate
    knots: Array  # every knot count's knots, masks and counts (`candidate_knots`)
    kmasks: Array
    counts: Array
    order: Array  # its reduced order
    foe: Array  # the family's FOE and BIC
    bic: Array


class _PhysicalFamily(NamedTuple):
    """The physical family as `estimate` reports it (`_physical_family`)."""

    model: LoopModel
    foe: Array
    bic: Array
    S: Array
    J: Array
    S_interval: Array
    J_interval: Array
    result: Array
    delay: Array | int
    order: int


class _Nulls(NamedTuple):
    """The verdict's null models (`_null_models`) and the padded sizes of B and A."""

    linear: LoopModel
    deadband: LoopModel
    delay: Array  # the linear valve's delay, less one
    foe: Array  # the linear valve's FOE and BIC
    bic: Array
    nb: int
    na: int


def _pick_spline(cand, sset: SplineSettings, count, dtype) -> _SplinePick:
    """The spline candidate of least FOE over the grid of direction rules × knot
    counts, and the family's FOE and BIC."""
    foe_grid = jnp.where(jnp.isfinite(cand.foe), cand.foe, jnp.inf)
    K = foe_grid.shape[1]
    flat = first_min(foe_grid.ravel())
    ri, ki = flat // K, flat % K
    pick = jax.tree.map(lambda x: x[ri, ki], cand)
    knots, kmasks, counts = candidate_knots(sset, dtype)
    order_s = jnp.sum(pick.model.linear.mask).astype(jnp.int32)
    dof_s = 2 * (counts[ki] + 2) + 2 * order_s - 1
    # a run-away candidate has an infinite FOE on the grid
    foe_s, bic_s = family_criteria(jnp.where(jnp.isfinite(foe_grid[ri, ki]), pick.v_oe, jnp.inf), count, dof_s)
    return _SplinePick(foe_grid, ri, ki, pick, knots, kmasks, counts, order_s, foe_s, bic_s)


def _pick_paper(cand, sset: SplineSettings, count, counts):
    """The paper's literal method: the literal rule, its own FOE choice of the knot
    count, no polish. Returns the count's index and the candidates there."""
    dof_p = 2 * sset.arx_order + counts
    foe_paper = jnp.where(jnp.isfinite(cand.v_oe_paper[0]), foe(cand.v_oe_paper[0], count, dof_p), jnp.inf)
    lit = first_min(foe_paper)
    return lit, jax.tree.map(lambda x: x[0, lit], cand)


def _model_sizes(settings: Settings) -> tuple[int, int]:
    """Coefficients of B and A of the spline and physical models (so that they stack)."""
    sset = settings.spline
    nb = sset.max_delay + sset.max_order
    na = sset.max_order + 1
    if settings.use_physical:
        nb = max(nb, settings.physical.max_delay + settings.physical.order)
        na = max(na, settings.physical.order + 1)
    return nb, na


def _spline_models(p: Prepared, s: _SplinePick, lit, plit, settings: Settings, none: Kano, nb: int, na: int):
    """The chosen spline candidate and the paper's literal one as `LoopModel`s in
    engineering units, each with a first-order noise model fitted to its
    simulation error."""
    y, u, H, lo, hi, dtype = p.y, p.u, p.H, p.lo, p.hi, p.y.dtype
    D = settings.spline.max_delay

    def spline_model(hm: HammersteinModel, rule, k, phi_rule_thr):
        phi = hysteresis_regressors(u, H[rule], s.knots[k], s.kmasks[k])
        v = y - hm.simulate(phi, D)
        nm = fit_noise_model(v, p.w_est, order=1)
        b, a = hm.linear.polynomials(D)
        valve = SplineValve(hm.beta, s.knots[k], s.kmasks[k], lo, hi, phi_rule_thr)
        one = jnp.ones((1,), dtype)
        return scaled_loop_model((none, valve), b, a, hm.offset, jnp.concatenate([one, nm.c]),
                                 jnp.concatenate([one, nm.d]), p.mu, p.sd, variance=nm.variance, lengths=(nb, na))

    m_spline = spline_model(s.fit.model, s.rule, s.k, jnp.where(s.rule == 1, p.thr, 0.0))
    paper_hm = HammersteinModel(plit.paper.beta, plit.paper.linear, plit.paper.offset, jnp.zeros_like(plit.paper.state))
    m_paper = spline_model(paper_hm, 0, lit, jnp.zeros((), dtype))
    return m_spline, m_paper


def _physical_family(p: Prepared, phys: PhysicalFit | None, settings: Settings, m_spline: LoopModel, nb: int,
                     na: int) -> _PhysicalFamily:
    """The Kano fit as a `LoopModel` in engineering units, its FOE, BIC and outcome;
    without the physical family, placeholders (the spline model, infinite criteria,
    NaN S and J) that are never chosen."""
    dtype = p.y.dtype
    if settings.use_physical:
        pset = settings.physical
        M = max(settings.spline.knot_counts)
        pb, pa = phys.model.linear.polynomials(pset.max_delay)
        c_n, d_n = phys.noise
        m_phys = scaled_loop_model((Kano(phys.S, phys.J), SplineValve.linear(p.lo, p.hi, M, dtype)), pb, pa,
                                   phys.model.offset, c_n, d_n, p.mu, p.sd, variance=phys.v_oe, lengths=(nb, na))
        dof_ph = 2 + 2 * pset.order + 1
        foe_ph, bic_ph = family_criteria(phys.v_oe, p.count, dof_ph)
        # the Box-Jenkins fits are budgeted refinements of grid points: only a
        # non-finite criterion is a failure
        res_ph = optx.RESULTS.where(jnp.isfinite(phys.v_oe), optx.RESULTS.successful, optx.RESULTS.nonlinear_divergence)
        return _PhysicalFamily(m_phys, foe_ph, bic_ph, phys.S, phys.J, phys.S_interval, phys.J_interval, res_ph,
                               phys.delay, pset.order)
    inf = jnp.asarray(jnp.inf, dtype)
    nan = jnp.asarray(jnp.nan, dtype)
    S_int = jnp.full((2,), jnp.nan, dtype)
    return _PhysicalFamily(m_spline, inf, inf, nan, nan, S_int, S_int, optx.RESULTS.successful, 0, 0)


def _null_models(p: Prepared, settings: Settings, ph: _PhysicalFamily, none: Kano, nb: int, na: int) -> _Nulls:
    """The null models of the verdict: a linear valve, and a deadband (Kano with J =
    0) at widths around the fitted S, each with a Box-Jenkins linear part of the
    physical model's structure: the stiction verdict compares the Kano valve with
    both (see [`jaxstiction.verdict`][])."""
    op, y, w_est, count, lo, hi = p.op, p.y, p.w_est, p.count, p.lo, p.hi
    dtype = y.dtype
    N = op.shape[0]
    M = max(settings.spline.knot_counts)
    pset = settings.physical
    x_lin = scale_input(op, lo, hi)
    x_lin, _ = jax.lax.optimization_barrier((x_lin, ph.foe))

    def oe_at(x, wb, d):
        m, cd, _ = fit_oe(x, y, wb, pset.order, d, pset.max_delay, pset.oe_steps)
        v = jnp.sum((wb * (y - m.simulate(x, pset.max_delay))) ** 2) / jnp.maximum(jnp.sum(wb), 1.0)
        v = jnp.where(jnp.isfinite(v) & (jnp.sum(wb) >= 0.5 * count), v, jnp.inf)
        return (m, cd), v

    nb = max(nb, pset.max_delay + pset.order)
    na = max(na, pset.order + 1)

    def as_model(fit, v, valve0):
        m, (c_, d_) = fit
        b_, a_ = m.linear.polynomials(pset.max_delay)
        return scaled_loop_model((valve0, SplineValve.linear(lo, hi, M, dtype)), b_, a_, m.offset, c_, d_, p.mu,
                                 p.sd, variance=v, lengths=(nb, na))

    # one vmapped Box-Jenkins fit for both nulls: the linear valve at every delay,
    # then the deadband at each width around S (at the physical fit's delay)
    L = pset.max_delay
    xs, wbs, ds = jnp.broadcast_to(x_lin, (L, N)), jnp.broadcast_to(w_est, (L, N)), jnp.arange(1, L + 1)
    if settings.use_physical:
        S_db = jnp.where(jnp.isfinite(ph.S), ph.S, 0.0) * jnp.asarray(DEADBAND_WIDTHS, dtype)
        x_db, wb_db, _ = jax.vmap(lambda width: valve_from(op, width, 0.0, w_est, pset.burn_in, -1, pset.init_count))(
            S_db
        )
        xs = jnp.concatenate([xs, scale_input(x_db, lo, hi)])
        wbs = jnp.concatenate([wbs, wb_db])
        ds = jnp.concatenate([ds, jnp.full((len(DEADBAND_WIDTHS),), ph.delay)])
    # as many at once as the memory budget allows (all of them up to ~30 000 samples)
    null_fits, v_null = chunked_vmap(oe_at, (xs, wbs, ds), fits_at_once(N, pset.memory_budget))
    bl = first_min(v_null[:L])
    m_lin = as_model(jax.tree.map(lambda t: t[bl], null_fits), v_null[bl], none)
    dof_lin = 2 * pset.order + 1
    foe_lin, bic_lin = family_criteria(v_null[bl], count, dof_lin)
    if settings.use_physical:
        bd = first_min(v_null[L:])
        m_db = as_model(jax.tree.map(lambda t: t[L + bd], null_fits), v_null[L + bd],
                        Kano(S_db[bd], jnp.zeros((), dtype)))
    else:
        m_db = m_lin  # without a fitted S there is no width to try: the deadband of width 0 is the linear valve
    return _Nulls(m_lin, m_db, bl, foe_lin, bic_lin, nb, na)


def _scores(p: Prepared, models: dict, settings: Settings, after) -> dict:
    """Every score (model × scored part: `"val"` held out, `"est"` estimation) the
    settings call for, one after the other in one `lax.map`: one trace, and the
    memory of one simulation at a time. The others are NaN. (`after`: a value the
    scoring waits for, so that it runs after the stages' work.)"""
    parts = {"val": p.w_val, "est": p.w_est}
    wanted = [("lin", "val"), ("lin", "est"), ("db", "val"), ("db", "est")]
    if settings.use_physical:
        wanted += [("phys", "val"), ("phys", "est")]
    if settings.use_spline:
        wanted += [("paper", "val"), ("spline", "val"), ("spline", "est")]
    stacked = stack_trees(*(models[m] for m, _ in wanted))
    ws = jnp.stack([parts[w] for _, w in wanted])
    stacked, ws, _ = jax.lax.optimization_barrier((stacked, ws, after))
    out = jax.lax.map(lambda mw: score(mw[0], p.op, p.pv, mw[1], settings.score), (stacked, ws))
    nan = jnp.asarray(jnp.nan, p.y.dtype)
    scores = {k: out[i] for i, k in enumerate(wanted)}
    return {(m, w): scores.get((m, w), nan) for m in models for w in parts}


def _choice(bics, fitness_estimation):
    """The chosen family (`choose_family`), whether it is the physical one, and
    `chosen(spline_value, physical_value, linear_value)`, the chosen family's value.

    Between the families by BIC on the estimation data (FOE, the paper's criterion,
    still picks each family's orders): the choice never looks at the validation
    data, and a run-away spline candidate is already excluded. The spline model has
    ~30 parameters against the Kano model's 7, and FOE's fixed penalty let it win
    by fitting noise: on `paper_sim` (seeds 0-29) FOE chose it twice (seeds 11 and
    26, FOE within 1 % of the Kano model's) and both times its simulation ran away
    on the validation record (-67 and -197 %, against 83 and 48 % for the Kano
    model); on every other seed the Kano model won by either criterion.

    The linear valve (fitted anyway, as the verdict's null) is the third family: a
    stiction model must beat it. On 48 loops with processes drawn per loop
    (`make_diverse` of `benchmarks/calibrate_verdict.py`, seeds 0-7) the linear
    valve beat the chosen model by more than 5 points on the estimation data on 3;
    held out it gained 66.5 and 45.8 points on two integrating loops, whose Kano
    fits (with a noise model that integrates, which forgives a drifting level) scored
    -128 % and -31 % in simulation.

    A stiction family is eligible only if its scored simulation of the estimation
    part (initial state from the opening samples, as every score) is at least as
    good as the linear valve's, which it nests (S = J = 0): BIC compares each
    family's output error as its own fit computes it (its fitted initial
    conditions), and on integrating loops the two disagree. Of 48 loops with
    processes drawn per loop, deadband-5 kept a Kano model scoring -45.5 % on its
    own estimation data against the linear valve's +15 % held out. The reverse: the
    linear valve is not eligible when it simulates the estimation part worse than
    the data's mean while a stiction family does not (external-6 of the same loops:
    linear -142.9 %, Kano +45.0 %; held out -106.7 and +52.9 %)."""
    kind = choose_family(bics, fitness_estimation)
    physical, linear = kind == 1, kind == 2

    def chosen(spline_value, physical_value, linear_value):
        return jnp.where(linear, linear_value, jnp.where(physical, physical_value, spline_value))

    return kind, physical, linear, chosen


def _result_code(p: Prepared, relaxation_result, ph: _PhysicalFamily, physical, linear, bics) -> RESULTS:
    """The fit's outcome: a data code, else the chosen family's solver outcome.

    The output-error polish is a budgeted refinement that keeps the better of its
    start and its end, so only the relaxation's outcome counts."""
    res_spline = RESULTS.promote(relaxation_result)
    solver = RESULTS.where(physical, RESULTS.promote(ph.result), res_spline)
    solver = RESULTS.where(linear, RESULTS.successful, solver)  # a finite BIC: the fit is budgeted
    solver = RESULTS.where(jnp.isfinite(jnp.min(bics)), solver, RESULTS.not_converged)
    xk = Kano(ph.S, ph.J)(p.op)
    never = physical & jnp.all(jnp.where(p.w_est > 0, xk == xk[0], True))
    result = RESULTS.where(never, RESULTS.valve_never_moves, solver)
    result = RESULTS.where(p.const_pv, RESULTS.constant_pv, result)
    result = RESULTS.where(p.const_op, RESULTS.constant_op, result)
    result = RESULTS.where(p.too_short, RESULTS.too_short, result)
    return RESULTS.where(p.bad, RESULTS.nonfinite_data, result)


def _finish(p: Prepared, cand, phys: PhysicalFit | None, settings: Settings) -> LoopFit:
    """The rest of `estimate` from its stages' results: the chosen candidates, the
    verdict's null models, every score, the choice between the families and the
    result code. (`phys` is `None` without the physical family.)"""
    dtype = p.y.dtype
    s = _pick_spline(cand, settings.spline, p.count, dtype)
    lit, plit = _pick_paper(cand, settings.spline, p.count, s.counts)
    nb, na = _model_sizes(settings)
    none = Kano(jnp.zeros((), dtype), jnp.zeros((), dtype))
    m_spline, m_paper = _spline_models(p, s, lit, plit, settings, none, nb, na)
    ph = _physical_family(p, phys, settings, m_spline, nb, na)
    nulls = _null_models(p, settings, ph, none, nb, na)
    m_spline = _pad_model(m_spline, nulls.nb, nulls.na)
    m_paper = _pad_model(m_paper, nulls.nb, nulls.na)
    m_phys = _pad_model(ph.model, nulls.nb, nulls.na)
    models = {"paper": m_paper, "spline": m_spline, "phys": m_phys, "lin": nulls.linear, "db": nulls.deadband}
    f = _scores(p, models, settings, ph.foe)

    bics = jnp.stack([s.bic, ph.bic, nulls.bic])
    kind, physical, linear, chosen = _choice(bics, jnp.stack([f["spline", "est"], f["phys", "est"], f["lin", "est"]]))
    model = jax.tree.map(chosen, m_spline, m_phys, nulls.linear)
    fit_val = chosen(f["spline", "val"], f["phys", "val"], f["lin", "val"])
    fit_est = chosen(f["spline", "est"], f["phys", "est"], f["lin", "est"])
    band_spline = spline_band(s.fit.model.beta, s.knots[s.k], s.kmasks[s.k], p.lo, p.hi)
    band = chosen(band_spline, ph.S, 0.0)
    result = _result_code(p, s.fit.relaxation.result, ph, physical, linear, bics)

    i32 = jnp.int32
    return LoopFit(
        model=model,
        paper=m_paper,
        spline=m_spline,
        physical=m_phys,
        linear=nulls.linear,
        deadband=nulls.deadband,
        kind=kind.astype(i32),
        fitness=fit_val,
        fitness_estimation=fit_est,
        fitness_paper=f["paper", "val"],
        fitness_spline=f["spline", "val"],
        fitness_physical=f["phys", "val"],
        fitness_linear=f["lin", "val"],
        fitness_spline_estimation=f["spline", "est"],
        fitness_physical_estimation=f["phys", "est"],
        fitness_linear_estimation=f["lin", "est"],
        fitness_deadband=f["db", "val"],
        fitness_deadband_estimation=f["db", "est"],
        band_percent=band,
        S=ph.S,
        J=ph.J,
        S_interval=ph.S_interval,
        J_interval=ph.J_interval,
        direction_rule=jnp.where(kind > 0, 0, s.rule).astype(i32),
        num_knots=jnp.where(kind > 0, 0, s.counts[s.k]).astype(i32),
        order=chosen(s.order, ph.order, settings.physical.order).astype(i32),
        delay=chosen(s.fit.model.linear.delay, ph.delay, nulls.delay + 1).astype(i32),
        foe=s.foe_grid,
        candidate_fitness=cand.fitness,
        foe_spline=s.foe,
        foe_physical=ph.foe,
        foe_linear=nulls.foe,
        bic_spline=s.bic,
        bic_physical=ph.bic,
        bic_linear=nulls.bic,
        n_estimation=p.n_est.astype(i32),
        n_validation=p.n_val.astype(i32),
        op_range=jnp.stack([p.lo, p.hi]),
        relax_steps=s.fit.relaxation.num_steps.astype(i32),
        result=result,
    )


# Traces are counted (`eqx.debug.get_num_traces(_estimate_traced)`) so tests can check
# that new data of one shape never recompiles.
_estimate_traced = eqx.debug.assert_max_traces(_estimate, max_traces=None)
estimate = eqx.filter_jit(_estimate_traced)

