"""Compare two screens of the same loops, field by field.

    jaxstiction screen ../shared/data/plant --chunk 2 --json > a.json
    jaxstiction screen ../shared/data/plant --chunk 64 --json > b.json
    python benchmarks/compare_screens.py a.json b.json

Prints how many loops are identical in every field, whether the verdicts,
probabilities and statuses all agree, and each loop's differing fields.
"""

import argparse
import json
import pathlib


def differences(a, b, path=""):
    """`(path, a, b)` for every leaf where the JSON values `a` and `b` differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in differences(a.get(k), b.get(k), f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [(path, a, b)]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("first")
    p.add_argument("second")
    args = p.parse_args()
    a, b = ({r["name"]: r for r in json.loads(pathlib.Path(f).read_text())["loops"]} for f in (args.first, args.second))
    if a.keys() != b.keys():
        raise SystemExit(f"error: the screens hold different loops: {sorted(a.keys() ^ b.keys())}")
    diff = {n: differences(a[n], b[n]) for n in a}
    same = [n for n, d in diff.items() if not d]
    print(f"{len(a)} loops: {len(same)} identical in every field")
    for key in ("verdict", "stiction_probability", "status"):
        print(f"  {key}: {'the same on every loop' if all(a[n].get(key) == b[n].get(key) for n in a) else 'differs'}")
    for n, d in diff.items():
        if d:
            print(f"  {n}: {len(d)} fields differ, e.g. " + "; ".join(f"{p[1:]} {x} / {y}" for p, x, y in d[:4]))


if __name__ == "__main__":
    main()
