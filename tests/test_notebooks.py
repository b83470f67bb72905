"""The notebooks are stored with their outputs (notebooks/README.md): each must be a
valid notebook, run top to bottom in one session, with no error among its outputs."""

import pathlib

import nbformat
import pytest


NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_the_three_notebooks_are_there():
    assert {p.stem for p in NOTEBOOKS} == {"paper_sim", "chem23", "gradients"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_stored_as_run(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code, f"{path.name} has no code cells"
    counts = [c.execution_count for c in code]
    assert None not in counts, f"{path.name}: cell {counts.index(None)} was not run"
    assert counts == list(range(1, len(code) + 1)), f"{path.name}: cells not run in order from a fresh kernel"
    errors = [o for c in code for o in c.outputs if o.output_type == "error"]
    assert not errors, f"{path.name}: stored error {errors[0].ename}: {errors[0].evalue}"
    # the figures are stored with the rest (at least one picture)
    images = [o for c in code for o in c.outputs if "image/png" in o.get("data", {})]
    assert images, f"{path.name} stores no figure"
