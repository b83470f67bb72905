"""Command line: `jaxstiction demo | fit | screen | diagnose | compensate | trend`.

Every command takes `--json` (exactly one JSON object on stdout, nothing else there)
and `--out DIR` (pictures and a report). Progress and messages go to stderr. Bad input
gives a one-line `error: ...` on stderr and exit status 2; data that can be used but
may mislead (an unevenly spaced time column) a one-line `warning: ...`.
"""

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path


EXIT_BAD_INPUT = 2
EXIT_INTERNAL = 1


def _log(msg):
    print(msg, file=sys.stderr, flush=True)


def _clean(obj):
    """JSON-safe: NaN/inf become null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def _emit(args, payload: dict, text: str):
    payload = _clean(payload)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").write_text(json.dumps(payload, indent=2) + "\n")
        (out / "report.txt").write_text(text + "\n")
    if args.json:
        sys.stdout.write(json.dumps(payload) + "\n")
    else:
        print(text)


def _figures(args, result, **kw):
    if not args.out:
        return []
    from ._plots import write_fit_figures

    return write_fit_figures(result, Path(args.out), **kw)


def _summary(r, head: str | None = None) -> str:
    """The text summary of a fit report; `head` replaces its first line (which counts
    the estimation and validation samples)."""
    lines = [
        head or f"loop {r.name}: {r.n_estimation} estimation + {r.n_validation} validation samples, Ts = {r.ts:g} s",
        (
            f"  model: spline valve, direction rule {r.direction_rule}, {r.num_knots} knots, "
            if r.model_kind == "spline"
            else "  model: linear valve (no stiction model beat it), "
            if r.model_kind == "linear"
            else "  model: physical (Kano) valve, "
        )
        + f"linear order {r.order}, delay {r.delay}",
        f"  fitness (34): {r.fitness:.2f} %  ({'validation' if r.n_validation else 'estimation data'}); "
        f"paper's literal method {r.fitness_paper:.2f} %",
        f"  apparent stiction band: {r.band_percent:.2f} % of OP",
    ]
    if r.S is not None:
        lines.append(
            f"  Kano fit: S = {r.S:.2f} [{r.S_interval[0]:.2f}, {r.S_interval[1]:.2f}], "
            f"J = {r.J:.2f} [{r.J_interval[0]:.2f}, {r.J_interval[1]:.2f}] % "
            f"(physical-model fitness {r.fitness_physical:.2f} %)"
        )
    lines += [f"  note: {n}" for n in r.notes]
    lines.append(f"  converged: {r.converged} (relaxation: {r.relax_steps} sweeps)")
    return "\n".join(lines)


def cmd_demo(args):
    from ._demo import paper_sim_case

    _log(f"demo: paper_sim scenario, seed {args.seed}: simulating and fitting (the first run in a new cache "
         "compiles, about a minute on 2 cores) ...")
    t0 = time.time()
    payload, vr, clean = paper_sim_case(args.seed)
    _log(f"demo: done in {time.time() - t0:.1f} s")
    # `vr` is the report re-targeted at the validation record (no estimation samples
    # of its own): say what was fitted and what was scored
    head = (f"loop {vr.name}: fitted on {payload['fit']['samples']['estimation']} estimation samples, "
            f"scored on an independent {vr.n_validation}-sample validation record, Ts = {vr.ts:g} s")
    text = "\n".join(
        [
            _summary(vr, head),
            "validation on an independent 1500-sample record (initial state estimated from its opening samples):",
            f"  fitness vs measured PV {payload['fitness_validation']:.2f} %, vs noise-free PV "
            f"{payload['fitness_noise_free']:.2f} %, ceiling {payload['ceiling']:.2f} %",
            f"  paper's literal method: {payload['fitness_paper_method']:.2f} % "
            f"(noise-free {payload['fitness_paper_method_noise_free']:.2f} %)",
        ]
    )
    _figures(args, vr, noise_free=clean)
    _emit(args, payload, text)
    return 0


# A record longer than this gets a note of what its fit costs: time and memory grow
# about linearly in the record, ~7.5 ms and ~5 KB per sample on the README's 2-core
# machine (a 54 000-sample fit: 400 s, 1.39 GB; README, *Cost*).
LONG_RECORD = 50_000


def _long_record_note(command: str, n: int, decimate: int) -> None:
    """Log what a fit of `n` samples costs when the record is long, and the way out."""
    if n <= LONG_RECORD:
        return
    minutes, gb = n * 7.5e-3 / 60, 0.9 + 5e-6 * n
    many = "each of its fits" if command == "diagnose" else "the fit"
    hint = ("if the loop moves slowly against its sampling time, "
            + ("a larger --decimate K" if decimate > 1 else "--decimate K") + " fits K times fewer samples")
    _log(f"{command}: note: {n} samples is a long record: on a 2-core machine {many} takes about "
         f"{minutes:.0f} min and {gb:.1f} GB of memory; {hint}")


def _decimated(args) -> str:
    return f" (decimated by {args.decimate})" if args.decimate > 1 else ""


def _decimate_field(args) -> dict:
    """`{"decimate": K}` in the JSON when the record was decimated, else nothing."""
    return {"decimate": args.decimate} if args.decimate > 1 else {}


def cmd_fit(args):
    import numpy as np

    from ._estimate.report import fit
    from ._estimate.settings import Settings
    from ._io.read import loop_name, read_loop
    from ._loop import decimate

    if not 0.0 <= args.validate < 1.0:  # bad options fail before the record is read
        raise ValueError(f"`--validate` must be a fraction in [0, 1), got {args.validate:g}")
    if args.pi and not args.whatif:
        raise ValueError("`--pi` gives the controller of the what-if: it needs --whatif")
    _pi(args)
    loop = decimate(read_loop(args.file, ts=args.ts, name=args.name), args.decimate)
    name = args.name if args.name is not None else loop_name(args.file)
    op, pv, ts = np.asarray(loop.op), np.asarray(loop.pv), float(loop.ts)
    _log(f"fit: {name}: {op.shape[0]} samples, Ts = {ts:g} s{_decimated(args)}; fitting ...")
    _long_record_note("fit", op.shape[0], args.decimate)
    t0 = time.time()
    settings = None if args.max_delay is None else Settings().with_max_delay(args.max_delay)
    r = fit(op, pv, ts=ts, validate=args.validate, name=name, settings=settings)
    _log(f"fit: done in {time.time() - t0:.1f} s")
    if args.json:
        for n in r.notes:
            _log(f"fit: note: {n}")
    _figures(args, r, validation_start=r.n_estimation if r.n_validation else None)
    payload, text = {**r.to_json(), **_decimate_field(args)}, _summary(r)
    if args.whatif:
        entry = _whatif_of(args, r.fit, loop, name)
        payload["whatif"] = entry
        text += "\n" + _whatif_text(entry)
    _emit(args, payload, text)
    return 0


def _pi(args):
    """`--pi GAIN,TI` as `(gain, integral time)`, checked before any record is read;
    `None` without it (the controller is identified)."""
    if not getattr(args, "pi", None):
        return None
    try:
        gain, ti = (float(v) for v in args.pi.split(","))
    except ValueError:
        raise ValueError(f"`--pi` must be GAIN,INTEGRAL_TIME (two numbers, the integral time in seconds), "
                         f"got {args.pi!r}") from None
    if not (ti > 0 and gain != 0 and math.isfinite(gain) and math.isfinite(ti)):
        raise ValueError(f"`--pi` needs a finite non-zero gain and an integral time > 0 s, got {args.pi!r}")
    return gain, ti


def _controller(args, ts: float):
    """The controller `--pi GAIN,TI` gives, or `None` (identify it)."""
    pi = _pi(args)
    if pi is None:
        return None
    from ._control.controller import Controller

    return Controller.pi(pi[0], pi[1], ts)


def _whatif_of(args, fit, loop, name: str) -> dict:
    """`fit --whatif`: the `whatif` object of one fitted loop, and its picture in `--out`."""
    import jax
    import numpy as np

    from ._programs import exported_call
    from ._whatif.report import whatif_json
    from ._whatif.settings import WhatIfSettings
    from ._whatif.whatif import whatif

    settings = WhatIfSettings()
    ts = float(loop.ts)
    controller = _controller(args, ts)
    _log(f"fit: {name}: closing the fitted loop again (as is, repaired, compensated) ...")
    t0 = time.time()
    # from its exported program: a new process loads it instead of tracing it again
    w = jax.tree.map(np.asarray, exported_call("whatif-one", lambda f, lp, c: whatif(f, lp, settings, controller=c),
                                               fit, loop, controller, static=repr(settings)))
    _log(f"fit: what-if done in {time.time() - t0:.1f} s")
    entry = whatif_json(w, ts, settings)
    if args.out:
        from ._whatif.figure import write_whatif_figure

        n = int(np.asarray(loop.op).shape[0])
        sp = np.asarray(loop.setpoint)
        sp = sp if np.all(np.isfinite(sp)) else np.full(n, float(np.mean(np.asarray(loop.pv))))
        traces = {"sp": sp, "start": int(w.start), **{f"{q}_{s}": getattr(w, f"{q}_{s}") for q in ("pv", "valve", "op")
                                                      for s in ("as_is", "repaired", "compensated")}}
        write_whatif_figure(name, ts, traces, entry, Path(args.out) / "whatif.png")
    return entry


def _whatif_text(e: dict) -> str:
    """The text summary of a `whatif` object."""
    from ._whatif.report import compensator_words

    def f(v, nd=3):
        return "–" if v is None else f"{v:.{nd}g}"

    iv = e.get("error_std_repaired_interval")
    k, c = e["compensator"], e["controller"]
    lines = [
        "  what a repair would buy (the fitted loop replayed under the disturbance it met):",
        f"    std(SP - PV): as is {f(e['error_std_as_is'])}, repaired {f(e['error_std_repaired'])}"
        + (f" [{f(iv[0])}, {f(iv[1])}]" if iv else "") + f", compensated {f(e['error_std_compensated'])}"
        f" (recorded {f(e['error_std_recorded'])}); benefit {f(e['benefit'])}"
        + (f" ({f(e['benefit_percent_of_range'])} % of the PV range)" if e.get("benefit_percent_of_range") is not None
           else ""),
        f"    valve travel (% of span per hour): as is {f(e['travel_as_is'], 4)}, repaired "
        f"{f(e['travel_repaired'], 4)}, compensated {f(e['travel_compensated'], 4)}; reversals per hour "
        f"{f(e['reversals_as_is'], 4)}, {f(e['reversals_repaired'], 4)}, {f(e['reversals_compensated'], 4)}",
        f"    {compensator_words(k)}",
        f"    controller: kp {f(c['kp'], 4)}, ki {f(c['ki'], 4)} per sample ({c['source']}, explains "
        f"{f(100 * c['fit'] if c['fit'] is not None else None, 3)} % of OP's moves)",
    ]
    if e.get("note"):
        lines.append(f"    note: {e['note']}")
    return "\n".join(lines)


def screen_settings(args):
    """The `ScreenSettings` of `screen`'s options (`--full-search`, `--max-delay`, `--threads`, `--chunk`,
    `--threshold`)."""
    from ._estimate.settings import FULL_SEARCH_ESTIMATE, SCREEN_ESTIMATE
    from ._screen.settings import ScreenSettings

    estimate = FULL_SEARCH_ESTIMATE if args.full_search else SCREEN_ESTIMATE
    if args.max_delay is not None:
        estimate = estimate.with_max_delay(args.max_delay)
    whatif = None
    if getattr(args, "whatif", False):
        from ._whatif.settings import WhatIfSettings

        whatif = WhatIfSettings()
    from ._verdict.settings import VerdictSettings

    threshold = getattr(args, "threshold", None)
    verdict = VerdictSettings() if threshold is None else VerdictSettings(threshold=threshold)
    return ScreenSettings(estimate=estimate, threads=args.threads or 0, chunk=getattr(args, "chunk", None) or 0,
                          whatif=whatif, verdict=verdict)


def cmd_screen(args):
    from ._screen.outputs import write_screen_outputs
    from ._screen.screen import screen

    progress = not args.json and sys.stderr.isatty() and not args.quiet
    t0 = time.time()
    if args.criticality and not args.whatif:
        raise ValueError("--criticality ranks by what a repair would buy: it needs --whatif")
    criticality = None
    if args.criticality:
        from ._screen.whatif import read_criticality

        criticality = read_criticality(args.criticality)  # a bad table fails before any loop is fitted
    by_valve = bool(args.by_valve)
    if args.tags:
        from ._io.tags import read_tags

        by_valve = read_tags(args.tags)  # as the criticality table: before any loop is fitted
    settings = screen_settings(args)
    rep = screen(args.paths, settings, ts=args.ts, progress=progress, scheduler=args.scheduler,
                 pictures=bool(args.out), diagnose=args.diagnose, recursive=args.recursive,
                 decimate=args.decimate, criticality=criticality, window=args.window, by_valve=by_valve)
    if args.out:
        write_screen_outputs(rep, args.out)
    # evidence: the Kano valve's held-out gain over a linear valve (points), in
    # trend-free simulation and in short-horizon prediction
    lines = [f"{'loop':<16} {'status':<6} {'stiction':<8} {'cause':<21} {'band %':>7} {'evidence':>8} "
             f"{'(pred.)':>8} {'fitness %':>9}"]
    for e in rep.loops:
        if e["status"] == "ok":
            f = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
            lines.append(f"{e['name']:<16} {'ok':<6} {'yes' if e['stiction_detected'] else 'no':<8} "
                         f"{e['cause']:<21} {f(e['band_percent']):>7} {f(e['evidence']):>8} "
                         f"{f(e.get('evidence_prediction')):>8} {f(e['fitness']):>9}")
        else:
            lines.append(f"{e['name']:<16} error  {e['status']}")
    if args.whatif:
        lines += _ranking_text(rep.loops)
    if rep.valves is not None:
        from ._screen.valves import valves_text

        lines += valves_text(rep.valves)
    summary = rep.summary_line() + f" ({time.time() - t0:.0f} s)"
    lines.append(summary)
    if args.json:
        _log(summary)
    window = {"window": args.window} if args.window else {}
    _emit(args, {**rep.to_json(), **_decimate_field(args), **window}, "\n".join(lines))
    return 0


def _ranking_text(loops) -> list[str]:
    """`screen --whatif`: the sticky loops in the maintenance ranking's order."""
    rows = [e for e in loops if isinstance(e.get("whatif"), dict)]
    if not rows:
        return ["maintenance ranking: no sticky loop"]

    def f(v, nd=3):
        return "–" if v is None else f"{v:.{nd}g}"

    lines = ["maintenance ranking (predicted fall of std(SP - PV) from a repair, x criticality):",
             f"  {'loop':<16} {'as is':>9} {'repaired':>9} {'benefit':>9} {'% range':>8} {'weight':>6} "
             f"{'priority':>8} {'knocker':>9}"]
    for e in rows:
        w = e["whatif"]
        lines.append(f"  {e['name']:<16} {f(w.get('error_std_as_is')):>9} {f(w.get('error_std_repaired')):>9} "
                     f"{f(w.get('benefit')):>9} {f(w.get('benefit_percent_of_range')):>8} "
                     f"{f(w.get('criticality')):>6} {f(w.get('priority')):>8} {f(w.get('error_std_compensated')):>9}")
    return lines


