"""`jaxstiction diagnose` without a nominal model on the ISDB loops (read in place).

    python benchmarks/diagnose_isdb.py [FOLDER_OR_FILE...]   # default ../shared/data/isdb

Prints, per loop, the verdict, what else is accepted with it, the runner-up, the held-out fitness of the fitted
linear-valve model and of the diagnosed one, and the time. The contributors'
labels (where the data set gives them) are not used by the method.
"""

import argparse
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

from jaxstiction import diagnose, find_loop_files, read_loop  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("paths", nargs="*", type=Path, metavar="FOLDER_OR_FILE",
                   help="loop files or folders (default: ../shared/data/isdb beside the repository)")
    paths = p.parse_args().paths or [Path(__file__).resolve().parents[2] / "shared/data/isdb"]
    for path in find_loop_files(paths):
        t = time.time()
        try:
            loop = read_loop(path)
            d = diagnose(loop)
        except ValueError as e:
            print(f"{path.stem:8s} error: {e}", flush=True)
            continue
        acc = [f for f in d.findings if f.accepted]
        after = acc[0].heldout_after["fitness"] if acc else d.heldout_nominal["fitness"]
        params = {k: v for k, v in acc[0].parameters.items() if k != "interval"} if acc else {}
        also = "+".join(e for e in d.accepted if e != d.verdict) or "-"
        print(f"{path.stem:8s} n={int(loop.op.shape[0]):6d}  verdict {d.verdict:22s} with {also:22s} "
              f"runner-up {str(d.runner_up):22s} "
              f"held-out {d.heldout_nominal['fitness']:7.2f} -> {after:7.2f} %  {params}  [{time.time() - t:.0f} s]",
              flush=True)


if __name__ == "__main__":
    main()
