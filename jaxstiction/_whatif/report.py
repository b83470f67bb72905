"""Host-side read-out of [`jaxstiction.WhatIf`][] and [`jaxstiction.Compensation`][]:
the `whatif` and `compensate` JSON objects, with a `note` saying why a field is
null. NumPy only; nothing here is traced."""

from __future__ import annotations

import math

import numpy as np

from .._control.controller import SOURCES
from .._misc import json_number as _r
from .compensate import METHODS
from .settings import WhatIfSettings


SCENARIOS = ("as_is", "repaired", "compensated")


def _f(x) -> float:
    return float(np.asarray(x))


def controller_json(c, ts: float) -> dict:
    """The `controller` object: gains per sample, the standard-form tuning (gain and
    integral time in seconds), the lag, the fit, how it was obtained and, without a
    recorded setpoint, the constant setpoint used."""
    kp, ki = _f(c.kp), _f(c.ki)
    ti = kp * ts / ki if ki != 0 and math.isfinite(ki) else None
    out = {"kind": "PI", "kp": _r(kp, 6), "ki": _r(ki, 6), "gain": _r(kp, 6),
           "integral_time_s": _r(ti) if ti is not None and ti > 0 else None, "lag_samples": int(np.asarray(c.lag)),
           "fit": _r(c.fit), "source": SOURCES[int(np.asarray(c.source))]}
    if math.isfinite(_f(c.setpoint)):
        out["setpoint"] = _r(c.setpoint, 6)
    return out


def knocker_json(k, ts: float, method: str) -> dict:
    """The `compensator` object of a knocker (amplitude in % of span, width and
    period in samples and seconds); `kind` is `"constant reinforcement"` for the
    knocker whose pulse never ends (period 1)."""
    width, period = int(round(_f(k.width))), int(np.asarray(k.period))
    kind = "constant reinforcement" if period == 1 else "knocker"
    return {"kind": kind, "method": method, "amplitude": _r(k.amplitude), "width_samples": width,
            "period_samples": period, "width_s": _r(width * ts), "period_s": _r(period * ts)}


def compensator_words(k: dict) -> str:
    """A `compensator` object in words, for the command line and the pictures."""
    if k["kind"] == "constant reinforcement":
        return f"constant reinforcement of {k['amplitude']:.3g} % of span in the direction OP last moved"
    return (f"knocker: pulses of {k['amplitude']:.3g} % of span, {k['width_samples']} sample(s) wide, every "
            f"{k['period_samples']} samples")


def _stats(s, i=None) -> dict:
    pick = (lambda x: np.asarray(x)) if i is None else (lambda x: np.asarray(x)[i])
    return {k: pick(getattr(s, k)) for k in ("error_std", "error_ptp", "pv_std", "pv_ptp", "amplitude", "period",
                                             "travel", "reversals")}


NO_KNOCKER = ("no compensator of the grid (knocks and constant reinforcement) reduces the variability of this "
              "loop at the fitted valve and at its neighbours (CompensateSettings.robust_S, robust_J): none is "
              "recommended")
PARKED = ("the compensator's predicted gain comes from a valve that stays parked at one position (travel "
          "{travel:.3g} against {travel0:.3g} % of span per hour as is): it holds only while the load does not move "
          "the balance point, so treat it as optimistic")


def _parked(travel_comp: float, travel_as_is: float) -> bool:
    """The compensated valve barely moves: under a quarter of the as-is travel."""
    return travel_as_is > 0 and travel_comp < 0.25 * travel_as_is