def _diagnosis_text(name, d) -> str:
    also = [e for e in d.accepted if e != d.verdict]
    lines = [f"loop {name}: verdict {d.verdict}" + "".join(f", with {e}" for e in also)
             + (f" (runner-up: {d.runner_up})" if d.runner_up else ""),
             f"  nominal model on held-out data: fitness {d.heldout_nominal['fitness']:.2f} %"]
    for f in d.findings:
        if not f.accepted:
            continue
        params = ", ".join(f"{k} = {v}" for k, v in f.parameters.items() if k != "interval")
        lines.append(f"  {f.effect}: {params}; held-out fitness {f.heldout_before['fitness']:.2f} -> "
                     f"{f.heldout_after['fitness']:.2f} %"
                     + (f" ({f.evidence['note']})" if "note" in f.evidence else ""))
    alternatives = [f.effect for f in d.findings if "alternative_to" in f.evidence]
    if alternatives:
        lines.append(f"  alternatives (pass on their own, not fitted with {d.verdict}, not claimed): "
                     + ", ".join(alternatives))
    L = d.located
    periods = [x["period_samples"] for x in L["spectrum"]["lines"]]
    lines.append(f"  located: residual white {L['whiteness']['white']}, OP-residual cross-correlation passes "
                 f"{L['cross_correlation']['passes']}, narrow lines (period, samples) {periods}, "
                 f"segments {[x['segment'] for x in L['segments'] if x['significant']]}, windows {L['time_windows']}")
    for note in d.not_identifiable:
        lines.append(f"  not identifiable: {note}")
    return "\n".join(lines)


