"""What fixing the valve would buy, against the truth: simulated sticky loops whose
plant is known, fitted and replayed by `jaxstiction.whatif`, then the true plant run
again with a linear valve and with the designed knocker under the same noise and
setpoint.

    python benchmarks/whatif.py --set concealed --seeds 0-23 --estimator full   # (a), (c)
    python benchmarks/whatif.py --set concealed --seeds 0-23                    # the screen's fits
    python benchmarks/whatif.py --set fleet --seeds 0-49 --pad --no-oracle      # (b): ranking, 50 loops
    python benchmarks/whatif.py --set concealed --seeds 0-7 --design both       # grid against gradient
    python benchmarks/whatif.py --set concealed --seeds 0-49 --no-oracle --no-polish   # the refit without the polish
    python benchmarks/whatif.py --set concealed --seeds 0-49 --ceiling            # the best compensator on the truth
    python benchmarks/whatif.py --set concealed --seeds 0-49 --no-oracle --true-valve  # the valve known
    python benchmarks/whatif.py ... --json

Two sets of loops:

- `concealed`: the concealed-case process (q^-1 + 0.5 q^-2)/(1 - 1.5 q^-1 + 0.7 q^-2)
  around OP 50 with a Kano valve, S uniform on 1-10 % and J on 0-S; the detuned PI
  (kp 0.05, ki 0.01; even seeds) or the paper's tight one (kp 0.3, ki 0.01; odd
  seeds); the setpoint constant (seeds 0, 1 mod 4) or stepping every 300-600
  samples by up to +-10 (seeds 2, 3 mod 4); AR(1) noise (pole 0.9, std 0.2-2 PV
  units) at the output and a slowly wandering load (AR(1), pole 0.995, std 0.3-2 %)
  at the process input, so a loop with a constant setpoint cycles too. 500 samples
  of run-in, then 2000 recorded, with the setpoint. Ts = 1 s.
- `fleet`: `jaxstiction.internal.realistic_fleet(seeds, "stiction")`: processes,
  dead times (1-20 samples), tunings, setpoints, loads and historian effects drawn
  per loop (500-3000 samples).

Per loop: the fit (`--estimator screen`: the screen's `SCREEN_ESTIMATE`, what
`screen --whatif` replays; `full`: `Settings(use_spline=False)`, the Kano search of
`fit --whatif`), `whatif` (default settings), and the truth over the same samples
(from the what-if's `start`): the plant as recorded, with a linear valve, and with
the designed knocker. Also `oracle`: `whatif_model` of the true plant model (the
method with a perfect fit). Prints per loop (S and J: the plant's, the fit's, and
the ones replayed after the what-if's polish) and a summary: the share of loops whose
`error_std_repaired` is within +-15 % of the truth (min, median, which seeds miss),
Spearman's rho of predicted against true benefit (also over the loops the screen's
verdict calls sticky, the only ones `screen --whatif` ranks), and the share of a repair's
variability reduction that the knocker achieves on the true plant, with its travel.

`--ceiling` fits nothing: it runs each true plant with every compensator of a wide
grid (`CEILING_GRID`: knocks and constant reinforcement, amplitudes scaled by the
true S) and prints the best share of a repair's reduction reached with the valve
travel capped at 2, 5 and 20 times the as-is travel, and without a cap: what the
design could reach with the valve known exactly.
"""

from __future__ import annotations

import argparse
import json
import time

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _args import seeds_arg, seeds_text  # noqa: E402
from _gate import hard_gated  # noqa: E402

from jaxstiction import (  # noqa: E402
    CompensateSettings,
    Controller,
    estimate,
    Kano,
    KnockerGrid,
    make_loop,
    Settings,
    verdict,
    whatif,
    WhatIfSettings,
)
from jaxstiction.internal import (  # noqa: E402
    bucket_length,
    closed_loop,
    fleet_draw,
    FLEET_RUN_IN,
    grid_knockers,
    nominal_model,
    pad,
    realistic_fleet,
    release_programs_near_map_limit,
    SCREEN_ESTIMATE,
    whatif_model,
    with_valve,
)