def whatif_json(w, ts: float, settings: WhatIfSettings = WhatIfSettings()) -> dict:
    """The `whatif` object of one loop from an unbatched [`jaxstiction.WhatIf`][] (see
    the command-line page): the fields of the contract, each null with a `note`
    where it cannot be computed, plus the oscillation, PV spread, the window the
    numbers were read on, S and J, and the recorded loop's own numbers."""
    notes = []
    ts = float(ts)
    stats = {s: _stats(getattr(w, s)) for s in SCENARIOS}
    ivs = {s: _stats(getattr(w, f"{s}_interval")) for s in SCENARIOS}
    rec = _stats(w.recorded)
    ctrl = controller_json(w.controller, ts)
    comp = knocker_json(w.knocker, ts, settings.compensate.method)
    usable = bool(np.asarray(w.enough))
    if not bool(np.asarray(w.stable)):
        notes.append("the fitted process in closed loop with the controller is unstable or runs away: "
                     "the fitted model cannot be replayed")
    elif not usable:
        notes.append(f"only {int(np.asarray(w.samples))} samples are left after the valve's unknown start (sample "
                     f"{int(np.asarray(w.sync))}) and the repaired loop's settling ({int(np.asarray(w.settle))} "
                     f"samples): fewer than {settings.min_samples}, too few to read the numbers on")
    elif not bool(np.asarray(w.settled)):
        notes.append(f"the repaired loop settles in {int(np.asarray(w.settle))} samples, longer than the record "
                     f"leaves after the valve's unknown start (sample {int(np.asarray(w.sync))}): the numbers are "
                     f"read on the last {int(np.asarray(w.samples))} samples, where the repaired run may still "
                     "carry some of its start")
    fit = _f(w.controller.fit)
    if int(np.asarray(w.controller.source)) != 2 and not fit >= settings.min_controller_fit:
        notes.append(f"the identified controller explains {100 * fit:.0f} % of OP's moves (a historian may have "
                     "compressed PV, OP may be quantised, or the controller is not a PI): the replay is approximate")
    if not bool(np.asarray(w.has_setpoint)):
        notes.append("no setpoint recorded: it is taken as constant, and errors are measured about the mean PV")
    used = int(np.asarray(w.draws_used))
    intervals = used >= 2
    if settings.draws == 0:
        notes.append("no models drawn (draws = 0): no intervals")
    elif not intervals:
        notes.append(f"only {used} of {settings.draws} drawn models stayed finite and fit the record as well as "
                     "the chi-square bound allows: no intervals")
    elif used < settings.draws:
        notes.append(f"{settings.draws - used} of {settings.draws} drawn models ran away or fit the record worse than "
                     "the chi-square bound allows, and are left out of the intervals")
    a, r, c = (stats[s] for s in SCENARIOS)
    if usable and rec["error_std"] > 0 and abs(a["error_std"] / rec["error_std"] - 1) > 0.25:
        notes.append(f"the as-is replay's variability ({a['error_std']:.4g}) is not the record's "
                     f"({rec['error_std']:.4g}): the identified controller does not reproduce the loop")
    removable = a["error_std"] - r["error_std"]
    if usable and c["error_std"] >= a["error_std"]:
        notes.append(NO_KNOCKER)
    elif usable and _parked(float(c["travel"]), float(a["travel"])):
        notes.append(PARKED.format(travel=float(c["travel"]), travel0=float(a["travel"])))

    def num(v, nd=4):
        return _r(v, nd) if usable else None

    def iv(s, k="error_std"):
        return [num(ivs[s][k][0]), num(ivs[s][k][1])] if usable and intervals else None

    pv_range = _f(w.pv_range)
    benefit = a["error_std"] - r["error_std"]
    out = {
        "error_std_as_is": num(a["error_std"]),
        "error_std_repaired": num(r["error_std"]),
        "error_std_compensated": num(c["error_std"]),
        "error_std_repaired_interval": iv("repaired"),
        "error_std_as_is_interval": iv("as_is"),
        "error_std_compensated_interval": iv("compensated"),
        "error_std_recorded": num(rec["error_std"]),
        "benefit": num(benefit),
        "benefit_interval": ([num(np.asarray(w.benefit_interval)[0]), num(np.asarray(w.benefit_interval)[1])]
                             if usable and intervals else None),
        "benefit_percent_of_range": num(100.0 * benefit / pv_range, 3) if pv_range > 0 else None,
        "pv_range": _r(pv_range, 4),
        "travel_as_is": num(a["travel"], 2),
        "travel_repaired": num(r["travel"], 2),
        "travel_compensated": num(c["travel"], 2),
        "reversals_as_is": num(a["reversals"], 2),
        "reversals_repaired": num(r["reversals"], 2),
        "reversals_compensated": num(c["reversals"], 2),
        "compensator": {**comp,
                        "reduction_percent": num(100.0 * (a["error_std"] - c["error_std"]) / a["error_std"], 2)
                        if a["error_std"] > 0 else None,
                        "share_of_repair": num((a["error_std"] - c["error_std"]) / removable, 3)
                        if removable > 0 else None,
                        "extra_travel": num(c["travel"] - a["travel"], 2)},
        "controller": ctrl,
        "pv": {s: {"std": num(stats[s]["pv_std"]), "ptp": num(stats[s]["pv_ptp"]),
                   "error_ptp": num(stats[s]["error_ptp"])} for s in SCENARIOS},
        "oscillation": {s: {"amplitude": num(stats[s]["amplitude"]), "period_samples": num(stats[s]["period"], 1),
                            "period_s": num(stats[s]["period"] * ts, 1)} for s in SCENARIOS},
        "window": {"start": int(np.asarray(w.start)), "samples": int(np.asarray(w.samples)),
                   "sync": int(np.asarray(w.sync)), "settle": int(np.asarray(w.settle)),
                   "settled": bool(np.asarray(w.settled))},
        "S": _r(w.S), "J": _r(w.J),
        "note": "; ".join(notes),
    }
    if removable <= 0 and usable:
        out["note"] = "; ".join(notes + ["the replay predicts no benefit from a repair"])
    return out


def compensation_json(c, ts: float) -> dict:
    """The `compensate` command's JSON object from an unbatched
    [`jaxstiction.Compensation`][]."""
    ts = float(ts)
    a, k, r = _f(c.error_std_as_is), _f(c.error_std_compensated), _f(c.error_std_repaired)
    notes = []
    if k >= a:
        notes.append(NO_KNOCKER)
    elif _parked(_f(c.travel_compensated), _f(c.travel_as_is)):
        notes.append(PARKED.format(travel=_f(c.travel_compensated), travel0=_f(c.travel_as_is)))
    if a - r <= 0:
        notes.append("the replay predicts no benefit from a repair either: the valve does not limit this loop")
    fit = _f(c.controller.fit)
    if int(np.asarray(c.controller.source)) != 2 and not fit >= 0.8:
        notes.append(f"the identified controller explains {100 * fit:.0f} % of OP's moves: the design is approximate")
    return {
        "compensator": knocker_json(c.knocker, ts, METHODS[int(np.asarray(c.method))]),
        "error_std_as_is": _r(a, 4), "error_std_compensated": _r(k, 4), "error_std_repaired": _r(r, 4),
        "reduction_percent": _r(c.reduction_percent, 2), "share_of_repair": _r(c.reduction, 3),
        "travel_as_is": _r(c.travel_as_is, 2), "travel_compensated": _r(c.travel_compensated, 2),
        "travel_repaired": _r(c.travel_repaired, 2),
        "extra_travel": _r(_f(c.travel_compensated) - _f(c.travel_as_is), 2),
        "reversals_as_is": _r(c.reversals_as_is, 2), "reversals_compensated": _r(c.reversals_compensated, 2),
        "reversals_repaired": _r(c.reversals_repaired, 2), "objective": _r(c.objective, 4),
        "controller": controller_json(c.controller, ts),
        "note": "; ".join(notes),
    }
