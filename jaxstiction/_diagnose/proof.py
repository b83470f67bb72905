"""Prove: the run-to-run spread of a candidate's held-out gain against the
bootstrap's records, and the narrow-band test of an oscillation (`_Proof`), on
top of the held-out figures of `heldout`."""

from __future__ import annotations

import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .heldout import (
    _band_statistics,
    _heldout,
    _jit_kstep_rms,
    _jit_scored,
    _jit_scores,
    _noise_records,
    _null_tail,
    _shift_phase,
)
from .settings import DiagnoseSettings
from .significance import _Baseline, _Significance


class _Proof:
    """Held-out proof of a candidate against the bootstrap's records: the run-to-run
    spread of its gains, and the narrow-band test of an oscillation. `before`: the
    nominal's held-out figures."""

    def __init__(self, b: _Baseline, s: _Significance, settings: DiagnoseSettings):
        self.b, self.s, self.settings = b, s, settings
        self.before = _heldout(b.nominal, b.op, b.pv, b.n_est)
        # id(reference) -> (reference, records, its held-out score on each); holding the
        # reference keeps its id from being reused by a later object
        self._ref_scores = {}

    def null_gain(self, model, reference=None):
        """Held-out gains of `model` over `reference` (default: the nominal) on the
        bootstrap records (simulated from `reference` when one is given, else from the
        refitted linear valve) plus fresh noise. Their standard deviation is the
        run-to-run spread of a gain: the noise common to both scores cancels."""
        b, s = self.b, self.s
        ref = b.nominal if reference is None else reference
        op_hold = b.opj[b.n_est:]
        if id(ref) not in self._ref_scores:  # the reference's scores serve every candidate
            data = s.base_sim if reference is None else np.asarray(_jit_scored(ref, b.opj, b.pvj, b.whole)[0])
            recs = jnp.asarray(np.stack([(data + v)[b.n_est:] for v in s.pv_boot]))  # held-out parts
            self._ref_scores[id(ref)] = (ref, recs, np.asarray(_jit_scores(_shift_phase(ref, b.n_est), op_hold, recs)))
        _, recs, base = self._ref_scores[id(ref)]
        gains = np.asarray(_jit_scores(_shift_phase(model, b.n_est), op_hold, recs)) - base
        return float(np.mean(gains)), float(np.std(gains))

    def null_kstep_gain(self, model, reference, pole):
        """Held-out k-step RMS gains of `model` over `reference` on records of the
        reference's stationary null: the nominal's simulation plus AR(1) noise with
        `pole` and the innovation scale the nominal's residual leaves."""
        b, settings = self.b, self.settings
        zc = b.z[:b.n_est] - np.mean(b.z[:b.n_est])
        sig = float(np.std(zc[1:] - pole * zc[:-1]))
        noise = _noise_records(jnp.ones(1), jnp.asarray([1.0, -pole]), jr.key(settings.seed + 1), sig,
                               settings.bootstrap, b.n)
        recs = jnp.asarray(b.sim_nom)[None, :] + noise
        gains = np.asarray(_jit_kstep_rms(reference, b.opj, recs, b.n_est + 20)) - np.asarray(
            _jit_kstep_rms(model, b.opj, recs, b.n_est + 20))
        return float(np.mean(gains)), float(np.std(gains))

    def narrow_band(self, ev, params, gain, resid, c, d, period, base="the nominal"):
        """Is the oscillation, whose sinusoid did not hold up held out, a narrow-band
        disturbance whose band persists on the held-out part? A disturbance whose
        phase wanders (PAP7's, period ~54 samples) is no sinusoid: fitted on the
        estimation part, its phase is wrong held out and the simulation loses. Its
        band's excess over the neighbouring frequencies (`_band_statistics`, on the
        held-out part of `resid`, the residual of the model it would be added to,
        whitened by `c`/`d`) is tested against the same statistic on the bootstrap's
        noise records (one test at `alpha`). Updates `ev` and, when accepted, `params`
        (a band has no amplitude or phase: the sinusoid's move to `ev`)."""
        b = self.b
        recs = jnp.asarray(np.stack([resid] + self.s.pv_boot) / b.sy)
        w_h = (b.t >= b.n_est + 50).astype(b.opj.dtype)
        lr = np.log(np.asarray(_band_statistics(recs, c, d, w_h, 1.0 / float(period))))
        p_h = _null_tail(lr[0], lr[1:])
        ev.update(heldout_band_log_ratio=round(float(lr[0]), 3), heldout_band_null_median=round(
            float(np.median(lr[1:])), 3), heldout_band_p_value=round(p_h, 4))
        if p_h > self.settings.alpha:
            return False
        ev.update(kind="narrow-band", stochastic=True, sinusoid_heldout_gain=round(gain, 3), heldout_gain=0.0,
                  sinusoid_k_step_gain=ev.get("k_step_gain"), k_step_gain=0.0,
                  sinusoid_amplitude=params.pop("amplitude"), sinusoid_phase=params.pop("phase"),
                  note=(f"a narrow-band disturbance, not a sinusoid: the sinusoid fitted on the estimation data "
                        f"gains {gain:+.2f} points held out (its phase wanders), but the band's excess power "
                        f"persists held out (p = {p_h:.4f}); a stochastic disturbance, so no simulation gain "
                        f"is claimed and the model is {base}"))
        params["band_period_samples"] = [round(float(period) / 1.1, 3), round(float(period) / 0.9, 3)]
        return True
