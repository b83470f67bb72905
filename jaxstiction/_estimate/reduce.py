r"""Reduction of the high-order model to a low-order Box–Jenkins model: (17)–(23).

The frequency-weighted criterion (19) between $\hat G^n$ and
$G^l = q^{-n_k} B^l / A^l$ is weighted by the inverse of the asymptotic variance
(18). (The paper prints the weight of (19) upside down; Zhu (1998) weights
by the inverse variance, which is what is done here.) It is minimised with
`optx.GaussNewton`, started from a Sanathanan–Koerner linear fit. All candidate
orders $l$ and delays $n_k$ share one padded parameter shape and are solved in one
`vmap`; ASYC (21) picks among them.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from .._filters import freq_response, lagged, lfilter
from .._linalg import HouseholderQR, is_stable, lstsq as _lstsq
from .._misc import first_min


def welch(x, e, seg: int, weights=None):
    """Smoothed auto- and cross-spectra of `x`, `e` (Hann-windowed segments of length
    `seg`, half overlap). Returns angular frequencies in (0, pi] and Phi_x, Phi_e,
    Phi_xe on them (two-sided scaling: white noise of variance R has Phi = R).

    `weights` (time,) in {0, 1}: only segments lying wholly on samples with weight 1
    are averaged, so masked or padded samples never dilute the spectra.
    """
    N = x.shape[0]
    step = seg // 2
    starts = jnp.arange(0, N - seg + 1, step)
    win = jnp.hanning(seg + 2)[1:-1].astype(x.dtype)
    norm = jnp.sum(win**2)
    w_all = jnp.ones((N,), x.dtype) if weights is None else weights

    def one(s):
        xs = jax.lax.dynamic_slice(x, (s,), (seg,))
        es = jax.lax.dynamic_slice(e, (s,), (seg,))
        ok = jnp.min(jax.lax.dynamic_slice(w_all, (s,), (seg,))) > 0
        X = jnp.fft.rfft(win * (xs - xs.mean()))
        E = jnp.fft.rfft(win * (es - es.mean()))
        return jnp.abs(X) ** 2, jnp.abs(E) ** 2, X * jnp.conj(E), ok.astype(x.dtype)

    pxx, pee, pxe, ok = jax.vmap(one)(starts)
    cnt = jnp.maximum(jnp.sum(ok), 1.0)

    def avg(p):
        return jnp.sum(ok[:, None] * p, 0) / cnt

    w = 2 * jnp.pi * jnp.arange(seg // 2 + 1) / seg
    sl = slice(1, None)
    return w[sl], avg(pxx)[sl] / norm, avg(pee)[sl] / norm, avg(pxe)[sl] / norm


class LowOrder(eqx.Module):
    """Low-order transfer function $q^{-n_k} B^l/A^l$, padded to `max_order`.
    `a` = $[a_1..a_L]$, `b` = $[b_0..b_{L-1}]$ multiplying $q^{-n_k}\\dots q^{-n_k-L+1}$,
    `mask` marks the active coefficients (first `order` of each)."""

    a: Float[Array, " L"]
    b: Float[Array, " L"]
    delay: Array
    mask: Float[Array, " L"]

    def polynomials(self, max_delay: int):
        """`(b_full, a_full)` coefficient arrays from $q^0$ (static length)."""
        L = self.a.shape[0]
        b_full = jnp.zeros((max_delay + L,), self.b.dtype)
        b_full = b_full.at[self.delay + jnp.arange(L)].set(self.b * self.mask)
        a_full = jnp.concatenate([jnp.ones((1,), self.a.dtype), self.a * self.mask])
        return b_full, a_full


def _freq(model: LowOrder, w, max_delay):
    b, a = model.polynomials(max_delay)
    return freq_response(b, a, w)


class ReductionSolution(eqx.Module):
    """All reduction candidates (leading axis) and ASYC's choice `best`."""

    models: LowOrder
    criterion: Float[Array, " cand"]
    asyc: Float[Array, " cand"]
    stable: Array
    result: optx.RESULTS
    best: Array


def _sk_init(Gn, sw, w, order, delay, L, ridge=1e-10):
    # Sanathanan–Koerner: minimise sum W |A G^n - q^-nk B|^2, linear in (a, b).
    mask = (jnp.arange(L) < order).astype(Gn.real.dtype)
    k = jnp.arange(1, L + 1)
    za = jnp.exp(-1j * w[:, None] * k[None, :])
    zb = jnp.exp(-1j * w[:, None] * (delay + k[None, :] - 1))
    cols = jnp.concatenate([sw[:, None] * Gn[:, None] * za * mask, -sw[:, None] * zb * mask], axis=1)
    M = jnp.concatenate([cols.real, cols.imag], axis=0)
    v = jnp.concatenate([-(sw * Gn).real, -(sw * Gn).imag])
    th = _lstsq(M, v, ridge)
    return LowOrder(a=th[:L], b=th[L:], delay=delay, mask=mask)


