"""Power curves of the mismatch diagnosis on random concealed cases: how often the
right effect is named against its size, with false discoveries alongside.

    python benchmarks/diagnose_power.py                          # the docs' 200 draws (seeds 1000-1199)
    python benchmarks/diagnose_power.py --seeds 0-49 --save runs.jsonl
    python benchmarks/diagnose_power.py --load runs.jsonl,none.jsonl --plot power.png   # tables from saved runs
    python benchmarks/diagnose_power.py --seeds 0-99 --lengths 2000          # 2000-sample records only
    python benchmarks/diagnose_power.py --seeds 0-99 --only none             # effect-free draws only

Each draw is `concealed.build(seed)` (see `benchmarks/concealed.py`: one hidden
effect of a drawn size, an input effect and an external oscillation, or nothing, in
a drawn plant, controller, noise, operating point and record length) diagnosed with
its nominal model, the plant without the hidden effect: exactly
`jaxstiction.diagnose(case.loop, case.nominal)`. The draws run in order of record
length, so each length's programs are compiled once.

It prints, per effect, the share of draws named right in bins of the effect's size
(`concealed.SIZES`), and the smallest size from which every bin is named right in
at least 90 % of its draws (`--target`); the false-discovery rate on the effect-free
draws (any verdict but `none`), and the share of two-effect draws named right. Then
the audit of the rules that reject a finding which passed the acceptance test
(significant, a held-out gain beyond the spread, residuals that pass): per rule
(`evidence["rejected_by"]`), how many findings of an effect the draw did not hide
it removed (false discoveries) and how many of the hidden effect (true findings),
and how many of each it removed alone (every other check passed). `--plot` writes
the curves as a PNG.
"""

import argparse
import collections
import json
import statistics
import time

import jax


jax.config.update("jax_enable_x64", True)

import concealed  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from _args import seeds_arg, seeds_text  # noqa: E402

from jaxstiction import diagnose  # noqa: E402
from jaxstiction.internal import ACCEPTANCE_RULES  # noqa: E402


# size bins per effect (left edges; the last bin is open)
BINS = {"stiction": (0.5, 2.0, 4.0, 7.0), "deadband": (0.5, 2.0, 4.0, 7.0), "dead_time": (1, 3, 5, 8),
        "valve_characteristic": (0.1, 1.0, 3.0, 10.0), "saturation": (0.0, 5.0, 20.0, 50.0),
        "actuator_lag": (0.5, 0.7, 0.8, 0.9), "external_oscillation": (0.3, 0.6, 1.2, 2.4),
        "drift": (0.05, 0.25, 0.5, 1.0), "quantization": (0.05, 0.15, 0.5, 1.0)}


def run_one(seed, ranges=None):
    """Draw `seed`, diagnose it, and return what the tables need (JSON-able)."""
    t = time.time()
    case = concealed.build(seed, ranges)
    t_sim = time.time() - t
    t = time.time()
    d = diagnose(case.loop, case.nominal)
    findings = [{"effect": f.effect, "accepted": f.accepted, "significant": bool(f.evidence.get("significant")),
                 "rejected_by": f.evidence.get("rejected_by"), "rules_failed": f.evidence.get("rules_failed"),
                 "statistic": f.evidence.get("statistic"), "p_value": f.evidence.get("p_value"),
                 "second": "with" in f.parameters} for f in d.findings]
    return {"seed": seed, "effects": list(case.effects), "label": case.label, "size": case.size, "n": case.n,
            "verdict": d.verdict, "right": concealed.right(case, d), "accepted": list(d.accepted),
            "findings": findings, "seconds": round(time.time() - t, 2), "simulation_seconds": round(t_sim, 2),
            "params": case.params}


def _bin(effect, size):
    edges = BINS[effect]
    k = max(i for i, e in enumerate(edges) if size >= e) if size >= edges[0] else 0
    return k


def _bin_label(effect, k):
    edges = BINS[effect]
    return f"{edges[k]:g}-{edges[k + 1]:g}" if k + 1 < len(edges) else f">={edges[k]:g}"


