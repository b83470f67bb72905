"""The stiction probability: fit it, and measure it where it was not fitted.

    python benchmarks/calibrate_probability.py                       # fit on seeds 0-399, check on 400-599
    python benchmarks/calibrate_probability.py --write               # ... and write jaxstiction/_verdict/calibration.py
    python benchmarks/calibrate_probability.py --fit-seeds 0-99 --check-seeds 100-149   # quick

Evidence comes from `jaxstiction.screen_loops`, exactly as `jaxstiction screen`
computes it, for three sets of loops:

- the simulated realistic fleet (`jaxstiction.internal.realistic_fleet`): seeds
  `--fit-seeds` to fit, `--check-seeds` to check (never fitted on);
- the real plant records of the development half (`--plant`, default
  `../shared/data/plant`: labels in its `labels.json`, frozen-sensor and too-short
  records are not judgeable);
- the six labelled ISDB loops (`--isdb`, default `../shared/data/isdb`; the eight
  withheld ones are screened and printed, never fitted on or scored).

The probability's coefficients are fitted (`fit_calibration`: an L2-penalised
logistic regression) on the fit seeds and the real labelled records together, the
real records weighted so that they carry two thirds of the total weight
(`--real-share`; the sweep behind that choice is on the results page). Within the
fleet and within the real records, the sticky and the healthy loops each carry
half of that part's weight: the probability is then at even prior odds, and its
cut at 0.5 is the one that maximises balanced accuracy, the figure the verdict is
judged by (`--natural-odds` weighs every record of a part the same, as drawn).
Printed:

- the fitted coefficients (written to `jaxstiction/_verdict/calibration.py` with
  `--write`);
- on the check seeds: a reliability table (predicted against observed stiction
  rate at the same odds, by probability decile) and the balanced accuracy of `stiction_detected`,
  counting `inconclusive` as not sticky, by kind, and over the loops whose valve
  slipped at least four times in the record (a sticky valve that never moves cannot
  be seen);
- on the plant development half: **leave-one-valve-out** figures. For each valve,
  the coefficients are refitted without that valve's recordings and its recordings
  are judged with them (the gate as shipped); balanced accuracy over recordings and
  over valves (a valve's verdict is the majority of its recordings). The same for
  the ISDB loops, each left out in turn;
- the same figures with the probability fitted on the simulated fleet alone (no
  real record seen: a pure out-of-sample check on every real record).
- with `--split-half N`, a check of how the calibration carries to a half of
  valves it never saw, as the hidden half is judged: N random splits of the
  labelled plant valves into halves, the probability fitted on the fleet, the ISDB
  and one half, the other half judged (`split_half`).
- `--l2 X` fits with another penalty on the standardised weights (shipped: 1).

The shipped probability weighs the data-driven indicators only (`UNWEIGHED`: the
blocked cross-validation, the model-based gains and the fitted band are taken as
missing, so the fit gives them no weight). Fitted on the simulated fleet alone, the
indicators judge the plant's recordings at 0.938 left out, against 0.650 with every
feature weighed, and every other figure here agrees (the results page has them):
the model-based evidence, fitted on simulated loops, does not carry to this plant.
It still decides a loop under setpoint moves (the gate), and gives the band, the
slip and the cause. `--drop none` weighs every feature, `--drop horch,ngi` any set.

`--shipped` scores the shipped coefficients on the check seeds instead of those
fitted in the run (the leave-one-out figures always refit).
`--limit-cycle` fits and scores with one more feature, the reproduction of the
limit-cycle check (`jaxstiction.internal.limit_cycle`, reported in each entry but not
weighed by the shipped probability), and `--drop` another set of features left
out: what a feature adds, measured side by side on the same cached evidence (each
beside the indicators; with `--drop none`, beside every feature).
`--integrating` adds a flag for an integrating (level) process and its products
with the model-based evidence (`INTEGRATING`), the flag taken from what is known,
not from the data: the truth on the fleet, an `LIC` tag on the plant records, 0 on
the ISDB loops. It measures what the best case of a
per-process-type weighing of the evidence would add. `--integrating data` takes the
flag from the record instead (`drift`: an ARX fit's autoregressive coefficients
summing to nearly 1).

The screened evidence is cached in `benchmarks/out/`, keyed by the seeds and by
the package's source (a changed package screens again); `--fresh` recomputes it.
"""

