r"""A calibrated stiction probability from all the evidence of one loop.

Each loop's evidence (the indicators of `_indicators`, the blocked cross-validation
of `_crossval`, the model-based gains of `jaxstiction.verdict`) is mapped to a
feature vector of fixed meaning (`FEATURES`, `features`); a logistic model turns it
into a probability. Its coefficients (`Calibration`) are fitted by
`fit_calibration` (L2-penalised logistic regression, Newton steps) in
`benchmarks/calibrate_probability.py`, on a simulated realistic fleet and the
labelled real records, and stored in `_calibration.py`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._linalg import spd_solve


class Calibration(eqx.Module):
    """Coefficients of the logistic stiction probability: `names` (static, the
    features in order), their `mean` and `scale` (standardisation) and `weights`,
    and the `bias`. `p = 1 / (1 + exp(-(bias + weights · (x - mean) / scale)))`; a
    feature that is NaN (missing: it could not be judged) is taken at its mean."""

    names: tuple = eqx.field(static=True)
    mean: Float[Array, " features"]
    scale: Float[Array, " features"]
    weights: Float[Array, " features"]
    bias: Float[Array, ""]

    def logit(self, x: Float[Array, " features"]) -> Float[Array, ""]:
        z = jnp.where(jnp.isfinite(x), (x - self.mean) / self.scale, 0.0)
        return self.bias + jnp.dot(self.weights, z)

    def probability(self, x: Float[Array, " features"]) -> Float[Array, ""]:
        return jax.nn.sigmoid(self.logit(x))


def fit_calibration(X, y, sample_weight=None, *, l2: float = 1.0, names: tuple = (), steps: int = 50) -> Calibration:
    """L2-penalised logistic regression (Newton's method; the bias unpenalised) of
    labels `y` (0/1) on the rows of `X`, each row weighted by `sample_weight`.
    Features are standardised first (mean and standard deviation of `X`); a NaN
    entry (a missing feature) is taken at its column's mean, as `Calibration.logit`
    takes it."""
    X = jnp.asarray(X)
    y = jnp.asarray(y, X.dtype)
    w = jnp.ones_like(y) if sample_weight is None else jnp.asarray(sample_weight, X.dtype)
    seen = jnp.isfinite(X)
    ws = seen * w[:, None]
    mean = jnp.sum(jnp.where(seen, X, 0.0) * w[:, None], axis=0) / jnp.maximum(jnp.sum(ws, axis=0), 1e-300)
    X = jnp.where(seen, X, mean)
    scale = jnp.sqrt(jnp.average((X - mean) ** 2, axis=0, weights=w))
    scale = jnp.where(scale > 0, scale, 1.0)
    Z = jnp.concatenate([jnp.ones((X.shape[0], 1), X.dtype), (X - mean) / scale], axis=1)
    pen = l2 * jnp.diag(jnp.concatenate([jnp.zeros((1,), X.dtype), jnp.ones((X.shape[1],), X.dtype)]))

    def newton(theta, _):
        p = jax.nn.sigmoid(Z @ theta)
        H = Z.T @ (Z * (w * p * (1 - p))[:, None]) + pen + 1e-9 * jnp.eye(Z.shape[1], dtype=X.dtype)
        g = Z.T @ (w * (y - p)) - pen @ theta
        return theta + spd_solve(H, g), None

    theta, _ = jax.lax.scan(newton, jnp.zeros((Z.shape[1],), X.dtype), None, length=steps)
    names = tuple(names) if names else tuple(f"x{i}" for i in range(X.shape[1]))
    return Calibration(names=names, mean=mean, scale=scale, weights=theta[1:], bias=theta[0])