def reduce_model(
    Gn: Float[Array, " freq"],
    weight: Float[Array, " freq"],
    w: Float[Array, " freq"],
    variance: Float[Array, " freq"],
    *,
    max_order: int = 4,
    max_delay: int = 3,
    rtol=1e-8,
    atol=1e-10,
    max_steps=100,
) -> ReductionSolution:
    r"""Fit $G^l$ for every order $1..$`max_order` and delay $1..$`max_delay` to the
    high-order frequency response `Gn` by (19), in one `vmap`, and choose by ASYC (21):
    $\sum_\omega \big|\,|G^n - G^l|^2 - \mathrm{var}\,G^n\big|$ (the absolute value
    makes "difference about equal to the variance" a minimisation, as Zhu intends).
    """
    L, D = max_order, max_delay
    orders = jnp.repeat(jnp.arange(1, L + 1), D)
    delays = jnp.tile(jnp.arange(1, D + 1), L)
    sw = jnp.sqrt(weight)
    solver = optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=HouseholderQR())

    def one(order, delay):
        init = _sk_init(Gn, sw, w, order, delay, L)

        def resid(theta, _):
            m = LowOrder(a=theta[0], b=theta[1], delay=delay, mask=init.mask)
            d = sw * (Gn - _freq(m, w, D))
            pin = jnp.concatenate([theta[0], theta[1]]) * jnp.tile(1.0 - init.mask, 2)
            return jnp.concatenate([d.real, d.imag, pin])

        sol = optx.least_squares(
            resid, solver, (init.a, init.b), max_steps=max_steps, throw=False
        )
        m = LowOrder(a=sol.value[0], b=sol.value[1], delay=delay, mask=init.mask)
        a_full = m.polynomials(D)[1]
        stable = is_stable(a_full)
        diff = jnp.abs(Gn - _freq(m, w, D)) ** 2
        crit = jnp.mean(weight * diff)
        asyc = jnp.where(stable & jnp.all(jnp.isfinite(diff)), jnp.mean(jnp.abs(diff - variance)), jnp.inf)
        return m, crit, asyc, stable, sol.result

    models, crit, asyc, stable, result = jax.vmap(one)(orders, delays)
    best = first_min(asyc)
    return ReductionSolution(models, crit, asyc, stable, result, best)


def asymptotic_weight(a_n, b_n, x, y, *, order: int, count, seg: int, weights=None):
    r"""High-order frequency response $\hat G^n$, the inverse-variance weight of (19)
    and the asymptotic variance (18), on a Welch frequency grid.

    With $\hat e = A^n y - B^n \hat x$, $R = \mathrm{var}\,\hat e$, $\Phi_v = R/|A^n|^2$:
    $\mathrm{var}\,\hat G^n = \frac{n}{N}\frac{\Phi_v R}{\Phi_x R - |\Phi_{xe}|^2}$.
    """
    a_full = jnp.concatenate([jnp.ones((1,), a_n.dtype), a_n])
    b_full = jnp.concatenate([jnp.zeros((1,), b_n.dtype), b_n])
    e = lfilter(a_full, jnp.ones((1,), a_n.dtype), y) - lfilter(b_full, jnp.ones((1,), a_n.dtype), x)
    e = e.at[:order].set(0.0)
    if weights is not None:
        # a residual is valid only where its whole regression window is on data
        valid = weights * jnp.prod(lagged(weights, order), axis=1)
        e = e * valid
    w, pxx, pee, pxe = welch(x, e, seg, weights)
    R = jnp.sum(e**2) / count
    Gn = freq_response(b_full, a_full, w)
    An = freq_response(a_full, jnp.ones((1,), a_n.dtype), w)
    phiv = R / jnp.abs(An) ** 2
    denom = jnp.maximum(pxx * R - jnp.abs(pxe) ** 2, 1e-3 * pxx * R)
    variance = order / count * phiv * R / denom
    weight = 1.0 / variance * (order / count)
    weight = weight / jnp.mean(weight)
    return w, Gn, weight, variance, e, R


class NoiseModel(eqx.Module):
    """$H = C/D$ with `c` = $[c_1..]$, `d` = $[d_1..]$, and the innovation variance."""

    c: Float[Array, " nc"]
    d: Float[Array, " nd"]
    variance: Float[Array, ""]
    result: optx.RESULTS


@eqx.filter_jit  # one program per shape and order, also when called eagerly
def fit_noise_model(v, weights, *, order: int = 1, max_steps=100) -> NoiseModel:
    r"""Low-order ARMA noise model $v = \frac{C}{D} e$ (23) for the output-error
    residual `v`, by Gauss–Newton on the prediction error $\varepsilon = \frac{D}{C} v$,
    started from an AR fit."""
    dtype = v.dtype
    # Start: AR(order) by least squares.
    V = lagged(v, order) * weights[:, None]
    d0 = -_lstsq(V, v * weights, 1e-10)

    def resid(theta, _):
        c, d = theta
        eps = lfilter(jnp.concatenate([jnp.ones((1,), dtype), d]), jnp.concatenate([jnp.ones((1,), dtype), c]), v)
        return eps * weights

    sol = optx.least_squares(
        resid,
        optx.GaussNewton(rtol=1e-8, atol=1e-10, linear_solver=HouseholderQR()),
        (jnp.zeros((order,), dtype), d0),
        max_steps=max_steps,
        throw=False,
    )
    one = jnp.ones((1,), dtype)

    def invertible(c, d):  # `is_stable` is False for non-finite coefficients too
        return is_stable(jnp.concatenate([one, c])) & is_stable(jnp.concatenate([one, d]))

    c, d = sol.value
    ok = invertible(c, d)
    # Where C and D nearly cancel (a residual close to white), Gauss-Newton can wander
    # along that ridge out of the unit circle (CHEM11's spline model: C and D with
    # roots at -3.137 and -3.135). Such a model's prediction errors D/C v diverge, and
    # so does every initial-state search and k-step prediction whitened by it: the
    # result code says so, and the model falls back to the AR start (C = 1), or to
    # white noise when that is unstable too.
    zeros = jnp.zeros((order,), dtype)
    ar_ok = invertible(zeros, d0)
    c = jnp.where(ok, c, zeros)
    d = jnp.where(ok, d, jnp.where(ar_ok, d0, zeros))
    result = optx.RESULTS.where(ok, sol.result, optx.RESULTS.nonlinear_divergence)
    eps = resid((c, d), None)
    return NoiseModel(c=c, d=d, variance=jnp.sum(eps**2) / jnp.sum(weights), result=result)
