"""The `paper_sim` demonstration: fit the estimation record, score on the
independent validation record (as on real data), compare with the truth."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ._criteria import simulate_scored
from ._estimate.report import fit, FitReport
from ._estimate.result import held_out_note
from ._filters import fitness
from ._scenarios import make_scenario


def paper_sim_case(seed: int = 0, settings=None) -> tuple[dict, FitReport, np.ndarray]:
    """Run `paper_sim` for one seed.

    Returns `(payload, validation_report, noise_free_pv)`: the demo's JSON object
    (`fitness_validation`, `fitness_noise_free`, `ceiling`, the paper's method scored
    the same way, `stiction` with the truth), the fit report re-targeted at the
    validation record (for the pictures), and the validation record's noise-free PV.

    The validation simulation starts from an initial state estimated on the opening
    samples of the *measured* validation PV; the noise-free PV is only compared
    against, never used to fit or to start the simulation.
    """
    sc = make_scenario("paper_sim", seed=seed)
    est, val = sc.estimation, sc.validation
    r = fit(np.asarray(est.op), np.asarray(est.pv), ts=1.0, validate=0.0, name="paper_sim", settings=settings)
    pv, clean = np.asarray(val.pv), np.asarray(val.pv_clean)
    whole = jnp.ones_like(val.op)
    sim = np.asarray(simulate_scored(r.fit.model, val.op, val.pv, whole)[0])
    sim_paper = np.asarray(simulate_scored(r.fit.paper, val.op, val.pv, whole)[0])

    def f(a, b):
        return float(fitness(a, b))

    truth = sc.plant.chain[0]
    payload = {
        "scenario": "paper_sim",
        "seed": seed,
        "fitness_validation": f(pv, sim),
        "fitness_noise_free": f(clean, sim),
        "ceiling": f(pv, clean),
        "fitness_paper_method": f(pv, sim_paper),
        "fitness_paper_method_noise_free": f(clean, sim_paper),
        "stiction": {
            "band_percent": r.band_percent,
            "S": r.S,
            "J": r.J,
            "S_interval": r.S_interval,
            "J_interval": r.J_interval,
            "true_S": float(truth.S),
            "true_J": float(truth.J),
        },
        "fit": r.to_json(),
    }
    vr = dataclasses.replace(
        r, op=np.asarray(val.op), pv=pv, pv_sim=sim, pv_sim_paper=sim_paper, n_estimation=0,
        n_validation=pv.shape[0], fitness=payload["fitness_validation"], fitness_paper=payload["fitness_paper_method"],
        notes=tuple(n for n in (*r.notes, held_out_note(payload["fitness_validation"], r.fitness_estimation,
                                                        pv.shape[0])) if n),
    )
    return payload, vr, clean