import argparse
import json
import pathlib
import time

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _args import seeds_arg, seeds_text, slip_count  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

import jaxstiction as js  # noqa: E402
from jaxstiction.internal import CALIBRATION, FEATURES, fit_calibration, HARD, realistic_fleet, source_hash  # noqa: E402


HERE = pathlib.Path(__file__).resolve().parent
SHARED = HERE.parents[1] / "shared" / "data"
ISDB_LABELS = {"CHEM1": True, "CHEM10": True, "CHEM23": True, "CHEM13": False, "PAP4": False, "PAP7": False}
REAL_SHARE = 2 / 3  # of the total weight carried by the real records (--real-share)
BALANCED = True  # sticky and healthy weigh the same in each part (--natural-odds: as drawn)
COLUMNS = FEATURES  # what the probability is fitted on (--limit-cycle adds one)
# the model-based evidence the shipped probability does not weigh (--drop's default)
UNWEIGHED = ("crossval", "evidence", "evidence_prediction", "evidence_estimation", "band")
DROPPED = frozenset(UNWEIGHED)  # columns taken as missing everywhere (--drop)
L2 = 1.0  # the logistic regression's penalty on the standardised weights (--l2)
# --integrating: the flag, and the evidence it multiplies
INTEGRATING = ("evidence", "evidence_estimation", "evidence_prediction", "crossval")


DRIFT = {}  # --integrating data: `drift` of each record, by `key`
DRIFT_FLAG = 0.05  # below this `drift`, a record is taken as integrating


def key(entry):
    return entry["name"] if "truth" in entry else f"{entry['set']}/{entry['name']}"


def drift(op, pv, na=8, nb=20):
    """One minus the sum of the autoregressive coefficients of an ARX(na, nb) fit of
    PV on OP (both standardised; least squares): 0 for an integrating process,
    larger the faster a self-regulating one settles. NaN-free: 1.0 where it cannot
    be computed."""
    op, pv = np.asarray(op, float), np.asarray(pv, float)
    u = (op - op.mean()) / (op.std() or 1.0)
    y = (pv - pv.mean()) / (pv.std() or 1.0)
    m = max(na, nb)
    if len(y) <= 3 * (na + nb):
        return 1.0
    X = np.column_stack([y[m - k:len(y) - k] for k in range(1, na + 1)]
                        + [u[m - k:len(u) - k] for k in range(1, nb + 1)] + [np.ones(len(y) - m)])
    theta = np.linalg.lstsq(X, y[m:], rcond=None)[0]
    return float(np.nan_to_num(1.0 - theta[:na].sum(), nan=1.0))


def drifts(entries):
    """`drift` of every entry's record: the fleet's drawn again, the real ones read."""
    fleet = [int(e["name"][1:]) for e in entries if "truth" in e]
    out = {f"s{f.seed}": drift(f.op, f.pv) for f in realistic_fleet(fleet)}
    for e in entries:
        if "truth" not in e and e.get("file"):
            try:
                lp = js.read_loop(e["file"])
                out[key(e)] = drift(lp.op, lp.pv)
            except ValueError:
                out[key(e)] = 1.0
    return out


def integrating(entry):
    """1.0 where the loop's process is known to integrate (fleet truth; a level
    controller's `LIC` tag on a plant record), else 0.0; with `--integrating data`,
    where the record's `drift` is below `DRIFT_FLAG`."""
    if DRIFT:
        return float(DRIFT.get(key(entry), 1.0) < DRIFT_FLAG)
    if "truth" in entry:
        return float(entry["truth"]["integrating"])
    return float("LIC" in entry.get("valve", ""))