def power_table(runs, target=0.9):
    """Per effect: per size bin `(label, right, count)`, and the smallest bin edge from
    which every bin with draws is named right in at least `target` of them."""
    out = {}
    for eff in concealed.EFFECTS:
        rs = [r for r in runs if r["effects"] == [eff]]
        rows = []
        for k in range(len(BINS[eff])):
            inb = [r for r in rs if _bin(eff, r["size"]) == k]
            rows.append((_bin_label(eff, k), sum(r["right"] for r in inb), len(inb)))
        detectable = None
        for k in range(len(rows)):
            tail = [(ok, n) for _, ok, n in rows[k:] if n]
            if tail and all(ok >= target * n for ok, n in tail):
                detectable = BINS[eff][k]
                break
        out[eff] = {"bins": rows, "right": sum(r["right"] for r in rs), "n": len(rs), "detectable_from": detectable}
    return out


def audit(runs):
    """Per rule that rejects a finding after the acceptance test: the false
    discoveries and true findings it removed, and those it removed alone."""
    rows = collections.defaultdict(lambda: collections.Counter())
    for r in runs:
        hidden = set(r["effects"])
        for f in r["findings"]:
            why = f["rejected_by"]
            if f["accepted"] or why is None or why in ACCEPTANCE_RULES:
                continue
            kind = "true" if f["effect"] in hidden else "false"
            rows[why][kind] += 1
            if not f["rules_failed"] or len(f["rules_failed"]) == 1:
                rows[why][kind + "_alone"] += 1
    return {k: dict(v) for k, v in sorted(rows.items())}