def cmd_diagnose(args):
    from ._diagnose.diagnose import diagnose
    from ._diagnose.settings import DiagnoseSettings
    from ._io.nominal import nominal_ts, read_nominal
    from ._io.read import loop_name, read_loop
    from ._loop import decimate

    settings = DiagnoseSettings(holdout=args.holdout, bootstrap=args.bootstrap)  # bad options fail first
    if args.model and args.decimate > 1:
        raise ValueError("--decimate cannot be used with --model: a nominal model is written for its "
                         "record's own sampling time (decimate the record and the model together)")
    nominal = read_nominal(args.model) if args.model else None
    ts = args.ts if args.ts is not None else (nominal_ts(args.model) if args.model else None)
    loop = decimate(read_loop(args.file, ts=ts, name=args.name), args.decimate)
    name = args.name if args.name is not None else loop_name(args.file)
    _log(f"diagnose: {name}: {int(loop.op.shape[0])} samples{_decimated(args)}"
         + (f", nominal model {args.model}" if args.model else ", no nominal model: fitting a linear-valve one"))
    _long_record_note("diagnose", int(loop.op.shape[0]), args.decimate)
    t0 = time.time()
    d = diagnose(loop, nominal, settings, progress=lambda m: _log(f"diagnose: {m}"), name=name)
    _log(f"diagnose: done in {time.time() - t0:.1f} s")
    if args.out:
        from ._plots import write_diagnosis_figures

        write_diagnosis_figures(d, Path(args.out), name=name, ts=float(loop.ts))
    payload = {"name": name, **d.to_json(), **_decimate_field(args)}
    _emit(args, payload, _diagnosis_text(name, d))
    return 0