def value(entry, name):
    """Column `name` of a screen entry: a feature, the limit-cycle check's
    reproduction (`limit_cycle`), or `integrating` and its products
    (`integrating*evidence`, ...); NaN where missing (null) or dropped."""
    if name in DROPPED:
        return np.nan
    if name == "integrating":
        return integrating(entry)
    if name.startswith("integrating*"):
        v = entry["features"][name.split("*")[1]]
        return integrating(entry) * (0.0 if v is None else v)
    v = entry["features"][name] if name in FEATURES else entry["limit_cycle"]["reproduction"]
    return np.nan if v is None else v


def row(entry):
    return np.array([value(entry, k) for k in COLUMNS], float)


def fleet_entries(seeds, threads):
    """Screen entries of the fleet draws `seeds`, with their truth."""
    fleet = realistic_fleet(seeds)
    loops = {f"s{f.seed}": js.make_loop(f.op, f.pv, 1.0, sp=f.sp) for f in fleet}
    t0 = time.time()
    entries = js.screen_loops(loops, js.ScreenSettings(threads=threads))
    print(f"screened {len(loops)} fleet loops in {time.time() - t0:.0f} s", flush=True)
    truth = {}
    for f in fleet:
        truth[f"s{f.seed}"] = {"sticky": f.sticky, "kind": f.kind, "slips": slip_count(f.valve),
                               "integrating": f.integrating}
    return [{**e, "truth": truth[e["name"]]} for e in entries]


def real_entries(plant: pathlib.Path, isdb: pathlib.Path, threads):
    """Screen entries of the real records, with `label` (True, False, or None when not
    judgeable or withheld), `valve` and `set`."""
    out = []
    if (plant / "labels.json").exists():
        labels = json.loads((plant / "labels.json").read_text())["loops"]
        for e in js.screen(plant, js.ScreenSettings(threads=threads)).loops:
            info = labels.get(e["name"], {})
            judgeable = e["status"] == "ok"
            out.append({**e, "set": "plant", "valve": info.get("valve", e["name"]),
                        "label": (info.get("label") == "stiction") if info and judgeable else None,
                        "label_given": info.get("label")})
    if isdb.exists():
        for e in js.screen(isdb, js.ScreenSettings(threads=threads)).loops:
            out.append({**e, "set": "isdb", "valve": e["name"], "label": ISDB_LABELS.get(e["name"])})
    return out


def cached(path: pathlib.Path, make, fresh: bool):
    """`make()`, stored in `path` with the hash of the package's source: evidence
    that another version of the package screened is screened again. The
    calibration that `--write` rewrites is left out of the hash: the features used
    here do not depend on it (the entries' stored probabilities do, and are not used)."""
    key = source_hash(exclude=("_verdict/calibration.py",))
    if path.exists() and not fresh:
        stored = json.loads(path.read_text())
        if isinstance(stored, dict) and stored.get("source") == key:
            return stored["entries"]
        print(f"{path.name}: screened by another version of the package, screening again", flush=True)
    value = make()
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps({"source": key, "entries": value}))
    return value


def matrix(entries):
    return np.array([row(e) for e in entries], float).reshape(len(entries), len(COLUMNS))


def weights(sim_labels, real_labels):
    """Sample weights of the fit: the fleet's loops weigh one each on average, and
    the real records together carry `REAL_SHARE` of the total weight. With
    `BALANCED`, sticky and healthy carry half of each part's weight, so the
    probability is at even prior odds, where 0.5 is the cut that maximises
    balanced accuracy; else every record of a part weighs the same."""
    ys = np.asarray(sim_labels, float)
    parts = [(ys, float(len(ys)))]
    if len(real_labels):
        parts.append((np.asarray(real_labels, float), REAL_SHARE / (1 - REAL_SHARE) * len(ys)))
    out = []
    for y, total in parts:
        w = np.full(len(y), total / len(y))
        if BALANCED and 0 < y.sum() < len(y):
            w = np.where(y > 0, 0.5 * total / y.sum(), 0.5 * total / (len(y) - y.sum()))
        out.append(w)
    return np.concatenate(out)


