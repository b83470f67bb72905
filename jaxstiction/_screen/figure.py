"""One loop of a screen on one page (matplotlib, on its own Agg canvas)."""

from pathlib import Path

import numpy as np

from .._drawing import C_CLOSE, C_MEAS, C_MODEL, C_OPEN, C_VAL, figure


def write_screen_loop_figure(entry: dict, path) -> Path:
    """One loop of a screen on one page: the fitted valve curve, the measured and
    simulated PV (held-out part shaded), and PV against OP, headed by the verdict.
    `entry` is a screen entry with its `figure` arrays."""
    f = entry["figure"]
    op, pv, sim = (np.asarray(f[k], float) for k in ("op", "pv", "pv_sim"))
    ts = float(entry.get("Ts") or 1.0)
    t = np.arange(pv.shape[0]) * ts
    fig = figure((11.0, 6.0))
    grid = fig.add_gridspec(2, 2, width_ratios=[1, 1.6])
    ax_v = fig.add_subplot(grid[0, 0])
    ax_xy = fig.add_subplot(grid[1, 0])
    ax_fit = fig.add_subplot(grid[:, 1])

    u, up, dn = (np.asarray(f[k], float) for k in ("valve_u", "valve_up", "valve_down"))
    ax_v.plot(u, up, color=C_OPEN, lw=1.3, label="OP rising")
    ax_v.plot(u, dn, color=C_CLOSE, lw=1.3, ls="--", label="OP falling")
    ax_v.set_xlabel("OP (% of span)")
    ax_v.set_ylabel("valve position (%)")
    ax_v.set_title(f"valve ({f['kind']} model)")
    ax_v.legend(fontsize=8, loc="upper left")
    ax_v.grid(alpha=0.3)

    ax_xy.plot(op, pv, color="0.6", lw=0.4)
    ax_xy.set_xlabel("OP (% of span)")
    ax_xy.set_ylabel("PV")
    ax_xy.set_title("PV against OP")
    ax_xy.grid(alpha=0.3)

    n_est = int(f["n_estimation"])
    if n_est < pv.shape[0]:
        ax_fit.axvspan(t[n_est], t[-1], color=C_VAL, alpha=0.15, lw=0, label="held out")
    ax_fit.plot(t, pv, color=C_MEAS, lw=0.8, label="measured PV")
    ax_fit.plot(t, sim, color=C_MODEL, lw=0.9, label="simulated PV")
    lo, hi = np.percentile(pv, [0.5, 99.5])
    pad = 0.3 * (hi - lo if hi > lo else 1.0)
    ax_fit.set_ylim(lo - pad, hi + pad)  # a run-away simulation must not flatten the data
    ax_fit.set_xlabel("time (s)")
    ax_fit.set_ylabel("PV")
    ax_fit.legend(fontsize=8, loc="upper right")
    ax_fit.grid(alpha=0.3)

    p = entry.get("stiction_probability")
    prob = f"P {p:.2f}" if p is not None else "P –"
    if entry["stiction_detected"]:
        verdict = ("STICTION" if entry.get("slip_identified") else "STICTION (no slip seen: a deadband fits as well)")
    elif entry.get("verdict") == "inconclusive":
        verdict = f"inconclusive ({entry.get('gate')})"
    else:
        verdict = f"no stiction (cause: {entry.get('cause')})"
    verdict = f"{verdict}, {prob}"
    band = entry.get("band_percent")
    ev = entry.get("evidence")
    fit_ = entry.get("fitness")
    fig.suptitle(f"{entry['name']}: {verdict}; band {band if band is not None else '–'} % of OP; "
                 f"Kano vs linear valve {ev if ev is not None else '–'} points held out; fitness "
                 f"{fit_ if fit_ is not None else '–'} %", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    return path
