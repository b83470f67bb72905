"""How much the screen's call on a real recording hangs on which part of it was kept.

Each judgeable recording of the plant development half (751 samples; not L00, too
short, nor L78 and L79, a frozen sensor) is screened whole, cut to its first
`--keep` samples and cut to its last `--keep`, with the shipped probability. The
cut copies are written to a temporary folder (the data are read in place and never
copied into the repository).

This is a stability check, not an accuracy figure: the shipped probability was
fitted with these records among its real ones (the leave-one-valve-out figures are
`calibrate_probability.py`'s). It counts the calls that change with the window.

    python benchmarks/plant_windows.py                 # ~2.5 min on 2 cores
    python benchmarks/plant_windows.py --keep 500
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile

import jax
import pandas as pd


jax.config.update("jax_enable_x64", True)  # the CLI's precision, as the calibration's evidence

import jaxstiction as js  # noqa: E402


SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"  # beside the repository
PARTS = ("whole", "head", "tail")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plant", type=pathlib.Path, default=SHARED / "plant")
    parser.add_argument("--keep", type=int, default=600, help="samples kept at each end (default 600 of 751)")
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = parser.parse_args()
    labels = json.loads((args.plant / "labels.json").read_text())["loops"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        names = []
        for f in sorted(args.plant.glob("*.csv")):
            df = pd.read_csv(f)
            if len(df) <= args.keep or f.stem in ("L78", "L79"):
                continue
            for part, rows in zip(PARTS, (df, df.iloc[: args.keep], df.iloc[-args.keep:])):
                rows.to_csv(tmp / f"{f.stem}@{part}.csv", index=False)
            names.append(f.stem)
        entries = {e["name"]: e for e in js.screen(tmp).loops}
    out = {}
    for n in names:
        out[n] = {"label": labels.get(n, {}).get("label"), "valve": labels.get(n, {}).get("valve"),
                  **{p: {"verdict": entries[f"{n}@{p}"]["verdict"],
                         "stiction_probability": entries[f"{n}@{p}"]["stiction_probability"],
                         "status": entries[f"{n}@{p}"]["status"]} for p in PARTS}}
    sticky = lambda r, p: r[p]["verdict"] == "stiction"  # noqa: E731
    changed = {p: [n for n, r in out.items() if sticky(r, p) != sticky(r, "whole")] for p in ("head", "tail")}
    if args.json:
        print(json.dumps({"keep": args.keep, "recordings": out, "changed": changed}))
        return
    right = {p: (sum(sticky(r, p) for r in out.values() if r["label"] == "stiction"),
                 sum(not sticky(r, p) for r in out.values() if r["label"] == "none")) for p in PARTS}
    n_s = sum(r["label"] == "stiction" for r in out.values())
    n_h = sum(r["label"] == "none" for r in out.values())

    def cell(r, p):
        prob = r[p]["stiction_probability"]
        return f"{r[p]['verdict'][:12]:<12} {'–' if prob is None else f'{prob:.2f}':>5}"

    print(f"{'rec':<5} {'label':<9} " + " ".join(f"{p:<18}" for p in PARTS))
    for n, r in out.items():
        print(f"{n:<5} {r['label']:<9} " + " ".join(cell(r, p) for p in PARTS))
    for p in PARTS:
        print(f"{p:>5}: sticky called sticky {right[p][0]}/{n_s}, healthy not called sticky {right[p][1]}/{n_h}")
        failed = [n for n, r in out.items() if r[p]["status"] != "ok"]
        if failed:  # a record too short to fit: no probability
            print(f"       {len(failed)} of {len(out)} could not be screened, e.g. {out[failed[0]][p]['status']}")
    for p, c in changed.items():
        print(f"{p:>5}: the call differs from the whole record's on {len(c)} of {len(out)}: {', '.join(c) or '-'}")


if __name__ == "__main__":
    main()