def fit(sim, real):
    """Calibration fitted on fleet entries `sim` (truth) and real entries `real` (label)."""
    X = np.concatenate([matrix(sim), matrix(real)]) if real else matrix(sim)
    ys = [e["truth"]["sticky"] for e in sim]
    yr = [e["label"] for e in real]
    return fit_calibration(X, np.array(ys + yr, float), weights(ys, yr), l2=L2, names=COLUMNS)


def called(entry, calibration, threshold=0.5):
    """Whether `entry` is called sticky with `calibration`: the gate as the screen
    applied it (hard gates and failed fits are never sticky), then the probability,
    or under setpoint moves the model-based test (`jaxstiction.internal.decide`)."""
    if entry["status"] != "ok" or entry["gate"] in HARD:
        return False
    x = row(entry)
    s = js.VerdictSettings()
    by_model = (entry["gate"] == "setpoint_moves" and bool(entry.get("model_wins"))
                and (entry.get("fitness_kano") or -np.inf) >= s.setpoint_fitness
                and (entry.get("band_fraction") or 0.0) >= s.setpoint_band)
    return float(calibration.probability(x)) >= threshold or by_model


def balanced(pairs):
    """Balanced accuracy of `(called, truth)` pairs, with the counts."""
    pos = [c for c, t in pairs if t]
    neg = [not c for c, t in pairs if not t]
    tpr = np.mean(pos) if pos else float("nan")
    tnr = np.mean(neg) if neg else float("nan")
    return 0.5 * (tpr + tnr), sum(pos), len(pos), sum(neg), len(neg)


def fmt(ba):
    return f"{ba[0]:.3f} (sticky {ba[1]}/{ba[2]}, healthy {ba[3]}/{ba[4]})"


def lovo(sim, real, pool, with_real=True):
    """Leave-one-valve-out calls on the labelled entries of `pool` (a subset of
    `real`): each valve judged by coefficients fitted without its recordings."""
    calls = {}
    for valve in sorted({e["valve"] for e in pool}):
        train = [e for e in real if e["valve"] != valve and e["label"] is not None] if with_real else []
        cal = fit(sim, train)
        for e in pool:
            if e["valve"] == valve:
                calls[e["name"]] = called(e, cal)
    return calls


def by_valve(pool, calls):
    valves = {}
    for e in pool:
        valves.setdefault(e["valve"], []).append((calls[e["name"]], e["label"]))
    return [(sum(c for c, _ in v) > len(v) / 2, v[0][1]) for v in valves.values()]


def report_real(title, sim, real, with_real):
    plant = [e for e in real if e["set"] == "plant" and e["label"] is not None]
    isdb = [e for e in real if e["set"] == "isdb" and e["label"] is not None]
    print(f"\n{title}")
    if plant:
        calls = lovo(sim, real, plant, with_real)
        print("  plant development half, leave-one-valve-out:")
        print(f"    recordings: balanced accuracy {fmt(balanced([(calls[e['name']], e['label']) for e in plant]))}")
        print(f"    valves:     balanced accuracy {fmt(balanced(by_valve(plant, calls)))}")
        for e in sorted(plant, key=lambda e: (e["valve"], e["name"])):
            print(f"      {e['name']:6s} {e['valve']:26s} label {'stiction' if e['label'] else 'none':8s} "
                  f"called {'sticky' if calls[e['name']] else '-':6s} gate {e['gate']}")
    if isdb:
        calls = lovo(sim, real, isdb, with_real)
        print(f"  ISDB labelled, each left out: {fmt(balanced([(calls[e['name']], e['label']) for e in isdb]))}")