RUN, N = 500, 2000


# ---------------------------------------------------------------------------- concealed


def _ar1(rng, n, pole, std):
    e = rng.standard_normal(n) * std * np.sqrt(1 - pole**2)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - pole**2)
    for t in range(1, n):
        x[t] = pole * x[t - 1] + e[t]
    return x


def _through_process(x):
    """`x` through (q^-1 + 0.5 q^-2)/(1 - 1.5 q^-1 + 0.7 q^-2) (a load at the input)."""
    y = np.zeros_like(x)
    for t in range(2, x.shape[0]):
        y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + x[t - 1] + 0.5 * x[t - 2]
    return y


class Concealed:
    """One concealed-case loop (see the module notes): `truth(S, J, knocker)` runs the
    plant over run-in and record and returns the recorded part."""

    def __init__(self, seed: int):
        rng = np.random.default_rng(seed)
        self.seed = seed
        self.S = float(rng.uniform(1, 10))
        self.J = float(rng.uniform(0, self.S))
        self.tight = seed % 2 == 1
        self.steps = (seed // 2) % 2 == 1
        self.kp, self.ki = (0.3, 0.01) if self.tight else (0.05, 0.01)
        r = np.zeros(RUN + N)
        if self.steps:
            t = RUN + 200
            while t < RUN + N:
                r[t:] += rng.uniform(-10, 10)
                t += int(rng.integers(300, 600))
        noise = _ar1(rng, RUN + N, 0.9, float(np.exp(rng.uniform(np.log(0.2), np.log(2.0)))))
        load = _ar1(rng, RUN + N, 0.995, float(rng.uniform(0.3, 2.0)))
        self.sp_full = r
        self.v_full = noise + _through_process(load)
        self.kind = f"{'tight' if self.tight else 'detuned'}/{'steps' if self.steps else 'constant'}"

    def plant(self, S=None, J=None):
        return nominal_model(chain=(Kano(self.S if S is None else S, self.J if J is None else J),))

    def truth(self, S=None, J=None, knocker=None):
        """`(op, pv, valve, sp)` of the recorded part of the plant run with valve
        `S`, `J` (default the plant's) and `knocker`."""
        plant = self.plant(S, J)
        ctrl = Controller(kp=jnp.asarray(self.kp), ki=jnp.asarray(self.ki))
        init = plant.rest_state(jnp.full((4,), 50.0))
        run = closed_loop(plant, ctrl, jnp.asarray(self.sp_full), jnp.asarray(self.v_full), init, 50.0, knocker)
        cut = slice(RUN, RUN + N)
        return np.asarray(run.op)[cut], np.asarray(run.pv)[cut], np.asarray(run.valve)[cut], self.sp_full[cut]

    def record(self):
        op, pv, _, sp = self.truth()
        return op, pv, sp, 1.0

    def truths(self, knockers):
        """`(pv, valve)` of the recorded part under each of a batch of `knockers`."""
        return _concealed_runs(self.plant(), jnp.asarray(self.kp), jnp.asarray(self.ki), jnp.asarray(self.sp_full),
                               jnp.asarray(self.v_full), knockers)


@jax.jit
def _concealed_runs(plant, kp, ki, sp, v, knockers):
    ctrl = Controller(kp=kp, ki=ki)
    init = plant.rest_state(jnp.full((4,), 50.0))

    def one(k):
        run = closed_loop(plant, ctrl, sp, v, init, 50.0, k)
        return run.pv[RUN:], run.valve[RUN:]

    return jax.vmap(one)(knockers)


# ---------------------------------------------------------------------------- fleet


def _fleet_loop(p, r, load, out, knock):
    """`jaxstiction._fleet._loop` with a knocker `(amplitude, width, period)` between
    the PI and the valve (amplitude 0: none)."""
    b, a, d, kp, ki, op0 = p["b"], p["a"], p["delay"], p["kp"], p["ki"], p["op0"]
    valve = Kano(p["S"], p["J"])
    amp, width, period = knock

    def body(carry, inputs):
        u1, e1, vs, xs, ys, sign, u_last, t = carry
        rt, lt, ot = inputs
        y = -jnp.dot(a[1:], ys) + jnp.dot(b, jnp.take(xs, d + jnp.arange(3)))
        pv = y + ot
        e = rt - pv
        u = jnp.clip(u1 + kp * (e - e1) + ki * e, 0.0, 100.0)
        start = jnp.mod(t, period) == 0
        moved = jnp.sign(u - u_last)
        sign = jnp.where(start & (moved != 0), moved, sign)
        u_last = jnp.where(start, u, u_last)
        uv = jnp.clip(u + jnp.where(jnp.mod(t, period) < width, amp * sign, 0.0), 0.0, 100.0)
        vs, v = valve.step(vs, uv)
        xs = jnp.concatenate([(v - op0 + lt)[None], xs[:-1]])
        ys = jnp.concatenate([y[None], ys[:-1]])
        return (u, e, vs, xs, ys, sign, u_last, t + 1), (u, pv, v)

    zero = jnp.zeros((), r.dtype)
    carry = (op0, zero, valve.init(op0), jnp.zeros((43,), r.dtype), jnp.zeros((3,), r.dtype), zero, op0, 0)
    _, (u, pv, v) = jax.lax.scan(body, carry, (r, load, out))
    return u, pv, v


_fleet_run = jax.jit(_fleet_loop)
_fleet_runs = jax.jit(jax.vmap(_fleet_loop, in_axes=(None, None, None, None, (0, 0, 0))))


class Fleet:
    """One `realistic_fleet` stiction draw; `truth` as `Concealed.truth` (before the
    historian: the plant's own PV)."""

    def __init__(self, seed: int, loop):
        self.seed, self.loop = seed, loop
        # the draw's signals come at the fleet's one length, so the truth's runs compile
        # once for the whole fleet (one program per record length exhausts the
        # process's memory maps over 50 loops)
        self.params, self.r, self.load, self.out, self.n, _ = fleet_draw(seed, "stiction")
        self.S, self.J = loop.S, loop.J
        self.kind = f"{'integrating' if loop.integrating else 'self-regulating'}, delay {loop.delay}" + (
            f", {'+'.join(h[0] for h in loop.historian)}" if loop.historian else "")

    def _params(self):
        p = {k: jnp.asarray(np.asarray(v, float)) for k, v in self.params.items()}
        p["delay"] = p["delay"].astype(jnp.int32)
        return p

    def truth(self, S=None, J=None, knocker=None):
        p = self._params()
        if S is not None:
            p["S"], p["J"] = jnp.asarray(S), jnp.asarray(J)
        knock = (0.0, 1.0, 2) if knocker is None else (knocker.amplitude, knocker.width, knocker.period)
        knock = (jnp.asarray(knock[0], float), jnp.asarray(knock[1], float), jnp.asarray(knock[2], jnp.int32))
        u, pv, v = _fleet_run(p, jnp.asarray(self.r), jnp.asarray(self.load), jnp.asarray(self.out), knock)
        cut = slice(FLEET_RUN_IN, FLEET_RUN_IN + self.n)
        return np.asarray(u)[cut], np.asarray(pv)[cut] + 50.0, np.asarray(v)[cut], self.r[cut] + 50.0

    def record(self):
        return self.loop.op, self.loop.pv, self.loop.sp, 1.0

    def truths(self, knockers):
        _, pv, v = _fleet_runs(self._params(), jnp.asarray(self.r), jnp.asarray(self.load), jnp.asarray(self.out),
                               (knockers.amplitude, knockers.width, knockers.period))
        cut = slice(FLEET_RUN_IN, FLEET_RUN_IN + self.n)
        return np.asarray(pv)[:, cut] + 50.0, np.asarray(v)[:, cut]

    def plant(self):
        return None  # the fleet's loops carry a load at the input: no LoopModel of them


# ---------------------------------------------------------------------------- the run


def spearman(x, y):
    rx = np.argsort(np.argsort(x)).astype(float)
    ry = np.argsort(np.argsort(y)).astype(float)
    return float(np.corrcoef(rx, ry)[0, 1])


def one_loop(case, settings: Settings, wset: WhatIfSettings, oracle: bool, designs=("grid",), padded=False,
             true_valve=False):
    op, pv, sp, ts = case.record()
    loop, bare = make_loop(op, pv, ts, sp=sp), make_loop(op, pv, ts)
    if padded:  # as the screen does: one compiled program per length bucket
        length = bucket_length(len(op))
        loop, bare = pad(loop, length), pad(bare, length)
    t0 = time.perf_counter()
    fit = estimate(bare, settings)
    jax.block_until_ready(fit.S)
    t1 = time.perf_counter()
    out = dict(seed=case.seed, kind=case.kind, S=case.S, J=case.J, S_fit=float(fit.S), J_fit=float(fit.J),
               seconds_fit=t1 - t0, gate_passes=not hard_gated(op, pv, sp),
               # the screen's verdict on this fit: `screen --whatif` ranks only the loops it calls sticky
               called_sticky=bool(verdict(fit, loop).stiction_detected))
    if true_valve:  # the valve known: the plant's S and J in the fit, its intervals moved along
        dS, dJ = case.S - fit.physical.chain[0].S, case.J - fit.physical.chain[0].J
        fit = eqx.tree_at(lambda f: (f.physical, f.S_interval, f.J_interval), fit,
                          (with_valve(fit.physical, case.S, case.J), fit.S_interval + dS, fit.J_interval + dJ))
    for design in designs:
        ws = eqx.tree_at(lambda s: s.compensate, wset, CompensateSettings(method=design))
        t1 = time.perf_counter()
        w = jax.tree.map(np.asarray, whatif(fit, loop, ws))
        t2 = time.perf_counter()
        start = int(w.start)
        sl = slice(start, None)
        _, pv_t, valve_t, sp_t = case.truth()
        _, pv_l, valve_l, _ = case.truth(0.0, 0.0)
        _, pv_k, valve_k, _ = case.truth(knocker=w.knocker)
        hours = (len(sp_t) - start) * ts / 3600.0

        def std(x):
            return float(np.std(x[sl])) if start < len(x) - 10 else float("nan")

        def travel(v):
            return float(np.sum(np.abs(np.diff(v[sl])))) / hours if start < len(v) - 10 else float("nan")

        true_asis, true_rep, true_comp = std(sp_t - pv_t), std(sp_t - pv_l), std(sp_t - pv_k)
        tag = "" if design == "grid" else f"_{design}"
        out.update({
            f"seconds_whatif{tag}": t2 - t1, f"start{tag}": start, f"enough{tag}": bool(w.enough),
            f"asis{tag}": float(w.as_is.error_std), f"rep{tag}": float(w.repaired.error_std),
            f"rep_lo{tag}": float(w.repaired_interval.error_std[0]),
            f"rep_hi{tag}": float(w.repaired_interval.error_std[1]), f"comp{tag}": float(w.compensated.error_std),
            f"true_asis{tag}": true_asis, f"true_rep{tag}": true_rep, f"true_comp{tag}": true_comp,
            f"true_travel_asis{tag}": travel(valve_t), f"true_travel_rep{tag}": travel(valve_l),
            f"true_travel_comp{tag}": travel(valve_k), f"travel_comp{tag}": float(w.compensated.travel),
            f"travel_asis{tag}": float(w.as_is.travel), f"pv_range{tag}": float(w.pv_range),
            f"knocker{tag}": [float(w.knocker.amplitude), int(round(float(w.knocker.width))),
                              int(w.knocker.period)],
            f"objective{tag}": float(w.objective),
            # the valve replayed: the fit's (or the plant's) after the what-if's polish
            f"S_whatif{tag}": float(w.S), f"J_whatif{tag}": float(w.J),
        })
    if oracle and case.plant() is not None:
        w = jax.tree.map(np.asarray, whatif_model(case.plant(), loop, jnp.full(2, jnp.nan), jnp.full(2, jnp.nan),
                                                  wset))
        _, pv_l, _, sp_t = case.truth(0.0, 0.0)
        st = int(w.start)
        out.update(oracle_rep=float(w.repaired.error_std),
                   oracle_true_rep=float(np.std((sp_t - pv_l)[st:])) if st < len(sp_t) - 10 else float("nan"))
    return out


CEILING_GRID = KnockerGrid(amplitudes=(0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.3), widths=(1, 2, 3, 5, 10),
                           periods=(2, 3, 4, 5, 6, 8, 10, 14, 20, 30, 50),
                           reinforcement=(0.1, 0.2, 0.3, 0.4, 0.45, 0.5, 0.55, 0.6, 0.8))
CEILING_CAPS = (2.0, 5.0, 20.0, np.inf)


def _cap_tag(cap) -> str:
    return "any" if np.isinf(cap) else f"{cap:g}"


def ceiling_loop(case) -> dict:
    """The best share of a repair's reduction in std(SP - PV) that any compensator of
    `CEILING_GRID` (amplitudes times the true S) reaches on the true plant, with the
    valve travel capped at each of `CEILING_CAPS` times the as-is travel."""
    _, pv_t, valve_t, sp = case.truth()
    _, pv_l, valve_l, _ = case.truth(0.0, 0.0)
    pts = CEILING_GRID.points()
    ks = grid_knockers(case.S, case.J, CompensateSettings(grid=CEILING_GRID))
    pv_k, valve_k = map(np.asarray, case.truths(ks))
    asis, rep = float(np.std(sp - pv_t)), float(np.std(sp - pv_l))
    travel0 = float(np.sum(np.abs(np.diff(valve_t))))
    share = (asis - np.std(sp[None] - pv_k, axis=1)) / (asis - rep)
    ratio = np.sum(np.abs(np.diff(valve_k, axis=1)), axis=1) / max(travel0, 1e-12)
    out = dict(seed=case.seed, kind=case.kind, S=case.S, J=case.J, true_asis=asis, true_rep=rep,
               travel_repaired=float(np.sum(np.abs(np.diff(valve_l)))) / max(travel0, 1e-12))
    for cap in CEILING_CAPS:
        ok = np.isfinite(share) & (ratio <= cap)
        i = int(np.argmax(np.where(ok, share, -np.inf)))
        tag = _cap_tag(cap)
        out[f"best_{tag}"] = float(share[i]) if ok.any() else float("nan")
        out[f"best_{tag}_at"] = [round(pts[i][0], 3), pts[i][1], pts[i][2], round(float(ratio[i]), 2)]
    return out


def ceiling_summary(rows) -> dict:
    res = {}
    for kind in sorted({r["kind"] for r in rows}) + ["all"]:
        sel = [r for r in rows if kind == "all" or r["kind"] == kind]
        res[kind] = {
            ("any" if np.isinf(c) else f"travel<={c:g}x"): dict(
                at_least_half=int(sum(r[f"best_{_cap_tag(c)}"] >= 0.5 for r in sel)), loops=len(sel),
                median=float(np.nanmedian([r[f"best_{_cap_tag(c)}"] for r in sel])))
            for c in CEILING_CAPS}
    return res


def summary(rows, designs) -> dict:
    """The figures over the loops the what-if could read (`enough`, and a finite
    truth over the same samples); `unusable` lists the others."""
    res = {"unusable": seeds_text([r["seed"] for r in rows if not (r["enough"] and np.isfinite(r["true_rep"]))])}
    rows = [r for r in rows if r["enough"] and np.isfinite(r["true_rep"])]
    err = np.array([r["rep"] / r["true_rep"] - 1 for r in rows])
    ok = np.abs(err) <= 0.15
    res["repaired"] = dict(loops=len(rows), within_15=int(np.sum(ok)), share=float(np.mean(ok)),
                           abs_error_min=float(np.nanmin(np.abs(err))),
                           abs_error_median=float(np.nanmedian(np.abs(err))),
                           missed=seeds_text([r["seed"] for r, o in zip(rows, ok) if not o]),
                           interval_covers=int(sum(r["rep_lo"] <= r["true_rep"] <= r["rep_hi"] for r in rows)))
    if "oracle_rep" in rows[0]:
        oe = np.array([r["oracle_rep"] / r["oracle_true_rep"] - 1 for r in rows])
        res["oracle"] = dict(within_15=int(np.sum(np.abs(oe) <= 0.15)),
                             abs_error_median=float(np.nanmedian(np.abs(oe))))
    pb = np.array([r["asis"] - r["rep"] for r in rows])
    tb = np.array([r["true_asis"] - r["true_rep"] for r in rows])
    rng_ = np.array([r["pv_range"] for r in rows])
    res["ranking"] = dict(spearman_benefit=spearman(pb, tb), spearman_benefit_percent=spearman(pb / rng_, tb / rng_))
    passes = np.array([r.get("gate_passes", True) for r in rows])
    if not passes.all():  # the screen ranks only loops its hard gates let through
        res["ranking"].update(gate_passes=int(passes.sum()),
                              spearman_benefit_gate_passes=spearman(pb[passes], tb[passes]),
                              within_15_gate_passes=int(np.sum(ok & passes)))
    called = np.array([r.get("called_sticky", True) for r in rows])
    if not called.all() and called.sum() > 2:  # what `screen --whatif` ranks
        res["ranking"].update(called_sticky=int(called.sum()),
                              spearman_benefit_called_sticky=spearman(pb[called], tb[called]),
                              within_15_called_sticky=int(np.sum(ok & called)))
    for design in designs:
        tag = "" if design == "grid" else f"_{design}"
        share = np.array([(r[f"true_asis{tag}"] - r[f"true_comp{tag}"]) / (r[f"true_asis{tag}"] - r[f"true_rep{tag}"])
                          for r in rows])
        extra = np.array([r[f"true_travel_comp{tag}"] / max(r[f"true_travel_asis{tag}"], 1e-12) for r in rows])
        res[f"compensator{tag}"] = dict(
            share_min=float(np.nanmin(share)), share_median=float(np.nanmedian(share)),
            at_least_half=int(np.sum(share >= 0.5)), loops=len(rows),
            missed=seeds_text([r["seed"] for r, s in zip(rows, share) if not s >= 0.5]),
            travel_ratio_median=float(np.nanmedian(extra)), travel_ratio_max=float(np.nanmax(extra)),
            objective_median=float(np.median([r[f"objective{tag}"] for r in rows])),
            seconds_whatif_median=float(np.median([r[f"seconds_whatif{tag}"] for r in rows[1:]] or [np.nan])))
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=("concealed", "fleet"), default="concealed")
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-23"))
    ap.add_argument("--estimator", choices=("screen", "full"), default="screen")
    ap.add_argument("--design", choices=("grid", "gradient", "both"), default="grid")
    ap.add_argument("--no-oracle", action="store_true", help="skip the whatif of the true plant model")
    ap.add_argument("--init-count", type=int, default=WhatIfSettings().init_count,
                    help="WhatIfSettings.init_count (candidate initial valve states per direction)")
    ap.add_argument("--no-refine", action="store_true",
                    help="WhatIfSettings(refine=False): replay the fit's process as fitted, not refitted")
    ap.add_argument("--no-polish", action="store_true",
                    help="WhatIfSettings(polish=False): refit the process on the fitted valve only")
    ap.add_argument("--pad", action="store_true",
                    help="pad each loop to the screen's length bucket (masked), so loops of many lengths share a "
                         "few compiled programs (the fleet)")
    ap.add_argument("--true-valve", action="store_true",
                    help="the plant's S and J in the fit before the what-if (the process still fitted)")
    ap.add_argument("--ceiling", action="store_true",
                    help="fit nothing: the best compensator of a wide grid on each true plant, by travel cap")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    settings = SCREEN_ESTIMATE if args.estimator == "screen" else Settings(use_spline=False)
    designs = ("grid", "gradient") if args.design == "both" else (args.design,)
    if args.set == "concealed":
        cases = [Concealed(s) for s in args.seeds]
    else:
        cases = [Fleet(s, lp) for s, lp in zip(args.seeds, realistic_fleet(args.seeds, "stiction"))]
    if args.ceiling:
        rows = []
        for c in cases:
            rows.append(ceiling_loop(c))
            if not args.json:
                r = rows[-1]
                print(f"seed {r['seed']:3d} {r['kind']:<22} S {r['S']:5.2f} J {r['J']:5.2f}  best share of a repair "
                      + ", ".join(f"{t}: {r[f'best_{t}']:.2f} at {r[f'best_{t}_at']}"
                                  for t in map(_cap_tag, CEILING_CAPS)),
                      flush=True)
        res = ceiling_summary(rows)
        res["set"], res["seeds"] = args.set, seeds_text(args.seeds)
        print(json.dumps({"summary": res, "loops": rows}) if args.json else json.dumps(res, indent=1))
        return
    rows = []
    for c in cases:
        wset = WhatIfSettings(init_count=args.init_count, refine=not args.no_refine, polish=not args.no_polish)
        r = one_loop(c, settings, wset, not args.no_oracle, designs, args.pad, args.true_valve)
        rows.append(r)
        release_programs_near_map_limit()  # each length bucket's fit and what-if hold ~7000 memory maps
        if not args.json:
            print(f"seed {r['seed']:3d} {r['kind']:<22} S {r['S']:5.2f}/{r['S_fit']:5.2f}/{r['S_whatif']:5.2f} J "
                  f"{r['J']:5.2f}/{r['J_fit']:5.2f}/{r['J_whatif']:5.2f}  start {r['start']:4d}  "
                  f"as-is {r['asis']:.3g}/{r['true_asis']:.3g}  repaired "
                  f"{r['rep']:.3g} [{r['rep_lo']:.3g}, {r['rep_hi']:.3g}] / true {r['true_rep']:.3g} "
                  f"({r['rep'] / r['true_rep'] - 1:+.1%})"
                  + (f" oracle {r['oracle_rep'] / r['oracle_true_rep'] - 1:+.1%}" if "oracle_rep" in r else "")
                  + f"  knocker {r['comp']:.3g}, true {r['true_comp']:.3g} (share "
                  f"{(r['true_asis'] - r['true_comp']) / (r['true_asis'] - r['true_rep']):.2f}, travel x"
                  f"{r['true_travel_comp'] / max(r['true_travel_asis'], 1e-12):.2f})"
                  + "".join(f"  {d}: share {(r[f'true_asis_{d}'] - r[f'true_comp_{d}']) / (r[f'true_asis_{d}'] - r[f'true_rep_{d}']):.2f} obj {r[f'objective_{d}']:.3f} {r[f'seconds_whatif_{d}']:.2f}s"  # noqa: E501
                            for d in designs if d != "grid")
                  + f"  ({r['seconds_fit']:.1f} + {r['seconds_whatif']:.2f} s)", flush=True)
    res = summary(rows, designs)
    res["set"], res["estimator"], res["seeds"] = args.set, args.estimator, seeds_text(args.seeds)
    res["init_count"], res["refine"], res["polish"] = args.init_count, not args.no_refine, not args.no_polish
    res["true_valve"] = args.true_valve
    if args.json:
        print(json.dumps({"summary": res, "loops": rows}))
    else:
        print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