def cmd_compensate(args):
    import jax
    import numpy as np

    from ._estimate.report import fit
    from ._estimate.settings import FULL_SEARCH_ESTIMATE
    from ._io.read import loop_name, read_loop
    from ._loop import decimate
    from ._programs import exported_call
    from ._whatif.report import compensation_json, compensator_words
    from ._whatif.settings import CompensateSettings
    from ._whatif.whatif import compensate

    settings = CompensateSettings(method=args.method, travel_weight=args.travel_weight)  # bad options fail first
    _pi(args)
    loop = decimate(read_loop(args.file, ts=args.ts, name=args.name), args.decimate)
    name = args.name if args.name is not None else loop_name(args.file)
    ts = float(loop.ts)
    controller = _controller(args, ts)
    op, pv = np.asarray(loop.op), np.asarray(loop.pv)
    _log(f"compensate: {name}: {op.shape[0]} samples, Ts = {ts:g} s{_decimated(args)}; fitting the valve and "
         "the process ...")
    _long_record_note("fit", op.shape[0], args.decimate)
    t0 = time.time()
    r = fit(op, pv, ts=ts, name=name, settings=FULL_SEARCH_ESTIMATE)
    _log(f"compensate: fitted in {time.time() - t0:.1f} s (S = {r.S:.3g}, J = {r.J:.3g} % of span); designing a "
         f"compensator ({args.method}) ...")
    t0 = time.time()
    c = jax.tree.map(np.asarray, exported_call("compensate", lambda f, lp, k: compensate(f, lp, settings, controller=k),
                                               r.fit, loop, controller, static=repr(settings)))
    _log(f"compensate: designed in {time.time() - t0:.1f} s")
    payload = {"name": name, **compensation_json(c, ts), "S": r.S, "J": r.J, "fitness": r.fitness,
               **_decimate_field(args)}
    if args.out:
        from ._whatif.figure import write_compensation_figure

        sp = np.asarray(loop.setpoint)
        sp = sp if np.all(np.isfinite(sp)) else np.full(op.shape[0], float(np.mean(pv)))
        write_compensation_figure(name, ts, sp, c, payload, Path(args.out) / "compensate.png")
    k = payload["compensator"]
    text = "\n".join([
        f"loop {name}: compensator for a Kano valve S = {r.S:.3g}, J = {r.J:.3g} % of span ({args.method} design)",
        f"  {compensator_words(k)} (a sample is {ts:g} s)",
        f"  std(SP - PV): as is {payload['error_std_as_is']:.4g}, compensated "
        f"{payload['error_std_compensated']:.4g} ({payload['reduction_percent']:.1f} % less), repaired "
        f"{payload['error_std_repaired']:.4g}",
        f"  valve travel: {payload['travel_as_is']:.4g} -> {payload['travel_compensated']:.4g} % of span per hour; "
        f"reversals {payload['reversals_as_is']:.4g} -> {payload['reversals_compensated']:.4g} per hour",
    ] + ([f"  note: {payload['note']}"] if payload["note"] else []))
    _emit(args, payload, text)
    return 0