def split_half(sim, real, count, seed=0):
    """How the calibration carries to valves it never saw when only half of the plant
    half's valves are there to fit on, as the hidden half is judged: `count` random
    splits of the labelled plant valves into a fitted half and a judged half (the
    sticky valves and the healthy ones each split as evenly as they go, the judged
    half taking the larger share every other split), the probability fitted on the
    fleet, the ISDB's labelled loops and the fitted half, and the judged half's
    recordings called. Prints the spread of the balanced accuracy over the judged
    recordings and valves (a valve by the majority of its recordings), how many
    splits reach 0.80, and each recording's share of the splits that judged it right."""
    plant = [e for e in real if e["set"] == "plant" and e["label"] is not None]
    others = [e for e in real if e["set"] != "plant" and e["label"] is not None]
    label = {e["valve"]: e["label"] for e in plant}
    sticky = sorted(v for v, y in label.items() if y)
    healthy = sorted(v for v, y in label.items() if not y)
    rng = np.random.default_rng(seed)
    recs, valves, fitted, right = [], [], [], {}
    for i in range(count):
        judged = set()
        for group in (sticky, healthy):
            take = (len(group) + (i % 2)) // 2
            judged |= set(rng.choice(group, size=take, replace=False).tolist())
        cal = fit(sim, others + [e for e in plant if e["valve"] not in judged])
        pool = [e for e in plant if e["valve"] in judged]
        calls = {e["name"]: called(e, cal) for e in pool}
        fitted.append(len(sticky) - len(judged & set(sticky)))
        recs.append(balanced([(calls[e["name"]], e["label"]) for e in pool])[0])
        valves.append(balanced(by_valve(pool, calls))[0])
        for e in pool:
            right.setdefault(e["name"], []).append(calls[e["name"]] == e["label"])
    print(f"\nsplit-half: {count} random splits of the {len(label)} labelled plant valves ({len(sticky)} sticky), "
          "fitted on one half (with the fleet and the ISDB), judged on the other")
    fitted = np.array(fitted)
    for k in [None] + sorted(set(fitted.tolist())):
        m = np.ones(len(fitted), bool) if k is None else fitted == k
        print("  all splits:" if k is None else f"  the splits that fit on {k} sticky valve{'s' * (k != 1)}:")
        for name, ba in (("recordings", np.array(recs)[m]), ("valves", np.array(valves)[m])):
            ba = ba[np.isfinite(ba)]
            print(f"    {name:10s} balanced accuracy min {ba.min():.3f}, quartiles {np.quantile(ba, 0.25):.3f} / "
                  f"{np.median(ba):.3f} / {np.quantile(ba, 0.75):.3f}, max {ba.max():.3f}; "
                  f"{np.sum(ba >= 0.8)} of {len(ba)} splits reach 0.80")
    print("  recordings judged wrong on some split (share of the splits that judged them right):")
    for e in sorted(plant, key=lambda e: (not e["label"], e["name"])):
        r = right.get(e["name"], [])
        if r and not all(r):
            print(f"    {e['name']:6s} {e['valve']:26s} label {'stiction' if e['label'] else 'none':8s} "
                  f"right on {np.mean(r):.2f} of {len(r)}")


def reliability(check, cal):
    """Predicted against observed stiction rate by probability decile. With
    `BALANCED` the observed rate is taken at even odds (each class's loops
    weighted by one over its count), as the probability is."""
    check = [e for e in check if e["status"] == "ok"]
    p = np.array([float(cal.probability(row(e))) for e in check])
    y = np.array([e["truth"]["sticky"] for e in check], float)
    w = weights(y, [])  # as the fit weighs the fleet
    odds = "at even odds" if BALANCED else "as drawn"
    print("\n  reliability on the check seeds (probability decile: mean predicted, "
          f"observed sticky rate {odds}, loops)")
    edges = np.linspace(0, 1, 11)
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (p >= lo) & (p < hi if hi < 1 else p <= hi)
        if m.any():
            print(f"    [{lo:.1f}, {hi:.1f}): {p[m].mean():.2f}  {np.average(y[m], weights=w[m]):.2f}  {m.sum()}")
    base = float(np.average(y, weights=w))
    brier = float(np.average((p - y) ** 2, weights=w))
    print(f"    Brier score {brier:.3f} (a constant at the base rate {base:.2f}: {base * (1 - base):.3f})")


