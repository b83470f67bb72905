"""The fitness measures of `_filters`: the trend-free fitness the verdict compares
models by, against a plain NumPy reference, under jit and vmap, and on padding."""

import jax
import numpy as np
import pytest

import jaxstiction as js


def _reference(y, yhat, start, stop, degree):
    """NumPy: least-squares polynomial of `degree` in the sample index over
    [start, stop), removed from the error and from y."""
    t = np.arange(start, stop, dtype=float)
    V = np.vander(t - t.mean(), degree + 1)

    def detrended(v):
        v = np.asarray(v, float)[start:stop]
        return v - V @ np.linalg.lstsq(V, v, rcond=None)[0]

    return 100.0 * (1.0 - np.linalg.norm(detrended(y - yhat)) / np.linalg.norm(detrended(y)))


@pytest.fixture(scope="module")
def series():
    rng = np.random.default_rng(0)
    t = np.arange(400.0)
    y = np.sin(2 * np.pi * t / 37.0) + 0.3 * rng.standard_normal(400) + 0.01 * t
    yhat = np.sin(2 * np.pi * (t - 2) / 37.0)
    return y, yhat


@pytest.mark.parametrize("start, stop, degree", [(0, 400, 0), (0, 400, 2), (150, 400, 2), (30, 270, 5)])
def test_fitness_trend_free_equals_numpy(series, start, stop, degree):
    y, yhat = series
    w = np.zeros(400)
    w[start:stop] = 1.0
    got = float(js.fitness_trend_free(y, yhat, w, degree))
    assert got == pytest.approx(_reference(y, yhat, start, stop, degree), rel=1e-9, abs=1e-9)
    assert float(jax.jit(js.fitness_trend_free, static_argnums=3)(y, yhat, w, degree)) == pytest.approx(got, rel=1e-12)


def test_fitness_trend_free_ignores_the_trend_and_the_padding(series):
    """A quadratic added to the data changes nothing at degree 2 (it is removed from
    the data and from the error alike); masked samples appended change nothing; vmap
    equals a loop over parts."""
    y, yhat = series
    w = np.ones(400)
    base = float(js.fitness_trend_free(y, yhat, w, 2))
    t = np.arange(400.0)
    assert float(js.fitness_trend_free(y + 5.0 - 0.02 * t + 1e-4 * t ** 2, yhat, w, 2)) == pytest.approx(base)
    assert float(js.fitness_trend_free(y + 0.02 * t, yhat, w, 2)) == pytest.approx(base)
    assert float(js.fitness_trend_free(y + 1e-4 * t ** 2, yhat, w, 1)) != pytest.approx(base)
    pad = np.concatenate([y, 1e3 * np.ones(50)]), np.concatenate([yhat, -1e3 * np.ones(50)])
    assert float(js.fitness_trend_free(*pad, np.concatenate([w, np.zeros(50)]), 2)) == pytest.approx(base)
    parts = np.stack([(t < 200) * 1.0, (t >= 200) * 1.0])
    batched = jax.vmap(js.fitness_trend_free, in_axes=(None, None, 0, None))(y, yhat, parts, 2)
    assert np.asarray(batched) == pytest.approx([float(js.fitness_trend_free(y, yhat, p, 2)) for p in parts])