def cmd_trend(args):
    from ._whatif.trend import trend_text, valve_trend

    mapping = None
    if args.tags:
        from ._io.tags import read_tags

        mapping = read_tags(args.tags)
    report = valve_trend(args.paths, mapping=mapping, ts=args.ts, recursive=args.recursive,
                         progress=lambda m: _log(f"trend: {m}"))
    if args.out:
        from ._whatif.trend import write_trend_figures

        write_trend_figures(report, Path(args.out))
    _emit(args, report, trend_text(report))
    return 0


def _version() -> str:
    """`jaxstiction X (jax Y, jaxlib Z)`, from the installed metadata: the exported
    programs and the lean compiler flag depend on the JAX versions, so a report of a
    problem needs all three."""
    from importlib.metadata import PackageNotFoundError, version

    from . import __version__

    def _of(dist):
        try:
            return version(dist)
        except PackageNotFoundError:
            return "not installed"

    return f"jaxstiction {__version__} (jax {_of('jax')}, jaxlib {_of('jaxlib')})"


class _VersionAction(argparse.Action):
    """`--version`, looked up only when asked for (reading the installed metadata
    costs every command ~40 ms at start-up otherwise)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(_version())
        parser.exit()


_NAME_HELP = ("which loop of a file holding several: a loop of a .mat file, or a tag of a CSV file with tagged "
              "columns (FIC101 for FIC101.OP, FIC101.PV)")


_PI_HELP = ("the controller's PI tuning instead of identifying it: gain (OP %% per PV unit, negative for a "
            "direct-acting loop) and integral time (s), e.g. 0.8,120")


_DECIMATE_HELP = ("fit the record at a K times longer sampling time, the means of K samples (for a record "
                  "sampled much faster than its loop moves: delays, orders and horizons count samples)")


_TAGS_HELP = ("the valve of each recording: a JSON object name -> tag (or a labels.json whose `loops` give each a "
              "`valve`), or a CSV with name and tag columns; default: a `tag` column, else the file name up to its "
              "last _ or -")


def build_parser():
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    common.add_argument("--out", metavar="DIR", help="write pictures and a report into DIR")
    p = argparse.ArgumentParser(
        prog="jaxstiction",
        description="Identify sticky control valves and the process behind them from OP/PV data.",
    )
    p.add_argument("--version", action=_VersionAction,
                   help="print the versions of jaxstiction, JAX and jaxlib, and exit")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", parents=[common], help="run the paper_sim scenario end to end")
    d.add_argument("--seed", type=int, default=0, help="random seed of the simulated records (default 0)")
    d.set_defaults(func=cmd_demo)
    f = sub.add_parser("fit", parents=[common], help="fit one loop (CSV with OP, PV; or .mat)")
    f.add_argument("file", help="the loop's record: CSV with OP and PV columns (t, SP optional), or MATLAB .mat")
    f.add_argument("--validate", type=float, default=1 / 3, metavar="FRACTION",
                   help="hold out the last FRACTION for validation (default 1/3; 0: validate on the estimation data)")
    f.add_argument("--ts", type=float, default=None, help="sampling time (s) when the file has no t column")
    f.add_argument("--name", default=None, help=_NAME_HELP)
    f.add_argument("--max-delay", type=_whole, default=None, metavar="N",
                   help="longest process dead time tried, in samples (default 3)")
    f.add_argument("--decimate", type=_whole, default=1, metavar="K", help=_DECIMATE_HELP)
    f.add_argument("--whatif", action="store_true",
                   help="also say what a repair would buy: the fitted loop closed again with the identified "
                        "controller under the disturbance it met, as is, repaired and with a knocker")
    f.add_argument("--pi", metavar="GAIN,TI", default=None, help=_PI_HELP)
    f.set_defaults(func=cmd_fit)
    s = sub.add_parser("screen", parents=[common],
                       help="screen loops (files, folders) for sticky valves, ranked; name other causes")
    s.add_argument("paths", nargs="+", help="CSV or .mat files, or folders holding them (their top level; "
                                            "subfolders too with --recursive)")
    s.add_argument("-r", "--recursive", action="store_true", help="also the loop files in subfolders")
    s.add_argument("--ts", type=float, default=None, help="sampling time (s) for files without a t column")
    s.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="run the chunks (and with --diagnose the diagnoses) on a Dask cluster (e.g. tcp://host:8786); "
                        "needs jaxstiction[dask]")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--max-delay", type=_whole, default=None, metavar="N",
                   help="longest process dead time tried, in samples (default 3)")
    s.add_argument("--full-search", action="store_true",
                   help="the full estimator's Kano search instead of the screen's lighter one: ~15 times slower "
                        "per loop, better on integrating (level) loops")
    s.add_argument("--diagnose", action="store_true",
                   help="name the cause of each loop not called sticky by the full diagnosis (as `diagnose` "
                        "without a nominal model: deadband, dead_time, saturation, external_oscillation, drift, "
                        "quantization, ...) instead of the screen's residual-line test; ~10-80 s per such loop")
    s.add_argument("--decimate", type=_whole, default=1, metavar="K", help=_DECIMATE_HELP)
    s.add_argument("--window", type=_whole, default=None, metavar="N",
                   help="screen a record longer than N samples (after --decimate) as the fewest consecutive "
                        "windows of equal length, at most N samples each, one entry per window named "
                        "NAME@START-STOP; over days of data a slow cycle can hide a limit cycle")
    s.add_argument("--threads", type=_whole, default=None, metavar="N",
                   help="batched fits running at once, each on one core (default: one per CPU core, at most 8; "
                        "memory grows with N)")
    s.add_argument("--whatif", action="store_true",
                   help="give each sticky loop a `whatif` object (what a repair would buy) and rank the sticky "
                        "loops by that benefit in %% of their PV range")
    s.add_argument("--criticality", metavar="CSV", default=None,
                   help="with --whatif: weights per tag (columns tag, weight) multiplying each loop's benefit in "
                        "the ranking")
    s.add_argument("--chunk", type=_whole, default=None, metavar="N",
                   help="loops per batched call (default: sized to the machine: 2 on a CPU, up to 1024 on a GPU "
                        "as its memory allows); the results do not depend on it, but for --whatif's replays")
    s.add_argument("--threshold", type=_probability, default=None, metavar="P",
                   help="call a loop sticky from this stiction probability (default 0.5; lower finds more sticky "
                        "valves and raises more false alarms)")
    s.add_argument("--by-valve", action="store_true",
                   help="also one verdict per valve, its recordings grouped by tag (a `tag` column, else the file "
                        "name up to its last _ or -): the verdict of most of its judged recordings")
    s.add_argument("--tags", metavar="FILE", default=None,
                   help="implies --by-valve; " + _TAGS_HELP)
    s.set_defaults(func=cmd_screen)
    g = sub.add_parser("diagnose", parents=[common],
                       help="locate, name and model what a nominal model leaves out (and prove it on held-out data)")
    g.add_argument("file", help="the loop's record: CSV with OP and PV columns (t, SP optional), or MATLAB .mat")
    g.add_argument("--model", metavar="NOMINAL.json", default=None,
                   help="nominal model (JSON); without it a linear-valve model is fitted first")
    g.add_argument("--holdout", type=float, default=1 / 3, metavar="FRACTION",
                   help="held-out fraction at the end (default 1/3)")
    g.add_argument("--bootstrap", type=int, default=39, metavar="N",
                   help="parametric bootstrap replicates (default 39)")
    g.add_argument("--ts", type=float, default=None,
                   help="sampling time (s) (default: the nominal model's, else the file's t column)")
    g.add_argument("--name", default=None, help=_NAME_HELP)
    g.add_argument("--decimate", type=_whole, default=1, metavar="K",
                   help=_DECIMATE_HELP + "; not with --model, which is written for the record's own sampling time")
    g.set_defaults(func=cmd_diagnose)
    c = sub.add_parser("compensate", parents=[common],
                       help="design a compensator (Hagglund's knocker or constant reinforcement) on the identified "
                            "closed loop, until the valve's repair")
    c.add_argument("file", help="the loop's record: CSV with OP and PV columns (t, SP optional), or MATLAB .mat")
    c.add_argument("--ts", type=float, default=None, help="sampling time (s) when the file has no t column")
    c.add_argument("--name", default=None, help=_NAME_HELP)
    c.add_argument("--decimate", type=_whole, default=1, metavar="K", help=_DECIMATE_HELP)
    c.add_argument("--method", choices=("grid", "gradient"), default="grid",
                   help="grid: every point of the compensator grid simulated (default); gradient: the knocker by "
                        "descent through a smoothed valve from a few starts")
    c.add_argument("--travel-weight", type=float, default=0.05, metavar="W",
                   help="what a doubling of the valve travel costs in the design, as a share of the as-is "
                        "variability (default 0.05)")
    c.add_argument("--pi", metavar="GAIN,TI", default=None, help=_PI_HELP)
    c.set_defaults(func=cmd_compensate)
    t = sub.add_parser("trend", parents=[common],
                       help="S and J per recording of each valve, in order, and whether its band grows")
    t.add_argument("paths", nargs="+", help="CSV or .mat files, or folders holding them")
    t.add_argument("-r", "--recursive", action="store_true", help="also the loop files in subfolders")
    t.add_argument("--ts", type=float, default=None, help="sampling time (s) for files without a t column")
    t.add_argument("--tags", metavar="FILE", default=None,
                   help=_TAGS_HELP)
    t.set_defaults(func=cmd_trend)
    return p


def _probability(text: str) -> float:
    try:
        p = float(text)
    except ValueError:
        p = float("nan")
    if not 0.0 < p < 1.0:
        raise argparse.ArgumentTypeError(f"must be a probability strictly between 0 and 1, got {text!r}")
    return p


def _whole(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text!r}")
    return n


def _cache_folder(default: str = "xla") -> str | None:
    """The persistent cache folder: `JAXSTICTION_CACHE` when set (`off`, `0`, `no` or
    `false`: none), else `jaxstiction/<default>` in the user's cache folder; created
    if missing (`None` when it cannot be)."""
    import os

    where = os.environ.get("JAXSTICTION_CACHE", "")
    if where.lower() in ("off", "0", "no", "false"):
        return None
    if not where:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        where = os.path.join(base, "jaxstiction", default)
    try:
        os.makedirs(where, exist_ok=True)
    except OSError:
        return None
    return where


def _xla_cache(where: str):
    """XLA's persistent compilation cache in folder `where`, for every program worth it."""
    import jax

    jax.config.update("jax_compilation_cache_dir", where)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _compilation_cache():
    """Persistent XLA compilation cache in the user's cache folder, so a second run of
    the same shapes in a new process does not recompile. `JAXSTICTION_CACHE=off`
    turns it off; `JAXSTICTION_CACHE=DIR` puts it elsewhere."""
    import os

    where = _cache_folder()
    if where is None:
        return
    from ._estimate.programs import use_program_cache

    use_program_cache(os.path.join(where, "programs"))
    _xla_cache(where)