def report_sim(check, cal):
    ok = [e for e in check if e["status"] == "ok"]
    print(f"\n  check seeds: {len(check)} loops, {len(check) - len(ok)} not fitted (their status), "
          f"{sum(e['gate'] != 'ok' for e in ok)} gated")
    calls = [(called(e, cal), e["truth"]["sticky"]) for e in check]
    print(f"    balanced accuracy (inconclusive = not sticky): {fmt(balanced(calls))}")
    seen = [(called(e, cal), e["truth"]["sticky"]) for e in check
            if not e["truth"]["sticky"] or e["truth"]["slips"] >= 4]
    print(f"    over loops whose sticky valve slipped >= 4 times: {fmt(balanced(seen))}")
    conclusive = [(called(e, cal), e["truth"]["sticky"]) for e in check
                  if e["status"] == "ok" and e["gate"] == "ok"]
    print(f"    over the loops the gate passes: {fmt(balanced(conclusive))}")
    for kind in ("stiction", "deadband", "linear", "tight", "external"):
        k = [called(e, cal) for e in check if e["truth"]["kind"] == kind]
        if k:
            print(f"      {kind:9s} called sticky {sum(k)}/{len(k)}")


def main():
    global REAL_SHARE, BALANCED, COLUMNS, DROPPED, L2
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fit-seeds", type=seeds_arg, default=seeds_arg("0-399"))
    parser.add_argument("--check-seeds", type=seeds_arg, default=seeds_arg("400-599"))
    parser.add_argument("--plant", type=pathlib.Path, default=SHARED / "plant")
    parser.add_argument("--isdb", type=pathlib.Path, default=SHARED / "isdb")
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--write", action="store_true", help="write jaxstiction/_verdict/calibration.py")
    parser.add_argument("--fresh", action="store_true", help="recompute the cached evidence")
    parser.add_argument("--ceiling", action="store_true",
                        help="also the best classifier tried over all the evidence (needs scikit-learn)")
    parser.add_argument("--natural-odds", action="store_true",
                        help="weigh every record of a part the same, not sticky and healthy half each")
    parser.add_argument("--real-share", type=float, default=REAL_SHARE,
                        help="share of the total weight carried by the real records (default 2/3)")
    parser.add_argument("--limit-cycle", action="store_true",
                        help="also fit on the limit-cycle check's reproduction (a measurement of what it would add)")
    parser.add_argument("--integrating", nargs="?", const="known", choices=("known", "data"),
                        help="also fit on an integrating-process flag (known, or 'data': estimated from the record) "
                             "and its products with the model-based evidence (a measurement of what weighing the "
                             "evidence by process type would add)")
    parser.add_argument("--shipped", action="store_true",
                        help="score the shipped coefficients on the check seeds, instead of those fitted here")
    parser.add_argument("--l2", type=float, default=L2,
                        help="the penalty on the standardised weights (the fit's total weight is about 1200)")
    parser.add_argument("--split-half", type=int, default=0, metavar="N",
                        help="also fit on half of the plant valves and judge the other half, N random splits")
    parser.add_argument("--drop", default=",".join(UNWEIGHED),
                        help="features left out, comma-separated (taken as missing everywhere: the fit gives them "
                             "no weight), to measure what they add; 'none' weighs every feature (default: the "
                             "model-based evidence, as shipped)")
    args = parser.parse_args()
    dropped = [] if args.drop == "none" else [k for k in args.drop.split(",") if k]
    if args.limit_cycle and args.write:
        parser.error("--limit-cycle is a measurement: it cannot be combined with --write")
    COLUMNS = FEATURES + (("limit_cycle",) if args.limit_cycle else ())
    if args.integrating:
        COLUMNS += ("integrating",) + tuple(f"integrating*{k}" for k in INTEGRATING)
    if args.integrating and args.write:
        parser.error("--integrating is a measurement: it cannot be combined with --write")
    if set(dropped) - set(COLUMNS):
        parser.error(f"--drop: unknown features {sorted(set(dropped) - set(COLUMNS))}; they are {COLUMNS}")
    DROPPED = frozenset(dropped)
    as_shipped = DROPPED == frozenset(UNWEIGHED)
    if not as_shipped and args.write:
        parser.error("--drop is a measurement: it cannot be combined with --write")
    if args.shipped and (args.write or args.limit_cycle or not as_shipped or args.integrating):
        parser.error("--shipped scores the shipped coefficients: it cannot be combined with --write, "
                     "--limit-cycle, --integrating or --drop")
    if not 0 < args.real_share < 1:
        parser.error("--real-share must lie strictly between 0 and 1")
    REAL_SHARE = args.real_share
    L2 = args.l2
    BALANCED = not args.natural_odds

    out = HERE / "out"
    sim = cached(out / f"fleet_{seeds_text(args.fit_seeds)}.json",
                 lambda: fleet_entries(args.fit_seeds, args.threads), args.fresh)
    check = cached(out / f"fleet_{seeds_text(args.check_seeds)}.json",
                   lambda: fleet_entries(args.check_seeds, args.threads), args.fresh)
    real = cached(out / "real.json", lambda: real_entries(args.plant, args.isdb, args.threads), args.fresh)
    if args.integrating == "data":
        DRIFT.update(drifts(sim + check + real))
        truth = [e["truth"]["integrating"] for e in sim]
        flagged = [integrating(e) for e in sim]
        print(f"--integrating data: flagged {sum(f for f, t in zip(flagged, truth) if t):.0f} of {sum(truth)} "
              f"integrating and {sum(f for f, t in zip(flagged, truth) if not t):.0f} of {len(truth) - sum(truth)} "
              f"self-regulating fit-seed loops")
        d = np.array([DRIFT[key(e)] for e in sim])
        pos, neg = d[np.array(truth)], d[~np.array(truth)]
        auc = np.mean(pos[:, None] < neg[None, :]) + 0.5 * np.mean(pos[:, None] == neg[None, :])
        print(f"  drift ranks integrating below self-regulating with an area under the ROC curve of {auc:.3f}")
    sim = [e for e in sim if e["status"] == "ok"]
    labelled = [e for e in real if e["label"] is not None]

    cal = fit(sim, labelled)
    print(f"\nfitted on {len(sim)} fleet loops (seeds {seeds_text(args.fit_seeds)}) and {len(labelled)} labelled "
          f"real records ({REAL_SHARE:.0%} of the weight)")
    for k, m, s, w in zip(COLUMNS, np.asarray(cal.mean), np.asarray(cal.scale), np.asarray(cal.weights)):
        print(f"  {k:20s} mean {m:8.4f} scale {s:8.4f} weight {w:8.4f}")
    print(f"  bias {float(cal.bias):.4f}")
    if args.shipped:
        cal = CALIBRATION
        print("\nscored with the shipped coefficients (jaxstiction/_verdict/calibration.py), not the ones above")
    reliability(check, cal)
    report_sim(check, cal)
    report_real("Real records, the probability fitted on the fleet and the other real records:", sim, real, True)
    report_real("Real records, the probability fitted on the simulated fleet alone:", sim, real, False)
    withheld = [e for e in real if e["set"] == "isdb" and e["label"] is None]
    if withheld:
        print("\n  withheld ISDB loops (never fitted on), with the coefficients above:")
        for e in withheld:
            print(f"    {e['name']:7s} called {'sticky' if called(e, cal) else '-'} (gate {e['gate']})")
    if args.split_half:
        split_half(sim, real, args.split_half)
    if args.ceiling:
        ceiling(sim, check, real)
    if args.write:
        write(cal, args)


