r"""Mismatch diagnosis: locate where a nominal simulation and a recording differ,
name the missing physics, model it, and prove the gain on held-out data.

A diagnosis is the nominal [`jaxstiction.LoopModel`][] plus one block of the library
(or two), refitted. The steps:

1. **Locate** ([`jaxstiction._diagnose.locate`]): tests on the simulation residual and on the
   one-step error of a refitted noise model.
2. **Name** ([`jaxstiction._diagnose.candidates`],
   [`jaxstiction._diagnose.significance`]). Every
   input-side candidate family (stiction, deadband, dead time, valve characteristic,
   travel limit, actuator lag) is added to the nominal model on a grid of its
   parameters, the linear part refitted by least squares at each point
   (all points in one `vmap`); an external oscillation is searched at every
   frequency. A family's statistic is the likelihood ratio $T = N \log(V_0 / V)$ of
   its best point against the refitted linear valve. The parameters are searched, so
   textbook $\chi^2$ thresholds do not hold: significance comes from a parametric
   bootstrap (the refitted nominal model plus noise from its fitted noise model,
   with the recorded OP), a normal approximation of each family's null tail, and a
   Bonferroni correction over the families. Drift has its own likelihood-ratio test
   ([`jaxstiction._diagnose.drift`]) on the nominal's residual, judged by its (conservative)
   chi-bar-squared null. A valve characteristic is also tested by the operating
   point the nominal states ([`jaxstiction._diagnose.characteristic`]: an equal-percentage
   block added with nothing refitted), which the refit of B and the offset hides.
3. **Model and prove** ([`jaxstiction._diagnose.heldout`], [`jaxstiction._diagnose.proof`];
   without a nominal model, stiction also jointly with the linear part,
   [`jaxstiction._diagnose.joint`]). Each significant family's best block is added to the
   nominal: input blocks with B and the offset refitted, output blocks (oscillation,
   drift) to the nominal as it is. It is scored on the held-out samples (simulation
   fitness from an estimated initial state, one-step and k-step prediction errors).
   A block is accepted when it is significant and improves held-out simulation
   fitness by more than the run-to-run spread (bootstrap); an input block's gain must
   also be its own, not the refit's (`_gain_from_the_block`); output blocks must also
   leave a residual that passes the input cross-correlation test. Accepted blocks
   are ranked by their penalised likelihood ratio; stiction against deadband by the
   significance of J. The first names the verdict; an external oscillation is then
   tested as a second block on top of it. Only what the diagnosed model holds stays
   `accepted`: the other blocks that passed on their own are alternative
   explanations of the same mismatch (never fitted together with the verdict's),
   marked `alternative_to` and not accepted. Effects that no deterministic block
   can predict (quantisation; drift) are named from their own evidence and reported with no simulation gain.
4. **One stiction policy with the screen** (no nominal model only): the screen's
   stiction verdict ([`jaxstiction.verdict`][], its light `estimate` on the same
   record) decides whether the valve sticks. A sticky valve is named `stiction` when
   its slip is identified, else `deadband` (a band with no visible slip: the J = 0
   member of the Kano family; to a plant engineer the same valve fault); a valve
   it does not call sticky is named neither. `Diagnosis.stiction` holds that
   verdict (probability, band seen, slip identified, gate and reason) and a note
   when it changed the name.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._blocks import EqualPercentage, Sinusoid
from .._estimate.estimate import estimate
from .._estimate.settings import SCREEN_ESTIMATE
from .._filters import lfilter
from .._loop import bucket_length, make_loop, pad
from .._misc import warn_without_float64
from .._models import LoopModel, NoiseModel
from .._verdict.gate import GATES
from .._verdict.verdict import verdict, verdict_reason, VERDICTS
from .candidates import _arma11, _fit_sinusoid, _quantisation
from .characteristic import rangeability_profile
from .drift import drift_noise_model
from .heldout import (
    _add_output,
    _diff,
    _heldout,
    _jit_scored,
    _normal_sf,
    _prove,
    _residual_cross_correlation,
    _revised,
    Finding,
    K_STEP,
)
from .joint import _joint_stiction
from .locate import ar_whiten, spectrum_lines, whiteness
from .proof import _Proof
from .settings import DiagnoseSettings, INPUT_FAMILIES, OUTPUT_FAMILIES
from .significance import _Baseline, _baseline, _Grid, _Significance, _significance


class Diagnosis(eqx.Module):
    """Result of [`jaxstiction.diagnose`][]: the verdict (one of `VERDICTS`), the
    findings ranked (accepted first, by held-out gain), where the mismatch is, the
    nominal and diagnosed models, what cannot be identified from OP and PV alone,
    and the series behind the pictures."""

    verdict: str = eqx.field(static=True)
    findings: tuple
    located: dict
    nominal: LoopModel
    model: LoopModel
    heldout_nominal: dict
    not_identifiable: tuple
    runner_up: str | None = eqx.field(static=True)
    n_estimation: int = eqx.field(static=True)
    series: dict
    stiction: dict | None = None

    @property
    def accepted(self) -> tuple[str, ...]:
        """The accepted effects, the verdict's first (a second block proven on top of
        it, e.g. an external oscillation beside stiction, follows; quantisation,
        named from the PV lattice, too)."""
        return tuple(f.effect for f in self.findings if f.accepted)

    def to_json(self) -> dict:
        return {
            "verdict": self.verdict,
            "accepted": list(self.accepted),
            "findings": [f.to_json() for f in self.findings],
            "runner_up": self.runner_up,
            "located": self.located,
            "heldout_nominal": self.heldout_nominal,
            "not_identifiable": list(self.not_identifiable),
            "stiction": self.stiction,
            "samples": {"estimation": self.n_estimation,
                        "heldout": int(len(self.series["pv"]) - self.n_estimation)},
        }


def _ranked(accepted: list[Finding]) -> list[Finding]:
    """The accepted findings in the order that names the verdict (first) and the
    runner-up.

    By the penalised likelihood ratio (`rank_score`), blocks whose residual passes
    the cross-correlation test first, except that an input block whose likelihood
    ratio exceeds every accepted deterministic oscillation's (all of them when none
    is accepted) joins the first group whatever the test says. Between input blocks,
    the cross-correlation test fails for the right block too when anything (an
    oscillation, a grid point's slip timing) is left in the residual: Kano S 6, J 2
    seed 103 was named actuator lag (LR 147, held-out gain 25.5) over stiction (LR
    474, gain 37.8), and one seed of travel limit lo 47.5 a valve characteristic.
    Against an oscillation, the oscillation is then judged as a second block on top
    of it (CHEM24: a deadband gaining 86 held-out points, LR 1531, had ranked below a
    period-13.6 oscillation gaining 1.2, LR 28).

    Stochastic effects (a drift, a narrow-band disturbance) claim no simulation gain:
    they come after every block that proved one, by their own likelihood ratios."""
    def stochastic(f):
        return bool(f.evidence.get("stochastic"))

    best_output = max((f.evidence["rank_score"] for f in accepted
                       if f.effect == "external_oscillation" and not stochastic(f)), default=-math.inf)

    def key(f):
        cc = f.evidence["residual_cross_correlation_passes"]
        promoted = f.effect in INPUT_FAMILIES and f.evidence["rank_score"] > best_output
        return not (cc or promoted), -f.evidence["rank_score"]

    return (sorted((f for f in accepted if not stochastic(f)), key=key)
            + sorted((f for f in accepted if stochastic(f)), key=lambda f: -f.evidence["rank_score"]))


def diagnose(loop, nominal: LoopModel | None = None, settings: DiagnoseSettings = DiagnoseSettings(),
             progress=None, *, name: str = "loop") -> Diagnosis:
    """Diagnose the mismatch between `nominal` (default: a linear-valve model fitted
    here) and the recorded loop; see the module docstring for the method.

    **Arguments:** `loop`: a [`jaxstiction.Loop`][] (unbatched; masked samples are
    dropped); `nominal`: a [`jaxstiction.LoopModel`][]; `settings`:
    `DiagnoseSettings`; `progress`: optional callable taking a message; `name`:
    the loop's name, which prefixes data errors.

    **Returns:** a `Diagnosis`. Raises `ValueError` (one line) on bad data. Warns
    when JAX runs in float32 (enable float64 with
    `jax.config.update("jax_enable_x64", True)`; the command line does).
    """
    warn_without_float64("diagnose", "its fits and its stiction verdict (the screen's, whose probability was "
                                     "calibrated on float64 evidence) were developed in float64")
    say = progress or (lambda msg: None)
    b = _baseline(loop, nominal, settings, say, name)
    g = _Grid.build(b, settings)
    s = _significance(b, g, settings, say)
    say("refitting the significant candidates")
    proof = _Proof(b, s, settings)
    findings = _family_findings(b, g, s, proof, settings)
    if not b.given and settings.joint_bootstrap > 0:
        # the grid's stiction candidate holds the linear-valve nominal's poles: refit
        # stiction jointly with the linear part and let that finding stand for it
        joint = _joint_stiction(b.op, b.pv, b.n_est, proof.before, len(s.names), settings, say)
        if joint is not None:
            stiction_j, deadband_j = joint
            findings = [stiction_j if f.effect == "stiction" else
                        deadband_j if f.effect == "deadband" and deadband_j is not None else f for f in findings]
    findings, ordered = _accepted_in_order(findings, g, s)
    verdict, model = "none", s.base_model
    if ordered:
        verdict, model = ordered[0].effect, ordered[0].model
    if verdict in INPUT_FAMILIES:  # two effects: does an external oscillation remain?
        findings, model = _second_oscillation(b, g, s, proof, settings, ordered[0], findings, say)
        slip = _slip_beside_oscillation(b, g, findings, ordered, model, say) if verdict == "deadband" else None
        if slip is not None:  # stiction after all, if the oscillation proves itself on top of it too
            f2, m2 = _second_oscillation(b, g, s, proof, settings, slip[1][0], slip[0], say)
            if any(f.effect == "external_oscillation" and f.accepted for f in f2):
                (findings, ordered), model, verdict = (f2, slip[1]), m2, "stiction"
    if ordered:
        findings = _alternatives(findings, ordered[0])
    # the runner-up: the best other explanation, not a block the diagnosed model holds
    claimed = {f.effect for f in findings if f.accepted}
    runner = next((f.effect for f in ordered[1:] if f.effect not in claimed), None)
    quant = _quantisation(b.pv, float(np.std((b.pv - s.base_sim)[:b.n_est])))
    if quant is not None:
        findings.append(Finding("quantization", quant, {
            "note": "sensor quantisation changes no simulation: no held-out gain is claimed"},
            proof.before, proof.before, True))
        if verdict == "none":
            verdict = "quantization"
    stiction = None
    if not b.given:  # one stiction policy with the screen (see `_screen_policy`)
        stiction = _stiction_verdict(loop, b)
        verdict, said = _screen_policy(verdict, findings, stiction)
        if said:
            stiction["note"] = said
            say(said)
        if stiction["verdict"] == "no_stiction":
            findings, model = _valve_demoted(findings, model, s.base_model)
    findings = _named_rejections(findings)
    order = {f.effect: i for i, f in enumerate(ordered)}  # the alternatives follow in their rank
    findings.sort(key=lambda f: (not f.accepted, order.get(f.effect, len(order)), -f.evidence.get("statistic", -1e9)
                                 if f.evidence.get("statistic") is not None else 0.0))
    sim_after = np.asarray(_jit_scored(model, b.opj, b.pvj, b.whole)[0])
    located = {**b.located, "whiteness_after": whiteness(ar_whiten((b.pv - sim_after)[:b.n_est], 2)[0])}
    series = {"op": b.op, "pv": b.pv, "sim_nominal": b.sim_nom, "sim_after": sim_after, "residual": b.z,
              "spectrum": spectrum_lines(b.z[:b.n_est])}
    return Diagnosis(verdict=verdict, findings=tuple(findings), located=located, nominal=b.nominal, model=model,
                     heldout_nominal=proof.before, not_identifiable=_not_identifiable(verdict, findings, b.given),
                     runner_up=runner, n_estimation=b.n_est, series=series, stiction=stiction)


def _stiction_verdict(loop, b: _Baseline) -> dict:
    """The screen's stiction verdict of the loop (its light `estimate` and
    [`jaxstiction.verdict`][] on the record padded to its screen bucket, the
    setpoint included when recorded), as plain values."""
    real = np.asarray(loop.mask) > 0
    sp = None if loop.sp is None else np.asarray(loop.sp)[real]
    lp = pad(make_loop(b.op, b.pv, float(np.asarray(loop.ts)), sp=sp), bucket_length(b.op.shape[0]))
    fit = estimate(dataclasses.replace(lp, sp=None), SCREEN_ESTIMATE)
    v = verdict(fit, lp)
    code = int(v.gate)
    reason = verdict_reason(v)
    which = VERDICTS[int(v.verdict)]
    return {"verdict": which, "probability": round(float(v.probability), 3), "band_seen": bool(v.stiction_detected),
            "slip_identified": bool(v.slip_identified), "gate": GATES[code],
            "reason": reason if which == "inconclusive" else ""}


# The two names of a sticky valve: a band with a slip jump, and one without
VALVE_EFFECTS = ("stiction", "deadband")


def _screen_policy(verdict: str, findings, stiction: dict) -> tuple[str, str]:
    """One stiction policy for `diagnose` (no nominal model) and the screen: the
    valve is sticky when the screen's verdict says so. A sticky valve is named
    `stiction` when its slip is identified, else `deadband` (the J = 0 member of the
    Kano family: a band with no visible slip), unless the diagnosis already named
    one of the two; a valve the verdict calls not sticky is named neither, and the
    next accepted effect (or `none`) stands. Where the verdict is `inconclusive` (its
    data-quality gate could not judge the record), the diagnosis' own held-out proof
    decides. Returns the verdict and a note saying what changed or why ("" when
    nothing needs saying)."""
    if stiction["verdict"] == "stiction" and verdict not in VALVE_EFFECTS:
        named = "stiction" if stiction["slip_identified"] else "deadband"
        return named, (f"the stiction verdict calls the valve sticky (probability {stiction['probability']:.2f}): "
                       f"named {named} instead of {verdict}")
    if stiction["verdict"] == "inconclusive" and verdict in VALVE_EFFECTS:
        return verdict, (f"the stiction verdict is inconclusive ({stiction['reason']}): {verdict} rests on "
                         "the diagnosis' own held-out proof")
    if stiction["verdict"] == "no_stiction" and verdict in VALVE_EFFECTS:
        others = [f.effect for f in findings if f.accepted and f.effect not in VALVE_EFFECTS]
        named = others[0] if others else "none"
        why = stiction["reason"] or f"probability {stiction['probability']:.2f}"
        return named, f"the stiction verdict does not call the valve sticky ({why}): {verdict} is not named"
    return verdict, ""


def _valve_demoted(findings, model, base: LoopModel):
    """The findings and diagnosed model once the stiction verdict has called the
    valve not sticky: an accepted stiction or deadband finding is no longer accepted
    (`rejected_by`: `stiction_verdict`), and the model is that of the next accepted
    finding, or the nominal refitted with a linear valve."""
    if not any(f.accepted and f.effect in VALVE_EFFECTS for f in findings):
        return findings, model
    out = [dataclasses.replace(f, accepted=False, evidence={**f.evidence, "rejected_by": "stiction_verdict"})
           if f.accepted and f.effect in VALVE_EFFECTS else f for f in findings]
    rest = [f for f in out if f.accepted and f.model is not None]
    return out, rest[0].model if rest else base


def _family_findings(b: _Baseline, g: _Grid, s: _Significance, proof: _Proof,
                     settings: DiagnoseSettings) -> list[Finding]:
    """One finding per family: its best block and its evidence; a significant one is
    added to the nominal and proven held out (see the module notes)."""
    findings = []
    before = proof.before
    dof = {"stiction": 2, "external_oscillation": 3}
    # A significant external oscillation also drives OP through the controller, so an
    # input block's residual keeps an OP-residual correlation that is the
    # oscillation's, not the block's: the blocks' cross-correlation tests run with
    # the oscillation removed.
    # Output-side blocks (the oscillation, the drift's noise model) are added to the
    # nominal as it is: they do not interact with its input side, and refitting B
    # and the offset here, with the block's signal still in the residual, only adds
    # their estimation error (P5 seeds 0-13: ~0.5 points of held-out fitness lost
    # on average, 2.2 on seed 8).
    amp, P, ph = _fit_sinusoid(b.z, b.n_est, 1.0 / max(s.f_best, 1e-9))
    sinusoid = Sinusoid(amp, P, ph)
    osc = None
    if s.pvals["external_oscillation"] <= settings.alpha and s.T_obs["external_oscillation"] > 0:
        osc = np.asarray(sinusoid(jnp.zeros(b.n)))  # the output block's own signal
    lvl = _level_only(b)
    drift_sig = s.pvals["drift"] <= settings.alpha and s.T_obs["drift"] > 0
    # the drift's own noise model (its integrating predictor), under which an input
    # block must still predict better than the linear valve (`_gain_from_the_block`)
    drift = None
    if drift_sig:
        drift_noise = NoiseModel(*drift_noise_model(float(s.drift_obs[1]), float(s.drift_obs[2])))

        @functools.cache
        def linear_heldout():
            # what every input block is held to under the drift, computed once (when
            # the first block reaches that check): the refitted linear valve's
            # held-out fitness, and its k-step error with the drift's noise model
            return (_heldout(s.base_model, b.op, b.pv, b.n_est)["fitness"],
                    _heldout(_with_noise(s.base_model, drift_noise), b.op, b.pv, b.n_est)[f"k{K_STEP}_step_rms"])

        drift = (drift_noise, linear_heldout)
    for fam in s.names:
        # significant: beyond the bootstrap null *and* better than the nominal itself
        sig_f = s.pvals[fam] <= settings.alpha and s.T_obs[fam] > 0
        ev = {"statistic": round(s.T_obs[fam], 3), "p_value": round(s.pvals[fam], 4), "significant": bool(sig_f)}
        if fam == "drift":
            ev["null"] = "1/2 chi2(0) + 1/2 chi2(1) of twice the statistic (conservative)"
        else:
            ev["bootstrap_median"] = round(float(s.med[s.names.index(fam)]), 3)
        iv = {}
        T_rank = s.T_obs[fam]
        if fam in INPUT_FAMILIES:
            k, params, iv = g.param_table(fam, s.v_in)
            blk = g.fams[fam][0][k]
            if fam == "valve_characteristic":
                ev.update(operating_point_statistic=round(float(s.T_op[0]), 3),
                          operating_point_p_value=round(s.p_op, 4),
                          operating_point_bootstrap_median=round(float(np.median(s.T_op[1:])), 3))
                if s.by_op:  # R from the operating point's profile (the nominal's B and offsets held)
                    # Ranked by that likelihood ratio too: no other block of the library
                    # moves the operating point, and with B refitted a band can mimic
                    # the characteristic's curvature (R 8, seed 103: stiction ranked first)
                    T_rank = max(T_rank, float(s.T_op[0]))
                    R_op, iv_op = rangeability_profile(g.count * np.log(s.op_losses[0]))
                    blk = EqualPercentage(R_op)
                    params = {"R": round(R_op, 4)}
                    iv = {"R": [round(v_, 4) for v_ in iv_op]}
            if sig_f:
                model = b.with_block((blk,), (blk(b.op_in_j) - b.om) / b.sx)
        elif fam == "external_oscillation":
            params = {"amplitude": round(amp, 4), "period_samples": round(float(P), 3), "phase": round(ph, 4)}
            model = _add_output(b.nominal, sinusoid)
        else:  # drift: an integrating noise model; no simulation gain possible
            _, a_d, q_d, s_d, a_s = (float(v) for v in s.drift_obs)
            c_d, d_d = drift_noise_model(a_d, q_d)
            model = _with_noise(b.nominal, NoiseModel(c=c_d, d=d_d))
            # what the drift must beat: the test's null, stationary AR(1) noise about a level
            stationary = eqx.tree_at(lambda m: (m.noise, m.pv_offset), b.nominal, (
                NoiseModel(c=jnp.ones(1), d=jnp.asarray([1.0, -a_s])),
                b.nominal.pv_offset + float(np.mean(b.z[:b.n_est]))))
            params = {"step_std": round(s_d * math.sqrt(q_d), 4), "noise_pole": round(a_d, 4),
                      "innovation_std": round(s_d, 4)}
        if not sig_f:
            ev["rejected_by"] = "significance"
            findings.append(Finding(fam, {**params, "interval": iv}, ev, before, before, False))
            continue
        after, gain, kgain, cc = _prove(model, b.op, b.pv, b.n_est, before, osc if fam in INPUT_FAMILIES else None,
                                        innovations=fam == "drift")
        ev.update(heldout_gain=round(gain, 3), k_step_gain=round(float(kgain), 5),
                  residual_cross_correlation_passes=cc["passes"],
                  rank_score=round(T_rank - 2 * dof.get(fam, 1), 3))
        if fam == "drift":
            # Held out, the drift model must predict k steps ahead better than the
            # test's stationary null. Not by more than that gain's spread: a drift
            # is a stochastic disturbance, and 1000 held-out samples often show too
            # little of it (P8 seeds 0-19: gains -0.1 to 2.0 against spreads of
            # 0.1 to 0.7 on the null's records); its evidence is the test above.
            k_stat = _heldout(stationary, b.op, b.pv, b.n_est)[f"k{K_STEP}_step_rms"]
            kgain_s = _diff(k_stat, after[f"k{K_STEP}_step_rms"])
            _, spread = proof.null_kstep_gain(model, stationary, a_s)
            ev.update(k_step_gain_over_stationary=round(kgain_s, 5), k_step_spread=round(spread, 5), stochastic=True)
            ok = kgain_s > 0
            if not ok:
                ev["rejected_by"] = "drift_k_step_gain"
            ev["note"] = ("drift is a stochastic disturbance: it cannot improve simulation fit, only prediction, "
                          "and its held-out k-step gain is not compared with its spread")
        else:
            _, spread = proof.null_gain(model)
            need = max(0.5, spread)
            ev.update(spread=round(spread, 3), gain_needed=round(need, 3))
            ok = gain > need
            if not ok:
                ev["rejected_by"] = "heldout_gain"
            if ok and fam in INPUT_FAMILIES:
                ok = _gain_from_the_block(fam, model, after, lvl, drift, b, s, proof, ev)
            if fam == "external_oscillation" and not ok and cc["passes"]:
                ok = proof.narrow_band(ev, params, gain, b.pv - s.base_sim, b.c0, b.d0, P)
                if ok:  # no deterministic block: the model stays the nominal
                    model, after = b.nominal, before
                    ev.pop("rejected_by", None)
        if fam in OUTPUT_FAMILIES and not cc["passes"]:
            # An output-side effect must leave no OP-residual correlation: an
            # oscillation or wander that OP still explains is one the loop makes (a
            # valve nonlinearity's cycle none of the input blocks captured), not an
            # external one. Input blocks are not rejected by this test (it only
            # ranks them below an oscillation with a larger likelihood ratio): on
            # real loops the right one can fail it beside a second effect (CHEM23's
            # stiction, beside its fast oscillation).
            if ok:
                ev["rejected_by"] = "output_cross_correlation"
            ok = False
            ev["note"] = ev.get("note", "") + ("; " if "note" in ev else "") + (
                "its residual still correlates with past OP: not accepted as an external effect")
        findings.append(Finding(fam, {**params, "interval": iv}, ev, before, after, bool(ok), model))
    return findings


def _level_only(b: _Baseline) -> LoopModel:
    """The nominal with only its PV offset refitted on the estimation part."""
    return eqx.tree_at(lambda m: m.pv_offset, b.nominal, b.nominal.pv_offset + float(np.mean(b.z[:b.n_est])))


def _with_noise(model: LoopModel, noise: NoiseModel) -> LoopModel:
    """`model` with its noise model replaced by `noise`."""
    return eqx.tree_at(lambda m: m.noise, model, noise)


def _gain_from_the_block(fam, model, after, level, drift, b, s, proof, ev) -> bool:
    """Does an input block's held-out gain over the nominal come from the block, not
    from what its refit of the offset (and B) picks up besides? Three checks, each
    recorded in `ev`:

    - it must beat the nominal with only its level refitted (`level`) by the
      spread, as it beat the nominal. A PV level that moved between the nominal's
      data and this record gives any refitted model the held-out points of the level
      (P8 seed 37: a 0.15 % deadband gained 5.5 points over the nominal, -0.2 over
      the level).
    - when the drift test is significant, it must also beat the linear valve
      refitted the same way (B and the offset). A wandering level makes the
      nominal's held-out score depend on it, and OP, which the controller moves
      against the wander, lets a refitted B follow part of it (P8 seed 35: a 0.15 %
      deadband gained 22.0 points over the nominal, 0.9 over the level, -0.03 over
      the refitted linear valve). Without a drift this check is not made: a refitted
      B absorbs much of a real block (stiction on P1 seed 12: +10.7 points over the
      nominal, +2.3 over the refitted linear valve), and the nominal stands. A
      characteristic proven by the operating point is exempt: the refit of B and the
      offset hides exactly that evidence (`characteristic`).
    - when the drift test is significant, it must also predict `K_STEP` steps ahead
      better than the refitted linear valve held out, both with the drift's own
      noise model (its integrating predictor follows the wander, so only what the
      block adds to OP's effect is scored). On random drift draws
      (`benchmarks/diagnose_power.py --only drift`, seeds 5000-5039) two travel
      limits and two actuator lags pass every other check, and all four predict
      worse this way (-0.02 to -1.3 PV units); the same exemption holds.

    A valve characteristic is exempt from the first check (its gain over the level
    is recorded, not required): on 200 random concealed draws
    (`benchmarks/diagnose_power.py`, seeds 1000-1199) it removed three true
    characteristics and no false one, while for the other blocks it removed three
    false discoveries and no true finding. A characteristic changes the loop's gain
    with the operating point, and a refitted level takes up much of that on a
    record whose OP moves little.
    """
    g_lvl = _diff(after["fitness"], _heldout(level, b.op, b.pv, b.n_est)["fitness"])
    _, sp_lvl = proof.null_gain(model, level)
    need = max(0.5, sp_lvl)
    ev.update(gain_over_level=round(g_lvl, 3), spread_over_level=round(sp_lvl, 3))
    failed, notes = [], []  # both checks are made, so an audit can tell which one decided
    if g_lvl <= need and fam != "valve_characteristic":
        failed.append("gain_over_level")
        notes.append(f"its held-out gain is the refitted level's: {g_lvl:+.2f} points over the nominal with only "
                     f"its level refitted, {need:.2f} needed")
    if drift is not None and not (fam == "valve_characteristic" and s.by_op):
        drift_noise, linear_heldout = drift
        f_lin, k_lin = linear_heldout()
        g_lin = _diff(after["fitness"], f_lin)
        ev["gain_over_linear"] = round(g_lin, 3)
        if g_lin <= 0:
            failed.append("gain_over_linear_under_drift")
            notes.append(f"a drift is significant, and the linear valve refitted the same way scores as well held "
                         f"out ({g_lin:+.2f} points): its gain is the refit following the drift, not the block")
        k_blk = _heldout(_with_noise(model, drift_noise), b.op, b.pv, b.n_est)[f"k{K_STEP}_step_rms"]
        g_k = _diff(k_lin, k_blk)
        ev["k_step_gain_under_drift"] = round(g_k, 5)
        if not g_k > 0:
            failed.append("k_step_gain_under_drift")
            notes.append(f"a drift is significant, and with the drift's integrating noise model the block predicts "
                         f"{K_STEP} steps ahead no better than the refitted linear valve held out ({g_k:+.4f}): "
                         "its gain is the drift's wander, which OP follows")
    if failed:
        ev.update(rejected_by=failed[0], rules_failed=failed, note="; ".join(notes))
    return not failed


SLIP_LR = 3.84  # chi2(1) at 95 %: J significantly above 0


def _slip_ratio(g: _Grid, v_in) -> float:
    """Likelihood ratio of the best stiction candidate over the best deadband (its
    J = 0 member) on the estimation data, from the grid's losses `v_in`."""
    vs, vd = float(np.min(v_in[g.slices["stiction"]])), float(np.min(v_in[g.slices["deadband"]]))
    return g.count * float(np.log(vd / vs))


def _accepted_in_order(findings: list[Finding], g: _Grid, s: _Significance):
    """Settle stiction against deadband, then rank the accepted findings (`_ranked`).
    Returns the findings (the one dropped marked so) and the accepted ones in order."""
    # stiction versus deadband (its J = 0 member), both proven: J decides, by the
    # likelihood ratio on the estimation data, not the ranking (the Kano S 6, J 2 +
    # sinusoid variant, seed 101: stiction beat the deadband by 80, but its residual
    # failed the cross-correlation test, which the unmodelled oscillation drives
    # through the controller, and the deadband's passed)
    acc = {f.effect: f for f in findings if f.accepted}
    if "stiction" in acc and "deadband" in acc and not acc["stiction"].evidence.get("joint"):
        lr_j = _slip_ratio(g, s.v_in)
        drop, note = (("stiction", "J is not significantly above 0: deadband") if lr_j < SLIP_LR else
                      ("deadband", f"subsumed by stiction: J is significantly above 0 (likelihood ratio {lr_j:.1f})"))
        acc.pop(drop)
        findings = [_revised(f, False, note=note, rejected_by="stiction_vs_deadband") if f.effect == drop else f
                    for f in findings]
    return findings, _ranked(list(acc.values()))


def _slip_beside_oscillation(b: _Baseline, g: _Grid, findings: list[Finding], ordered: list[Finding],
                             model: LoopModel, say):
    """Stiction against deadband again, once an oscillation is proven on top of the
    deadband: the oscillation left in the record inflates both candidates' losses
    alike, so it shrinks their likelihood ratio towards 0 and hides a slip (random
    draws 2054 and 2098: Kano valves beside an external oscillation named deadband).
    The same test as `_accepted_in_order`'s, on the record with the oscillation
    removed. Returns `(findings, ordered)` with stiction first and the oscillation to
    be judged again on top of it, or `None` when J is still not significantly above 0."""
    osc = next((f for f in findings if f.effect == "external_oscillation" and f.accepted
                and f.parameters.get("with") == "deadband"), None)
    st = next((f for f in findings if f.effect == "stiction"), None)
    if osc is None or st is None or st.evidence.get("rejected_by") != "stiction_vs_deadband":
        return None
    first = ordered[0]
    if model is first.model:  # proven as a narrow band, no sinusoid added: nothing to remove
        return None
    path = np.asarray(_jit_scored(model, b.opj, b.pvj, b.whole)[0] - _jit_scored(first.model, b.opj, b.pvj,
                                                                                 b.whole)[0])
    lr_j = _slip_ratio(g, g.stats((b.pvj - jnp.asarray(path) - b.mu) / b.sy)[1])
    say(f"stiction against deadband with the oscillation removed: likelihood ratio {lr_j:.1f}")
    if lr_j < SLIP_LR:
        return None
    note = (f"J is significantly above 0 once the oscillation proven on top of the deadband is removed "
            f"(likelihood ratio {lr_j:.1f}): the deadband is subsumed by stiction")
    st = _revised(st, True, slip_statistic_beside_oscillation=round(lr_j, 3),
                  note="J is significant with the oscillation on top removed")
    findings = [st if f.effect == "stiction" else
                _revised(f, False, note=note, rejected_by="stiction_vs_deadband") if f.effect == "deadband" else f
                for f in findings if f is not osc]
    return findings, [st] + [f for f in ordered if f.effect != "deadband"]


def _alternatives(findings: list[Finding], first: Finding) -> list[Finding]:
    """Only what the diagnosed model holds stays accepted: the verdict's block and
    a second block proven on top of it. Another block that passed on its own (an
    actuator lag or a travel limit beside stiction: each imitates part of it) is an
    alternative explanation of the same mismatch; it was never fitted together with
    the verdict's, so it is not claimed."""
    def kept(f):
        return f is first or not f.accepted or "with" in f.parameters

    note = (f"passes on its own, but as an alternative to {first.effect}, which explains the mismatch better; "
            "the two were not fitted together, so it is not claimed")
    return [f if kept(f) else _revised(f, False, alternative_to=first.effect, rejected_by="alternative",
                                       note=f"{f.evidence['note']}; {note}" if "note" in f.evidence else note)
            for f in findings]


def _second_oscillation(b: _Baseline, g: _Grid, s: _Significance, proof: _Proof, settings: DiagnoseSettings,
                        first: Finding, findings: list[Finding], say):
    """Does an external oscillation remain once the best input block (`first`) is in?
    Returns the findings (with the second block's, accepted or not) and the model."""
    verdict, model = first.effect, first.model
    i_osc = s.names.index("external_oscillation")
    zw = b.pv - np.asarray(_jit_scored(model, b.opj, b.pvj, b.whole)[0])
    # whitened by a noise model refitted on this residual: the shared one was
    # fitted with the block's effect still in it, and its extra colouring hides
    # lines (Kano 6/2 + sinusoid A 3, period 45, seeds 100/102: T2 12.6/15.5 ->
    # 18.9/24.2 against a null of 15.1 +- 2.5)
    zs = jnp.asarray(zw / b.sy)
    zs = zs - jnp.sum(b.w_fit * zs) / jnp.sum(b.w_fit)
    c2, d2 = _arma11(zs, b.w_fit) or (b.c0, b.d0)
    r = np.asarray(lfilter(d2, c2, zs)) * np.asarray(b.w_fit)
    m8 = 8 * b.n
    R = np.fft.rfft(r, n=m8)
    f = np.arange(R.shape[0]) / m8
    red = np.where((f >= g.fmin) & (f <= g.fmax), 2 * np.abs(R) ** 2 / g.count, 0.0)
    k = int(np.argmax(red))
    V = float(np.sum(r**2)) / g.count
    T2 = g.count * float(np.log(V / max(V - red[k] / g.count, 1e-300)))
    p2 = min(1.0, len(s.names) * _normal_sf((T2 - s.mean[i_osc]) / s.std[i_osc]))
    say(f"an oscillation on top of {verdict}: period {1.0 / f[k]:.1f} samples, statistic {T2:.1f}, p {p2:.4f}")
    if p2 > settings.alpha:
        return findings, model
    before = proof.before
    amp, Pk, ph = _fit_sinusoid(zw, b.n_est, 1.0 / f[k])
    both = _add_output(model, Sinusoid(amp, Pk, ph))
    after2 = _heldout(both, b.op, b.pv, b.n_est)
    _, g_std = proof.null_gain(both, model)
    gain2 = _diff(after2["fitness"], first.heldout_after["fitness"])
    params2 = {"amplitude": round(amp, 4), "period_samples": round(float(Pk), 3), "phase": round(ph, 4),
               "with": verdict}
    ev2 = {"statistic": round(T2, 3), "p_value": round(p2, 4), "significant": True,
           "heldout_gain": round(_diff(after2["fitness"], before["fitness"]), 3),
           "gain_over_first_block": round(gain2, 3), "spread": round(g_std, 3)}
    ok2 = gain2 > max(0.5, g_std)
    if not ok2 and _residual_cross_correlation(both, b.op, b.pv, b.n_est)["passes"]:
        # the same route as a first block's: a band that persists held out
        ok2 = proof.narrow_band(ev2, params2, gain2, zw, c2, d2, Pk, base=f"the {verdict} model")
        if ok2:
            both, after2 = model, first.heldout_after
    ev2["note"] = f"second block, on top of {verdict}" + (f"; {ev2['note']}" if "note" in ev2 else "")
    if not ok2:
        ev2["rejected_by"] = "heldout_gain"
    # reported either way; accepted only when it proved itself held out
    findings = findings + [Finding("external_oscillation", params2, ev2, before, after2, bool(ok2), both)]
    if ok2:
        findings = [f_ for f_ in findings if not (f_.effect == "external_oscillation" and "with" not in
                                                  f_.parameters)]
        model = both
    return findings, model


def _named_rejections(findings: list[Finding]) -> list[Finding]:
    """No silent rejection: every finding not accepted names the rule that rejected it
    (`evidence["rejected_by"]`, one of `REJECTION_RULES`). Each rejection site names
    its own; one that did not is named `unnamed` here (a defect the tests look for),
    and an accepted finding carries none."""
    out = []
    for f in findings:
        ev = f.evidence
        if f.accepted and "rejected_by" in ev:
            f = dataclasses.replace(f, evidence={k: v for k, v in ev.items() if k != "rejected_by"})
        elif not f.accepted and "rejected_by" not in ev:
            f = dataclasses.replace(f, evidence={**ev, "rejected_by": "significance" if not ev.get("significant")
                                                 else "unnamed"})
        out.append(f)
    return out


def _not_identifiable(verdict: str, findings, given: bool) -> tuple[str, ...]:
    """What the diagnosis cannot tell from OP and PV alone."""
    not_ident = ["a constant sensor offset on PV cannot be told from the process offset",
                 "where in the chain a static block sits (before or after the valve characteristic) is not "
                 "identifiable from OP and PV alone"]
    if verdict == "deadband":
        st = next((f for f in findings if f.effect == "stiction"), None)
        j_iv = st.parameters.get("interval", {}).get("J") if st is not None else None
        not_ident.append(
            "a deadband (J = 0) and a sticky valve whose slip jump is too small to show are alike in these data"
            + (f" (the stiction fit's 95 % profile allows J up to {j_iv[1]:.3g})" if j_iv else "")
            + ": the valve has a band of the width found either way")
    if not given:
        not_ident.append("no nominal model was given: dead time and valve characteristic are judged against "
                         "a linear-valve model fitted here, which absorbs part of them")
    return tuple(not_ident)