def plot(runs, table, fdr, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, NullFormatter

    fig, axes = plt.subplots(3, 3, figsize=(9.5, 7.5), sharey=True)
    for ax, eff in zip(axes.flat, concealed.EFFECTS):
        rs = [r for r in runs if r["effects"] == [eff]]
        xs = [r["size"] for r in rs]
        ys = [1.03 if r["right"] else -0.03 for r in rs]
        ax.scatter(xs, ys, s=9, c=["tab:green" if r["right"] else "tab:red" for r in rs], alpha=0.6, lw=0)
        edges = list(BINS[eff])
        hi = max(xs + [edges[-1]])  # the open last bin is drawn up to its largest draw
        log = eff in ("valve_characteristic", "external_oscillation", "drift", "quantization")
        cx, cy = [], []
        for k, (_, ok, n) in enumerate(table[eff]["bins"]):
            if n:
                right_edge = edges[k + 1] if k + 1 < len(edges) else hi
                cx.append((edges[k] * right_edge) ** 0.5 if log else 0.5 * (edges[k] + right_edge))
                cy.append(ok / n)
                ax.text(cx[-1], ok / n + 0.05, f"{ok}/{n}", ha="center", fontsize=7)
        ax.plot(cx, cy, "o-", color="tab:blue")
        ax.axhline(0.9, color="grey", ls=":", lw=1)
        if log:
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(eff.replace("_", " "), fontsize=9)
        ax.set_xlabel(concealed.SIZES[eff], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_ylim(-0.1, 1.15)
    axes[0, 0].set_ylabel("named right", fontsize=8)
    fig.suptitle(f"diagnosis power on {len(runs)} random draws; false discoveries on effect-free draws: "
                 f"{fdr[0]}/{fdr[1]}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=72)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds_arg, default=list(concealed.README_SEEDS), help="e.g. 1000-1199 or 3,5,7")
    p.add_argument("--lengths", default=None, help="record lengths drawn from, e.g. 2000 (default 1500,2000,3000)")
    p.add_argument("--only", default=None, help="every draw hides this: none, an effect, or e.g. "
                   "stiction+external_oscillation (default: drawn)")
    p.add_argument("--save", default=None, help="append each draw's result to this JSON-lines file as it finishes")
    p.add_argument("--load", default=None,
                   help="make the tables from saved JSON-lines files (comma-separated); diagnose nothing")
    p.add_argument("--plot", default=None, help="write the power curves to this PNG")
    p.add_argument("--target", type=float, default=0.9)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    ranges = {"lengths": tuple(int(v) for v in args.lengths.split(","))} if args.lengths else {}
    if args.only:
        ranges["only"] = args.only
    t0 = time.time()
    if args.load:
        runs = []
        for path in args.load.split(","):
            with open(path) as fh:
                runs += [json.loads(line) for line in fh if line.strip()]
    else:
        # in order of record length: one length's programs are compiled once
        order = sorted(args.seeds, key=lambda s: (concealed.draw_params(s, ranges)["n"], s))
        runs = []
        for seed in order:
            r = run_one(seed, ranges)
            runs.append(r)
            if args.save:
                with open(args.save, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
            if not args.json:
                size = "-" if r["size"] is None else f"{r['size']:.3g}"
                ok = "right" if r["right"] else "WRONG"
                print(f"draw {seed:5d} n {r['n']}: {r['label']:36s} size {size:8s} -> {r['verdict']:22s} {ok} "
                      f"{r['accepted']} [{r['seconds']:.1f} s]", flush=True)
    runs.sort(key=lambda r: r["seed"])
    table = power_table(runs, args.target)
    none = [r for r in runs if not r["effects"]]
    fdr = (sum(r["verdict"] != "none" for r in none), len(none))
    pairs = [r for r in runs if len(r["effects"]) == 2]
    aud = audit(runs)
    secs = [r["seconds"] for r in runs]
    valves = [r for r in runs if r["effects"] == ["valve_characteristic"]]
    cal = [r for r in valves if r["params"]["valve_characteristic"]["calibrated"]]
    moved = [r for r in valves if not r["params"]["valve_characteristic"]["calibrated"]]
    out = {"valves_calibrated_right": [sum(r["right"] for r in cal), len(cal)],
           "valves_moving_op_right": [sum(r["right"] for r in moved), len(moved)],
           "seeds": seeds_text(sorted(r["seed"] for r in runs)), "draws": len(runs), "power": table,
           "false_discoveries": list(fdr), "false_discovery_seeds": [r["seed"] for r in none if r["verdict"] != "none"],
           "pairs_right": [sum(r["right"] for r in pairs), len(pairs)], "audit": aud,
           "right": [sum(r["right"] for r in runs), len(runs)],
           "wrong": [(r["seed"], r["label"], r["size"], r["verdict"]) for r in runs if not r["right"]],
           "median_seconds": statistics.median(secs) if secs else None, "wall_seconds": round(time.time() - t0, 1)}
    if args.plot:
        plot(runs, table, fdr, args.plot)
    if args.json:
        print(json.dumps(out))
        return
    print(f"\n{len(runs)} draws (seeds {out['seeds']}): {out['right'][0]} named right; "
          f"false discoveries on the {fdr[1]} effect-free draws: {fdr[0]} ({fdr[0] / max(fdr[1], 1):.1%}); "
          f"two effects named right: {out['pairs_right'][0]}/{out['pairs_right'][1]}")
    print("\n| effect | size | " + " | ".join(f"bin {k + 1}" for k in range(4)) + f" | all | named right in >= "
          f"{args.target:.0%} from |")
    print("|---|---|---|---|---|---|---|---|")
    for eff, row in table.items():
        cells = " | ".join(f"{lab}: {ok}/{n}" for lab, ok, n in row["bins"])
        frm = "-" if row["detectable_from"] is None else f"{row['detectable_from']:g}"
        print(f"| {eff} | {concealed.SIZES[eff]} | {cells} | {row['right']}/{row['n']} | {frm} |")
    print(f"valve characteristic calibrated at the operating point: {out['valves_calibrated_right'][0]}/"
          f"{out['valves_calibrated_right'][1]} named right; moving the operating point (P3-like): "
          f"{out['valves_moving_op_right'][0]}/{out['valves_moving_op_right'][1]}")
    print("\nrules that reject a finding which passed the acceptance test (false discoveries removed / true "
          "findings removed; alone: no other check failed):")
    print("| rule | false discoveries removed | true findings removed | alone: false / true |")
    print("|---|---|---|---|")
    for rule, c in aud.items():
        print(f"| {rule} | {c.get('false', 0)} | {c.get('true', 0)} | {c.get('false_alone', 0)} / "
              f"{c.get('true_alone', 0)} |")
    print("\nwrong:", ", ".join(f"{s} {lab} ({'-' if z is None else round(z, 3)}) as {v}"
                                for s, lab, z, v in out["wrong"]))
    if secs:
        print(f"diagnosis seconds: median {statistics.median(secs):.1f}, max {max(secs):.1f}; "
              f"wall {out['wall_seconds']:.0f} s")


if __name__ == "__main__":
    main()