def ceiling(sim, check, real):
    """How well any classifier of this evidence could do: gradient-boosted trees
    (scikit-learn, not a dependency of the package) over every feature, the gate's
    measures and the count of oscillation periods, fitted on the fit seeds and scored
    on the check seeds (a loop not fitted, or stopped by a hard gate, is not sticky);
    on the plant half, leave one valve out, fitted on the fleet and the other real
    records. An upper reference for the logistic probability, not a product."""
    from sklearn.ensemble import GradientBoostingClassifier

    def rows(entries):
        x = np.array([list(row(e))
                      + [e["gate_measures"][k] for k in ("setpoint_share", "compressed", "saturated")]
                      + [e["indicators"]["periods"] or 0.0] for e in entries], float)
        return np.nan_to_num(x, nan=-1.0)  # a missing feature: below every value it takes

    def judged(e):
        return e["status"] == "ok" and e["gate"] not in HARD

    train = [e for e in sim if judged(e)]
    y_train = [e["truth"]["sticky"] for e in train]
    model = GradientBoostingClassifier(random_state=0).fit(rows(train), y_train, sample_weight=weights(y_train, []))
    scored = [e for e in check if judged(e)]
    calls = dict(zip([e["name"] for e in scored], model.predict(rows(scored)).astype(bool)))
    print("\nceiling: gradient-boosted trees over all the evidence, fitted on the fit seeds")
    print(f"  check seeds: balanced accuracy "
          f"{fmt(balanced([(calls.get(e['name'], False), e['truth']['sticky']) for e in check]))}")
    print(f"    over the loops no hard gate stops: "
          f"{fmt(balanced([(calls[e['name']], e['truth']['sticky']) for e in scored]))}")
    quiet = sum(e["truth"]["sticky"] and e["truth"]["slips"] < 4 for e in check)
    print(f"    sticky valves that slipped fewer than 4 times in their record: {quiet} of "
          f"{sum(e['truth']['sticky'] for e in check)}")
    plant = [e for e in real if e["set"] == "plant" and e["label"] is not None and judged(e)]
    labelled = [e for e in real if e["label"] is not None and judged(e)]
    plant_calls = {}
    for valve in sorted({e["valve"] for e in plant}):
        others = [e for e in labelled if e["valve"] != valve]
        X = np.concatenate([rows(train), rows(others)])
        y = [e["truth"]["sticky"] for e in train] + [e["label"] for e in others]
        w = weights(y[:len(train)], y[len(train):])
        m = GradientBoostingClassifier(random_state=0).fit(X, y, sample_weight=w)
        mine = [e for e in plant if e["valve"] == valve]
        plant_calls.update(zip([e["name"] for e in mine], m.predict(rows(mine)).astype(bool)))
    every = [e for e in real if e["set"] == "plant" and e["label"] is not None]
    pairs = [(plant_calls.get(e["name"], False), e["label"]) for e in every]
    print(f"  plant development half, leave one valve out: recordings {fmt(balanced(pairs))}")
    calls_by_name = {e["name"]: plant_calls.get(e["name"], False) for e in every}
    print(f"    valves: {fmt(balanced(by_valve(every, calls_by_name)))}")