# jaxlib releases on which `--xla_cpu_use_fusion_emitters=false` was measured (an
# unknown flag in XLA_FLAGS aborts XLA, so it is never passed to an untested one).
_LEAN_COMPILER_VERIFIED = ("0.10.",)


def _lean_compiler():
    """Compile with XLA's older CPU fusion code generator.

    Measured on a 2-core CPU with jaxlib 0.10.2: compiling `estimate` for a
    1500-sample loop peaks at 1.09 GB of memory instead of 2.57 GB and takes 15 s
    instead of 21 s; the compiled programs run as fast (the physical search a little
    faster). It must be set before JAX creates its CPU backend, so the command line
    sets it first thing; a flag already in `XLA_FLAGS` wins, and
    `JAXSTICTION_LEAN_COMPILER=off` leaves XLA alone. API users can set
    `XLA_FLAGS=--xla_cpu_use_fusion_emitters=false` themselves."""
    import os

    import jaxlib

    if os.environ.get("JAXSTICTION_LEAN_COMPILER", "").lower() in ("off", "0", "no", "false"):
        return
    if not jaxlib.__version__.startswith(_LEAN_COMPILER_VERIFIED):
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_cpu_use_fusion_emitters=false".strip()


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    _lean_compiler()
    import jax

    # The application (not the library) chooses float64, recommended for identification.
    jax.config.update("jax_enable_x64", True)
    _compilation_cache()
    from ._checks import error_line, LoopDataError, LoopDataWarning, one_line

    def show(message, category, *rest):
        if issubclass(category, LoopDataWarning):
            _log(f"warning: {message}")  # one line, like the errors
        else:
            default_show(message, category, *rest)

    default_show, warnings.showwarning = warnings.showwarning, show
    try:
        return args.func(args)
    except (LoopDataError, ValueError, OSError) as e:
        msg = one_line(e)
        print(f"error: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a bug: still one line, but say so
        msg = error_line(e, 500)
        print(f"error: internal failure ({msg}); please report it", file=sys.stderr)
        return EXIT_INTERNAL
    finally:
        warnings.showwarning = default_show


if __name__ == "__main__":
    sys.exit(main())
