"""Tests for the fit pictures (`_plots`), on a synthetic stand-in for `LoopFit`."""

import struct
import sys
import types

import matplotlib
import numpy as np
import pytest

from jaxstiction.internal import write_fit_figures


NAMES = ["valve_curve.png", "step_response.png", "model_fit.png", "op_pv.png"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def fake_fit(n_est=400, n_val=400, **overrides):
    """A `LoopFit`-like namespace with synthetic arrays (the estimator is not run)."""
    rng = np.random.default_rng(0)
    n = n_est + n_val
    k = np.arange(n)
    op = 50 + 10 * np.sin(2 * np.pi * k / 90) + rng.normal(0, 0.3, n)
    pv = 20 + 0.5 * np.sin(2 * np.pi * (k - 6) / 90) + rng.normal(0, 0.05, n)
    u = np.linspace(op.min(), op.max(), 400)
    up = np.clip(u - 3.0, u[0], u[-1])
    down = np.clip(u + 3.0, u[0], u[-1])
    step = 0.05 * (1 - 0.8 ** np.maximum(np.arange(60) - 2, 0))
    fields = dict(
        name="synthetic loop",
        ts=10.0,
        n_estimation=n_est,
        n_validation=n_val,
        model_kind="spline",
        fitness=87.25,
        fitness_paper=80.5,
        direction_rule="robust",
        num_knots=5,
        order=2,
        delay=2,
        band_percent=6.0,
        S=None,
        J=None,
        S_interval=None,
        J_interval=None,
        op=op,
        pv=pv,
        pv_sim=pv + rng.normal(0, 0.03, n),
        pv_sim_paper=pv + rng.normal(0, 0.06, n),
        valve_u=u,
        valve_up=up,
        valve_down=down,
        step=step,
    )
    fields.update(overrides)
    return types.SimpleNamespace(**fields)


def mpl_state():
    # `_get` reads the backend without resolving it (which would import pyplot)
    return {key: matplotlib.rcParams._get(key) for key in matplotlib.rcParams}


def check_pngs(paths, out_dir):
    assert [p.name for p in paths] == NAMES
    for path in paths:
        assert path.parent == out_dir and path.is_file()
        data = path.read_bytes()
        assert data[:8] == PNG_MAGIC, path
        assert len(data) > 5_000, (path, len(data))
        width, height = struct.unpack(">II", data[16:24])  # IHDR
        assert 600 <= width <= 1400 and 300 <= height <= 900, (path, width, height)


CASES = {
    "spline": ({}, {}),
    "physical-S-validation-noise-free": (
        dict(model_kind="physical", S=6.3, J=1.2, S_interval=(5.9, 6.7), J_interval=(0.8, 1.6), band_percent=6.3),
        dict(validation_start=400, noise_free=True),
    ),
    "nan-band-no-validation": (dict(band_percent=float("nan"), n_est=800, n_val=0), {}),
    "short-record-S-without-intervals": (dict(n_est=100, n_val=50, S=4.0), dict(validation_start=100)),
}


@pytest.mark.parametrize("overrides, kwargs", CASES.values(), ids=CASES.keys())
def test_write_fit_figures(tmp_path, overrides, kwargs):
    result = fake_fit(**overrides)
    if kwargs.get("noise_free"):
        kwargs = dict(kwargs, noise_free=result.pv - 0.02)
    before = mpl_state()
    had_pyplot = "matplotlib.pyplot" in sys.modules
    out_dir = tmp_path / "figs" / "loop"  # nested: must be created
    paths = write_fit_figures(result, out_dir, **kwargs)
    check_pngs(paths, out_dir)
    # the backend and every rcParam are untouched, and pyplot was not imported
    assert mpl_state() == before
    if not had_pyplot:
        assert "matplotlib.pyplot" not in sys.modules


def _line_labels(ax):
    return [line.get_label() for line in ax.get_lines()]


@pytest.mark.parametrize("runaway", [False, True])
def test_model_fit_gives_a_runaway_curve_its_own_panel(runaway):
    """A paper's-method curve that leaves the measured PV's range is drawn in a
    panel of its own, never over the data, whose axes keep the measured PV's range."""
    from jaxstiction.internal import model_fit_figure

    result = fake_fit()
    if runaway:
        k = np.arange(result.pv.shape[0])
        result.pv_sim_paper = result.pv + 1e3 * 1.01 ** k  # diverges
        result.fitness_paper = -3e5
    fig = model_fit_figure(result, 400, result.pv - 0.02)
    assert len(fig.axes) == (3 if runaway else 2)
    lo, hi = result.pv.min(), result.pv.max()
    for ax in fig.axes[:2]:
        labels = _line_labels(ax)
        assert ("paper's method (80.5 %)" in labels) != runaway
        assert any("model" in lab for lab in labels) and "noise-free PV" in labels
        y0, y1 = ax.get_ylim()
        assert y0 < lo and hi < y1 < hi + 2 * (hi - lo)  # limits from the data, not the runaway curve
    if runaway:
        own = fig.axes[2]
        assert own.get_yscale() == "symlog"
        assert "paper's method (-300000.0 %)" in _line_labels(own)


def test_model_fit_without_the_paper_method():
    """A fit that did not run the paper's method (its curve NaN) draws none."""
    from jaxstiction.internal import model_fit_figure

    result = fake_fit(pv_sim_paper=np.full(800, np.nan), fitness_paper=float("nan"))
    fig = model_fit_figure(result, 400, None)
    assert len(fig.axes) == 2
    assert not any("paper" in lab for ax in fig.axes for lab in _line_labels(ax))
