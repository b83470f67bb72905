"""Pictures of the what-if step (matplotlib, each on its own Agg canvas): the loop
replayed as is, repaired and compensated, side by side; a compensator's design; a
valve's trend across recordings."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._drawing import C_CLOSE, C_MEAS, C_MODEL, C_OPEN, figure
from .report import compensator_words


C_REPAIRED = "tab:green"
C_COMPENSATED = "tab:purple"


def write_whatif_figure(name: str, ts: float, traces: dict, entry: dict, path) -> Path:
    """One loop's what-if on one page: SP − PV as is, repaired and compensated (three
    panels on one scale, the numbers in their titles) and the valve's travel in each.
    `traces`: NumPy arrays `sp`, `pv_as_is`, `pv_repaired`, `pv_compensated`,
    `valve_as_is`, `valve_repaired`, `valve_compensated`, `op_compensated` and the
    window start `start`; `entry`: the `whatif` JSON object."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sp = np.asarray(traces["sp"], float)
    t = np.arange(sp.shape[0]) * ts
    start = int(traces.get("start", 0))
    fig = figure((12.0, 7.0))
    grid = fig.add_gridspec(2, 3, height_ratios=[1.3, 1])
    errors = {s: sp - np.asarray(traces[f"pv_{s}"], float) for s in ("as_is", "repaired", "compensated")}
    lo = min(np.percentile(e[start:], 0.5) for e in errors.values()) if start < sp.shape[0] else -1
    hi = max(np.percentile(e[start:], 99.5) for e in errors.values()) if start < sp.shape[0] else 1
    pad = 0.1 * (hi - lo if hi > lo else 1.0)
    titles = {"as_is": ("as is (fitted valve)", C_MEAS), "repaired": ("repaired (linear valve)", C_REPAIRED),
              "compensated": (f"compensated ({(entry.get('compensator') or {}).get('kind', 'knocker')})",
                              C_COMPENSATED)}
    for i, (s, (title, color)) in enumerate(titles.items()):
        ax = fig.add_subplot(grid[0, i])
        ax.plot(t, errors[s], color=color, lw=0.7)
        if start > 0:
            ax.axvspan(t[0], t[min(start, t.shape[0] - 1)], color="0.85", lw=0, label="not read (start)")
            ax.legend(fontsize=7, loc="upper right")
        std = entry.get(f"error_std_{s}")
        ax.set_title(f"{title}\nstd(SP − PV) = {std:.3g}" if std is not None else title, fontsize=9)
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_xlabel("time (s)")
        if i == 0:
            ax.set_ylabel("SP − PV")
        ax.grid(alpha=0.3)
        axv = fig.add_subplot(grid[1, i])
        if s == "compensated":
            axv.plot(t, np.asarray(traces["op_compensated"], float), color="0.7", lw=0.5, label="OP + compensator")
        axv.plot(t, np.asarray(traces[f"valve_{s}"], float), color=color, lw=0.9, label="valve")
        travel, rev = entry.get(f"travel_{s}"), entry.get(f"reversals_{s}")
        if travel is not None:
            axv.set_title(f"travel {travel:.0f} %/h, {rev:.0f} reversals/h", fontsize=9)
        axv.set_xlabel("time (s)")
        if i == 0:
            axv.set_ylabel("valve (% of span)")
        axv.legend(fontsize=7, loc="upper right")
        axv.grid(alpha=0.3)
    b = entry.get("benefit")
    head = f"{name}: what a repair would buy"
    if b is not None:
        iv = entry.get("error_std_repaired_interval")
        head += f": std(SP − PV) {entry['error_std_as_is']:.3g} → {entry['error_std_repaired']:.3g}"
        if iv:
            head += f" [{iv[0]:.3g}, {iv[1]:.3g}]"
    fig.suptitle(head, fontsize=11)
    fig.tight_layout()
    fig.savefig(path)
    return path


def write_compensation_figure(name: str, ts: float, sp, c, payload: dict, path) -> Path:
    """A compensator's design on one page: SP − PV as is, compensated and repaired,
    and OP with the compensator added. `c`: an unbatched `Compensation`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sp = np.asarray(sp, float)
    t = np.arange(sp.shape[0]) * ts
    fig = figure((11.0, 6.0))
    ax = fig.add_subplot(2, 1, 1)
    for key, label, color in (("pv_as_is", "as is", C_MEAS), ("pv_compensated", "compensated", C_COMPENSATED),
                              ("pv_repaired", "repaired", C_REPAIRED)):
        ax.plot(t, sp - np.asarray(getattr(c, key), float), lw=0.7, color=color, label=label)
    ax.set_ylabel("SP − PV")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    k = payload["compensator"]
    ax.set_title(f"{name}: {compensator_words(k)}: std(SP − PV) {payload['error_std_as_is']:.3g} → "
                 f"{payload['error_std_compensated']:.3g} (repaired {payload['error_std_repaired']:.3g})", fontsize=9)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax)
    ax2.plot(t, np.asarray(c.op_compensated, float), color=C_COMPENSATED, lw=0.6, label="OP + compensator")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("OP (% of span)")
    ax2.set_title(f"valve travel {payload['travel_as_is']:.0f} → {payload['travel_compensated']:.0f} % of span per "
                  "hour", fontsize=9)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    return path


def write_trend_figure(tag: str, rows: list[dict], path) -> Path:
    """A valve's S and J with their intervals per recording, in order."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = figure((8.0, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(rows))
    for key, color, dx in (("S", C_OPEN, -0.08), ("J", C_CLOSE, 0.08)):
        y = np.array([np.nan if r[key] is None else r[key] for r in rows], float)
        iv = np.array([[np.nan, np.nan] if r[f"{key}_interval"] is None else r[f"{key}_interval"] for r in rows],
                      float)
        err = np.abs(np.stack([y - iv[:, 0], iv[:, 1] - y]))
        ax.errorbar(x + dx, y, yerr=err, fmt="o-", color=color, capsize=4, label=f"{key} (95 % interval)")
    for i, r in enumerate(rows):
        if r.get("grows"):
            ax.annotate("grows", (i, r["S"] or 0), textcoords="offset points", xytext=(0, 12), ha="center",
                        color=C_MODEL, fontsize=8)
    ax.set_xticks(x, [r["name"] for r in rows], rotation=30, fontsize=8)
    ax.set_ylabel("% of span")
    ax.set_title(f"valve {tag}: S and J per recording", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    return path
