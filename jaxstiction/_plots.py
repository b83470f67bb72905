"""Pictures of one loop fit, in the spirit of the paper's Figs. 4-6 (and 8-10).

Matplotlib only, through `matplotlib.figure.Figure` and the Agg canvas: no `pyplot`,
no `matplotlib.use`, no `rcParams` edits, so calling this never changes the user's
global matplotlib state and works without a display.
"""

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ._drawing import BOX, C_CLEAN, C_CLOSE, C_MEAS, C_MODEL, C_OPEN, C_PAPER, C_VAL, DPI, figure as _figure, SIZE


ZOOM = 200  # samples shown in the zoomed model-fit panel


def write_fit_figures(result, out_dir, *, validation_start=None, noise_free=None) -> list[Path]:
    """Write the pictures of a loop fit as PNG files into `out_dir` (created if needed).

    **Arguments:**

    - `result`: a [`jaxstiction.LoopFit`][] (or any object with the same fields).
    - `out_dir`: folder for the files.
    - `validation_start`: sample index where the validation part of the record starts;
        when given, that part is shaded in the time plots.
    - `noise_free`: optional noise-free PV (simulation studies), drawn thinly in the
        model-fit figure.

    **Returns:**

    The written paths, in this order: `valve_curve.png` (estimated stiction
    nonlinearity, paper Fig. 4/8), `step_response.png` (linear model, Fig. 5/9),
    `model_fit.png` (measured vs simulated PV, Fig. 6/10) and `op_pv.png` (OP and PV
    against time and PV against OP).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = [
        ("valve_curve.png", _valve_curve(result)),
        ("step_response.png", _step_response(result)),
        ("model_fit.png", _model_fit(result, validation_start, noise_free)),
        ("op_pv.png", _op_pv(result, validation_start)),
    ]
    paths = []
    for name, fig in figures:
        path = out / name
        fig.tight_layout()  # on this figure's own Agg canvas, not via pyplot
        fig.savefig(path, dpi=DPI)
        paths.append(path)
    return paths


def _crossing(u, f, level):
    """OP at which curve `f(u)` crosses `level` (the middle crossing if several)."""
    s = np.sign(f - level)
    idx = np.flatnonzero(np.diff(s) != 0)
    if idx.size == 0:
        return None
    i = idx[len(idx) // 2]
    t = (level - f[i]) / (f[i + 1] - f[i])
    return u[i] + t * (u[i + 1] - u[i])


def _time(result, n=None):
    n = len(result.pv) if n is None else n
    return np.arange(n) * float(result.ts)


def _arrow_along(ax, u, f, frac, reverse, color):
    """An arrowhead on the curve `(u, f)` at fraction `frac` of it, pointing along the
    direction of travel (decreasing OP when `reverse`)."""
    n = len(u)
    i = int(np.clip(round(frac * (n - 1)), 1, n - 2))
    j0, j1 = (i + 1, i - 1) if reverse else (i - 1, i + 1)
    ax.annotate(
        "",
        xy=(u[j1], f[j1]),
        xytext=(u[j0], f[j0]),
        arrowprops=dict(arrowstyle="-|>", color=color, lw=1.5, mutation_scale=16),
    )


def _interval(iv):
    return "" if iv is None else f" [{iv[0]:.2f}, {iv[1]:.2f}]"


def _valve_curve(result) -> Figure:
    u = np.asarray(result.valve_u, float)
    up = np.asarray(result.valve_up, float)
    down = np.asarray(result.valve_down, float)
    fig = _figure()
    ax = fig.add_subplot()
    lo, hi = float(np.nanmin(u)), float(np.nanmax(u))
    ax.plot([lo, hi], [lo, hi], color="0.6", ls=":", lw=1.0, label="ideal valve (no stiction)")
    ax.plot(u, up, color=C_OPEN, lw=2.0, label="opening (OP rising, ascent branch)")
    ax.plot(u, down, color=C_CLOSE, lw=2.0, label="closing (OP falling, descent branch)")
    for frac in (0.3, 0.7):
        _arrow_along(ax, u, up, frac, reverse=False, color=C_OPEN)
        _arrow_along(ax, u, down, frac, reverse=True, color=C_CLOSE)

    band = result.band_percent
    band_ok = band is not None and np.isfinite(band)
    if band_ok and result.model_kind == "spline":
        # the apparent band is the loop's horizontal width at mid-height
        level = 0.5 * (min(up.min(), down.min()) + max(up.max(), down.max()))
        a, d = _crossing(u, up, level), _crossing(u, down, level)
        if a is not None and d is not None:
            ax.annotate("", xy=(a, level), xytext=(d, level), arrowprops=dict(arrowstyle="<->", color="0.25", lw=1.2))
            ax.text(0.5 * (a + d), level, "band", ha="center", va="bottom", fontsize=8, color="0.25")

    lines = [f"apparent band = {band:.1f} % of OP" if band_ok else "apparent band: not found"]
    if result.S is not None:
        kano = f"Kano S = {result.S:.2f}{_interval(result.S_interval)}"
        if result.J is not None:
            kano += f", J = {result.J:.2f}{_interval(result.J_interval)}"
        lines.append(kano)
    kind = f"chosen model: {result.model_kind}"
    if result.model_kind == "spline":
        kind += f" ({result.num_knots} knots, '{result.direction_rule}' direction rule)"
    lines.append(kind)
    ax.text(0.98, 0.04, "\n".join(lines), transform=ax.transAxes, ha="right", va="bottom", fontsize=9, bbox=BOX)

    ax.set_xlabel("controller output OP (% of span)")
    ax.set_ylabel("valve position (% of travel)")
    ax.set_title(f"{result.name}: estimated stiction nonlinearity ({result.model_kind} model)")
    ax.legend(loc="upper left", fontsize=9)
    ax.grid(alpha=0.3)
    return fig


def _step_response(result) -> Figure:
    step = np.asarray(result.step, float)
    t = _time(result, len(step))
    ts = float(result.ts)
    fig = _figure()
    ax = fig.add_subplot()
    ax.plot(t, step, color=C_MODEL, lw=1.8, drawstyle="steps-post", label="linear model")
    ax.plot(t, step, "o", color=C_MODEL, ms=2.5)
    if len(step):
        ax.axhline(step[-1], color="0.5", ls="--", lw=1.0, label=f"value at {t[-1]:g} s: {step[-1]:.3g}")
    if result.delay:
        ax.axvline(
            result.delay * ts,
            color="0.4",
            ls=":",
            lw=1.0,
            label=f"delay {result.delay} samples = {result.delay * ts:g} s",
        )
    ax.axhline(0.0, color="0.7", lw=0.8)
    ax.set_xlabel("time after a 1 % step in valve position (s)")
    ax.set_ylabel("PV change (PV units per % of valve travel)")
    ax.set_title(
        f"{result.name}: step response of the linear model (order {result.order}, delay {result.delay} samples)"
    )
    ax.legend(loc="lower right", fontsize=9)
    ax.grid(alpha=0.3)
    return fig


def _shade(ax, result, validation_start):
    """Shade the validation part and label both parts at the top of `ax`."""
    if validation_start is None:
        return
    ts = float(result.ts)
    start, end = validation_start * ts, len(result.pv) * ts
    ax.axvspan(start, end, color=C_VAL, alpha=0.15, lw=0)
    top = ax.get_xaxis_transform()  # x in data, y in axes fraction
    ax.text(start, 0.97, " validation \u2192", transform=top, ha="left", va="top", fontsize=8, color="0.3")
    if validation_start > 0:
        ax.text(start, 0.97, "\u2190 estimation ", transform=top, ha="right", va="top", fontsize=8, color="0.3")


def _headroom(ax, frac=0.22):
    """Raise the top y limit so a legend fits above the data."""
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo, hi + frac * (hi - lo))


RUNAWAY = 0.01  # share of samples outside the measured PV's range that sends a curve to its own panel


def _model_fit(result, validation_start, noise_free) -> Figure:
    """Measured PV against the chosen model's simulation (and the noise-free PV when
    known): the whole record, then the first `ZOOM` samples of the scored part.

    Axis limits come from the measured PV, so a curve that runs away cannot flatten
    the picture. The paper's literal method often diverges on new data; when it
    leaves that range on more than `RUNAWAY` of the samples it is drawn in a third
    panel of its own (symmetric-log axis), not over the data, where its clipped
    swings would hide the fit."""
    pv = np.asarray(result.pv, float)
    n = len(pv)
    t = _time(result, n)
    scored = "validation" if result.n_validation > 0 else "estimation data"
    first = int(result.n_estimation) if result.n_validation > 0 else 0
    stop = min(first + ZOOM, n)
    clean = None if noise_free is None else np.asarray(noise_free, float)
    paper = np.asarray(result.pv_sim_paper, float)
    sim = np.asarray(result.pv_sim, float)
    span = float(np.ptp(pv)) or 1.0
    lo_y, hi_y = float(pv.min()) - 0.15 * span, float(pv.max()) + 0.15 * span

    def outside(c):
        return (c < lo_y) | (c > hi_y)  # NaN (a method not run) is not outside

    has_paper = bool(np.any(np.isfinite(paper)))
    runaway = has_paper and float(np.mean(outside(paper) | ~np.isfinite(paper))) > RUNAWAY
    paper_label = f"paper's method ({result.fitness_paper:.1f} %)"

    if runaway:
        fig = _figure((SIZE[0], 1.75 * SIZE[1]))
        ax, zoom, own = fig.subplots(3, 1, height_ratios=[1, 1, 0.55])
    else:
        fig = _figure((SIZE[0], 1.5 * SIZE[1]))
        ax, zoom = fig.subplots(2, 1, height_ratios=[1, 1])
    for a, part, full in ((ax, slice(0, n), True), (zoom, slice(first, stop), False)):
        if full:
            _shade(a, result, validation_start)
        a.plot(t[part], pv[part], color=C_MEAS, lw=0.9 if full else 1.2, label="measured PV")
        if has_paper and not runaway:
            a.plot(t[part], paper[part], color=C_PAPER, lw=1.0, ls="--", label=paper_label)
        a.plot(
            t[part],
            sim[part],
            color=C_MODEL,
            lw=1.2 if full else 1.6,
            label=f"{result.model_kind} model ({result.fitness:.1f} %)",
        )
        if clean is not None:  # on top: the thin line the model should follow
            a.plot(t[part], clean[part], color=C_CLEAN, lw=0.8, label="noise-free PV")
        a.set_ylabel("PV (engineering units)")
        a.grid(alpha=0.3)
    ax.set_title(f"{result.name}: model fit, fitness {result.fitness:.1f} % ({scored})")
    for a in (ax, zoom):
        a.set_ylim(lo_y, hi_y)
        _headroom(a)
    if np.any(outside(sim)):
        ax.text(0.01, 0.02, "the model leaves the plotted range (limits from the measured PV)",
                transform=ax.transAxes, fontsize=8, color="0.3", va="bottom")
    zoom.legend(loc="upper center", fontsize=8, ncol=4)
    zoom.set_title(f"first {stop - first} samples of the scored part ({scored})", fontsize=10)
    if runaway:
        _shade(own, result, validation_start)
        own.plot(t, pv, color=C_MEAS, lw=0.7, label="measured PV")
        own.plot(t, paper, color=C_PAPER, lw=0.9, ls="--", label=paper_label)
        own.set_yscale("symlog", linthresh=max(float(np.max(np.abs(pv))), 1e-12))
        own.set_title("the paper's literal method runs away from the measured PV's range: its own axis "
                      "(symmetric log)", fontsize=10)
        own.set_ylabel("PV")
        own.legend(loc="lower left", fontsize=8, ncol=2)
        own.grid(alpha=0.3)
        own.set_xlabel("time (s)")
    else:
        zoom.set_xlabel("time (s)")
    return fig


def _op_pv(result, validation_start) -> Figure:
    op = np.asarray(result.op, float)
    pv = np.asarray(result.pv, float)
    t = _time(result, len(pv))
    fig = _figure((SIZE[0] * 1.25, SIZE[1] * 1.15))
    grid = fig.add_gridspec(2, 2, width_ratios=[1.8, 1])
    ax_op = fig.add_subplot(grid[0, 0])
    ax_pv = fig.add_subplot(grid[1, 0], sharex=ax_op)
    ax_xy = fig.add_subplot(grid[:, 1])

    _shade(ax_op, result, validation_start)
    ax_op.plot(t, op, color="tab:purple", lw=0.9, label="OP")
    ax_op.set_ylabel("OP (% of span)")
    ax_op.set_title(f"{result.name}: controller output and process output")
    ax_op.tick_params(labelbottom=False)
    _shade(ax_pv, result, validation_start)
    ax_pv.plot(t, pv, color=C_MEAS, lw=0.9)
    ax_pv.set_ylabel("PV (engineering units)")
    ax_pv.set_xlabel("time (s)")
    for a in (ax_op, ax_pv):
        a.grid(alpha=0.3)
        if validation_start is not None:
            _headroom(a, 0.15)

    ax_xy.plot(op, pv, color="0.75", lw=0.4, zorder=1)
    pts = ax_xy.scatter(op, pv, c=t, s=4, cmap="viridis", zorder=2)
    fig.colorbar(pts, ax=ax_xy, label="time (s)")
    ax_xy.set_xlabel("OP (% of span)")
    ax_xy.set_ylabel("PV (engineering units)")
    ax_xy.set_title("PV against OP")
    ax_xy.grid(alpha=0.3)
    return fig


def write_diagnosis_figures(diagnosis, out_dir, *, name: str = "loop", ts: float = 1.0) -> list[Path]:
    """Pictures of a [`jaxstiction.Diagnosis`][] into `out_dir`: `diagnosis.png` with
    the nominal simulation residual against time (located windows shaded, held-out
    part marked), its spectrum (narrow lines marked), PV against OP, and the held-out
    fit before (nominal) and after (diagnosed model)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = diagnosis.series
    op, pv, z = (np.asarray(s[k], float) for k in ("op", "pv", "residual"))
    n, n_est = len(pv), diagnosis.n_estimation
    t = np.arange(n) * ts
    fig = _figure((SIZE[0] * 1.5, SIZE[1] * 1.6))
    ax = fig.subplots(2, 2)
    a = ax[0, 0]
    a.plot(t, z, color=C_MEAS, lw=0.6)
    for w0, w1 in diagnosis.located.get("time_windows") or []:
        a.axvspan(w0 * ts, w1 * ts, color="tab:orange", alpha=0.25, lw=0)
    a.axvspan(n_est * ts, n * ts, color=C_VAL, alpha=0.15, lw=0, label="held out")
    a.set_title("residual of the nominal simulation (located windows shaded)")
    a.set_xlabel("time (s)")
    a.set_ylabel("PV - simulation")
    a.legend(loc="upper right", fontsize=8)
    a.grid(alpha=0.3)
    a = ax[0, 1]
    spec = s["spectrum"]
    f, P = np.asarray(spec["frequency"]), np.asarray(spec["power"])
    a.semilogy(f[1:] / ts, P[1:], color=C_MEAS, lw=0.8)
    for line in spec["lines"]:
        a.axvline(line["frequency"] / ts, color=C_MODEL, lw=0.8, ls="--")
        a.annotate(f"period {line['period_samples'] * ts:.3g} s", (line["frequency"] / ts, P.max()), fontsize=8,
                   color=C_MODEL, rotation=90, va="top", ha="right")
    a.set_title("residual spectrum (estimation part)")
    a.set_xlabel("frequency (Hz)" if ts != 1.0 else "frequency (cycles per sample)")
    a.grid(alpha=0.3, which="both")
    a = ax[1, 0]
    a.plot(op, pv, color="0.75", lw=0.4)
    a.scatter(op, pv, c=t, s=3, cmap="viridis")
    a.set_xlabel("OP (% of span)")
    a.set_ylabel("PV")
    a.set_title("PV against OP")
    a.grid(alpha=0.3)
    a = ax[1, 1]
    h = slice(n_est, n)
    a.plot(t[h], pv[h], color=C_MEAS, lw=0.7, label="measured")
    a.plot(t[h], np.asarray(s["sim_nominal"])[h], color=C_PAPER, lw=0.9,
           label=f"nominal ({diagnosis.heldout_nominal['fitness']:.1f} %)")
    acc = [f_ for f_ in diagnosis.findings if f_.accepted and f_.model is not None]
    after = acc[0].heldout_after["fitness"] if acc else diagnosis.heldout_nominal["fitness"]
    a.plot(t[h], np.asarray(s["sim_after"])[h], color=C_MODEL, lw=0.9,
           label=f"with {diagnosis.verdict} ({after:.1f} %)")
    lo, hi = np.percentile(pv[h], [0.5, 99.5])
    pad = 0.3 * (hi - lo + 1e-12)
    a.set_ylim(lo - pad, hi + pad)
    a.set_title("held-out fit, before and after")
    a.set_xlabel("time (s)")
    a.legend(loc="upper right", fontsize=8)
    a.grid(alpha=0.3)
    fig.suptitle(f"{name}: verdict {diagnosis.verdict}")
    fig.tight_layout()
    path = out / "diagnosis.png"
    fig.savefig(path, dpi=DPI)
    return [path]