def write(cal, args):
    import textwrap

    def arr(v):
        body = ", ".join(f"{float(x):.6g}" for x in np.asarray(v))
        return "np.array([\n" + textwrap.fill(body, 100, initial_indent=" " * 8, subsequent_indent=" " * 8) + "\n    ])"

    names = textwrap.fill(", ".join(json.dumps(k) for k in FEATURES), 100, initial_indent=" " * 8,
                          subsequent_indent=" " * 8)

    unweighed = ""
    if DROPPED:
        unweighed = "\n\n" + textwrap.fill(
            "Not weighed (weight 0, taken at 0): " + ", ".join(k for k in FEATURES if k in DROPPED)
            + ": the model-based evidence, which does not carry from simulated loops to real ones.", 84)
    text = f'''"""The stiction probability's coefficients (a leaf: fitted numbers only).

Written by `python benchmarks/calibrate_probability.py --write` (fit seeds
{seeds_text(args.fit_seeds)} of the realistic fleet and the labelled real records of
the plant development half and the ISDB); do not edit by hand.{unweighed}
"""

import numpy as np

from .probability import Calibration


CALIBRATION = Calibration(
    names=(\n{names},\n    ),
    mean={arr(cal.mean)},
    scale={arr(cal.scale)},
    weights={arr(cal.weights)},
    bias=np.array({float(cal.bias):.6g}),
)
'''
    path = HERE.parent / "jaxstiction" / "_verdict" / "calibration.py"
    path.write_text(text)
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
