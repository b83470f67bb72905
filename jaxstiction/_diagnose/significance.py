"""Name: what every candidate block is measured against, and each family's
significance.

`_baseline` checks the record, fits a linear-valve nominal model when none is given,
locates the mismatch, and sets up the refits: the data scaled, the nominal's poles
and delay, and a noise model held for every candidate (`_Baseline`). `_Grid` holds
the input candidates on their grids and scores every family's likelihood ratio
against the refitted linear valve. `_significance` computes those statistics on the
record and on the parametric bootstrap's records, and turns them into family-wise
p-values (the drift by its own test, the valve characteristic also by the operating
point the nominal states).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._checks import check_loop
from .._filters import lagged, lfilter
from .._linalg import lstsq
from .._misc import release_programs_near_map_limit, thread_map
from .._models import LinearProcess, LoopModel, NoiseModel
from .candidates import _arma11, _family_paths, _input_candidates, _linear_valve_nominal, _refit_b, _statistics
from .characteristic import characteristic_statistics
from .drift import drift_test
from .heldout import _bootstrap_noise, _jit_scored, _normal_sf, _null_tail
from .locate import locate
from .settings import DiagnoseSettings


@dataclasses.dataclass(frozen=True, eq=False)
class _Baseline:
    """The checked record, the nominal model and its residual `z`, where the mismatch
    is (`located`), and what every candidate is refitted against: the data scaled
    (`y`, `base_x`: the nominal chain's output, the valve position), the nominal's
    poles `a0` and delay, and the noise model `c0`/`d0` held for every candidate."""

    op: np.ndarray
    pv: np.ndarray
    n: int
    n_est: int
    given: bool
    nominal: LoopModel
    opj: jnp.ndarray
    pvj: jnp.ndarray
    t: jnp.ndarray
    whole: jnp.ndarray
    w_fit: jnp.ndarray
    sim_nom: np.ndarray
    z: np.ndarray
    located: dict
    delay: int
    nb: int
    mu: float
    sy: float
    om: float
    sx: float
    y: jnp.ndarray
    op_in: np.ndarray
    op_in_j: jnp.ndarray
    base_x: jnp.ndarray
    a_nom: np.ndarray
    c0: jnp.ndarray
    d0: jnp.ndarray

    def with_block(self, chain, x) -> LoopModel:
        """The nominal with `chain` added to its input chain, B and offset refitted."""
        th = np.asarray(_refit_b(x, self.y, self.w_fit, jnp.asarray(self.a_nom), self.c0, self.d0,
                                 jnp.asarray(self.delay), self.nb))
        b = np.concatenate([np.zeros(self.delay), th[:self.nb]]) * self.sy / self.sx
        return LoopModel(chain=tuple(self.nominal.chain) + tuple(chain), process=LinearProcess(b=b, a=self.a_nom),
                         noise=NoiseModel(c=self.c0, d=self.d0), op_offset=self.om,
                         pv_offset=self.mu + self.sy * th[self.nb], output=tuple(self.nominal.output))


def _baseline(loop, nominal, settings: DiagnoseSettings, say, name: str = "loop") -> _Baseline:
    """Check the record, fit a linear-valve nominal when none is given, locate the
    mismatch and set up the refits (see `_Baseline`)."""
    if np.ndim(loop.op) != 1:
        raise ValueError("diagnose takes one loop, not a batch")
    mask = np.asarray(loop.mask) > 0
    op, pv = check_loop(np.asarray(loop.op)[mask], np.asarray(loop.pv)[mask], name=name, min_length=300)
    op, pv = np.asarray(op, float), np.asarray(pv, float)
    n = len(op)
    n_est = int(round((1 - settings.holdout) * n))
    if n_est < 200 or n - n_est < 100:
        raise ValueError(f"record too short for a diagnosis: {n} samples (need 200 to fit and 100 held out)")
    given = nominal is not None
    if release_programs_near_map_limit():
        say("released compiled programs: the process neared its memory-map limit")
    if nominal is None:
        say("fitting a linear-valve nominal model")
        nominal = _linear_valve_nominal(op, pv, n_est, settings)
    opj, pvj = jnp.asarray(op), jnp.asarray(pv)
    t = jnp.arange(n)
    w_est = (t < n_est).astype(opj.dtype)
    whole = jnp.ones_like(opj)
    sim_nom = np.asarray(_jit_scored(nominal, opj, pvj, whole)[0])
    z = pv - sim_nom
    say("locating")
    located = locate(op[:n_est], z[:n_est], seed=settings.seed)

    # the nominal model, its poles held
    b_nom, a_nom = (np.asarray(v) for v in nominal.process.polynomials())
    nz = np.flatnonzero(np.abs(b_nom) > 0)
    delay = max(1, int(nz[0]) if nz.size else 1)
    nb = max(1, int(nz[-1] - delay + 1) if nz.size else 1)
    # candidate blocks act on the nominal chain's output (the valve position)
    op_in = np.asarray(nominal.valve(opj)) if nominal.chain else op
    mu, sy = float(np.mean(pv[:n_est])), float(np.std(pv[:n_est])) or 1.0
    om, sx = float(np.mean(op_in[:n_est])), float(np.std(op_in[:n_est])) or 1.0
    y = (pvj - mu) / sy
    op_in_j = jnp.asarray(op_in)
    base_x = (op_in_j - om) / sx
    a0 = jnp.asarray(a_nom)
    w_fit = w_est * (t >= 50)  # filter transients
    one = jnp.ones(1)
    # the noise model (held for every candidate) is that of the linear valve with
    # B and the offset refitted by output error: the nominal's own residual may
    # hold the whole unmodelled effect, which a noise model must not absorb
    th_oe = _refit_b(base_x, y, w_fit, a0, one, one, jnp.asarray(delay), nb)
    b_oe = jnp.concatenate([jnp.zeros(delay), th_oe[:nb]])
    r_oe = y - lfilter(b_oe, a0, base_x) - th_oe[nb]
    noise0 = _arma11(r_oe, w_fit)
    if noise0 is None:
        # an ARMA fit that failed or left the unit circle: an AR(1) noise model instead
        ar = float(np.clip(np.asarray(lstsq(lagged(r_oe, 1) * w_fit[:, None], r_oe * w_fit, 1e-12))[0], -0.99, 0.99))
        noise0 = one, jnp.asarray([1.0, -ar])
    c0, d0 = noise0
    return _Baseline(op=op, pv=pv, n=n, n_est=n_est, given=given, nominal=nominal, opj=opj, pvj=pvj, t=t,
                     whole=whole, w_fit=w_fit, sim_nom=sim_nom, z=z, located=located, delay=delay, nb=nb, mu=mu,
                     sy=sy, om=om, sx=sx, y=y, op_in=op_in, op_in_j=op_in_j, base_x=base_x, a_nom=a_nom, c0=c0, d0=d0)


@dataclasses.dataclass(frozen=True, eq=False)
class _Grid:
    """The input candidates on their grids (`fams`: each family's blocks and
    parameters; `slices`: their rows of `xs`, the scaled valve paths) and the
    oscillation's frequency range."""

    b: _Baseline
    fams: dict
    paths: jnp.ndarray
    slices: dict
    xs: jnp.ndarray
    fmin: float
    fmax: float
    count: float

    @classmethod
    def build(cls, b: _Baseline, settings: DiagnoseSettings) -> _Grid:
        fams = _input_candidates(b.op_in[:b.n_est], settings.grid)
        paths, slices = _family_paths(b.op_in_j, fams)
        return cls(b=b, fams=fams, paths=paths, slices=slices, xs=(paths - b.om) / b.sx, fmin=4.0 / b.n_est,
                   fmax=0.25, count=float(jnp.sum(b.w_fit)))

    def stats(self, yy):
        """Every family's likelihood ratio against the refitted linear valve on the
        scaled record `yy`, each input candidate's loss, and the best frequency."""
        b = self.b
        v_in, v_sin, v0, f_best = _statistics(yy, self.xs, b.base_x, b.w_fit, jnp.asarray(b.a_nom), b.c0, b.d0,
                                              jnp.asarray(b.delay), b.nb, self.fmin, self.fmax)
        v_in = np.asarray(v_in)
        T = {f: self.count * float(np.log(float(v0) / np.min(v_in[sl]))) for f, sl in self.slices.items()}
        T["external_oscillation"] = self.count * float(np.log(float(v0) / float(v_sin)))
        return T, v_in, float(f_best)

    def param_table(self, fam: str, v_in):
        """The family's best grid point, its parameters, and their 95 % profile
        intervals."""
        sl = self.slices[fam]
        vv = v_in[sl]
        k = int(np.argmin(vv))
        points = self.fams[fam][1]
        params = dict(points[k])
        inside = self.count * np.log(vv / vv[k]) <= 3.84  # profile: chi2(1, 95 %)
        iv = {}
        for key_ in params:
            vals = np.array([points[i][key_] for i in range(len(vv)) if inside[i] and key_ in points[i]])
            if vals.size:
                iv[key_] = [round(float(vals.min()), 4), round(float(vals.max()), 4)]
        return k, {k_: round(float(v_), 4) for k_, v_ in params.items()}, iv


@dataclasses.dataclass(frozen=True, eq=False)
class _Significance:
    """The observed statistics (`T_obs`, the input candidates' losses `v_in`, the
    oscillation's best frequency, the drift test), the bootstrap's noise records and
    null moments, the family-wise p-values, and the valve characteristic's
    operating-point test."""

    base_model: LoopModel
    base_sim: np.ndarray
    T_obs: dict
    v_in: np.ndarray
    f_best: float
    drift_obs: tuple
    pv_boot: list
    names: list
    med: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    pvals: dict
    T_op: np.ndarray
    op_losses: np.ndarray
    p_op: float
    by_op: bool


def _significance(b: _Baseline, g: _Grid, settings: DiagnoseSettings, say) -> _Significance:
    """Each family's statistic on the record and on the parametric bootstrap's
    records, and its p-value (see the module notes)."""
    say(f"scoring {g.paths.shape[0]} input blocks, oscillations and drift")
    # the reference every block must beat: the linear valve, refitted the same way
    base_model = b.with_block((), b.base_x)
    base_sim = np.asarray(_jit_scored(base_model, b.opj, b.pvj, b.whole)[0])
    T_obs, v_in, f_best = g.stats(b.y)
    # the drift is tested on the nominal's own residual: refitting B would let OP,
    # which the controller moves against the drift, absorb part of it
    drift_obs = drift_test(jnp.asarray(b.z[:b.n_est]))
    T_obs["drift"] = float(drift_obs[0])

    say(f"bootstrap: {settings.bootstrap} replicates")
    pv_boot = _bootstrap_noise(b.c0, b.d0, b.pv - base_sim, b.n_est, jr.key(settings.seed), settings.bootstrap, b.n)
    T_boot = thread_map(lambda v: g.stats((jnp.asarray(base_sim + v) - b.mu) / b.sy)[0], pv_boot)
    names = list(T_obs)
    Tb = np.array([[tb.get(f, np.nan) for f in names] for tb in T_boot])  # (B, F)
    med = np.median(Tb, axis=0)
    mean, std = Tb.mean(axis=0), np.maximum(Tb.std(axis=0, ddof=1), 1e-9)
    # each family's null from the bootstrap (normal approximation of its tail, so the
    # p-values are not limited to 1/(B+1)), Bonferroni over the families searched
    pvals = {f: min(1.0, len(names) * _normal_sf((T_obs[f] - mean[i]) / std[i])) for i, f in enumerate(names)}
    # The drift's null is not the shared records': their noise model was fitted with
    # any drift left in, so its pole sits near 1 and their statistics would hide the
    # drift. Its statistic (a log-likelihood ratio, q = 0 on the boundary) is judged
    # by the chi-bar-squared mixture 1/2 chi2(0) + 1/2 chi2(1) of twice its value,
    # which is conservative here: on 800 stationary AR(1) records (pole 0.9 or 0.5,
    # 2000 samples) the statistic was 0 on 62-69 % of them, not 50 %, and exceeded
    # 1.0, 2.0 and 3.3 half to three quarters as often as the mixture says.
    pvals["drift"] = min(1.0, len(names) * 0.5 * math.erfc(math.sqrt(T_obs["drift"]))) if T_obs["drift"] > 0 else 1.0
    # A valve characteristic is also judged by the operating point the nominal states
    # (`characteristic`: the grid's refit of B and the offset absorbs that evidence);
    # the family's p-value is the smaller of its two tests', doubled.
    b_p, a_p = b.nominal.process.polynomials()
    recs = jnp.asarray(np.stack([b.z] + pv_boot))  # the observed error, then the bootstrap's noise records
    T_op, op_losses = (np.asarray(v) for v in characteristic_statistics(b.op_in_j, recs, b_p, a_p, b.c0, b.d0,
                                                                         b.w_fit))
    p_op = 1.0
    if T_op[0] > 0:
        p_op = min(1.0, len(names) * _null_tail(T_op[0], T_op[1:]))
    by_op = p_op < pvals["valve_characteristic"]
    pvals["valve_characteristic"] = min(1.0, 2.0 * min(p_op, pvals["valve_characteristic"]))
    return _Significance(base_model=base_model, base_sim=base_sim, T_obs=T_obs, v_in=v_in, f_best=f_best,
                         drift_obs=tuple(drift_obs), pv_boot=pv_boot, names=names, med=med, mean=mean, std=std,
                         pvals=pvals, T_op=T_op, op_losses=op_losses, p_op=p_op, by_op=by_op)


