"""Named simulation scenarios: `paper_sim` and the concealed-effect cases P0–P10.

Each scenario is a plant [`jaxstiction.LoopModel`][] (the paper's process and noise
with blocks of the library in it) run in closed loop by
[`jaxstiction.simulate_loop`][]. The ground truth *is* the plant model; `effects`
names what it hides relative to the nominal (linear-valve) model.
"""

from __future__ import annotations

import equinox as eqx
import jax.random as jr

from ._blocks import ActuatorLag, Deadband, DeadTime, Drift, EqualPercentage, Kano, Quantiser, Sinusoid, TravelLimits
from ._models import LinearProcess, LoopModel, NoiseModel
from ._simulate import Experiment, LoopRecord, simulate_loop


SCENARIOS = ("paper_sim", "P0", "P1", "P2", "P3", "P4", "P5", "P6", "P7", "P8", "P9", "P10")

PAPER_N = 1500
P_N, P_SPLIT = 3000, 2000


def nominal_model(chain=(), output=()) -> LoopModel:
    r"""The paper's process $(q^{-1} + 0.5 q^{-2})/(1 - 1.5 q^{-1} + 0.7 q^{-2})$ around
    OP = 50 % with noise colouring $1/(1 - 0.9 q^{-1})$, plus the given blocks."""
    return LoopModel(
        chain=tuple(chain),
        process=LinearProcess(b=(0.0, 1.0, 0.5), a=(1.0, -1.5, 0.7)),
        noise=NoiseModel(c=(1.0,), d=(1.0, -0.9)),
        op_offset=50.0,
        pv_offset=0.0,
        output=tuple(output),
    )


def paper_experiment() -> Experiment:
    """The paper's PI 0.31/-0.3, GBN +-20 switching with probability 0.05, 5 % noise."""
    return Experiment(kc=(0.31, -0.3, 0.0), sp_amplitude=20.0, sp_switch_prob=0.05, nsr=0.05)


def p_experiment() -> Experiment:
    """The concealed-effect cases' detuned PI 0.06/-0.05, GBN +-40 (p = 0.03), 5 % noise."""
    return Experiment(kc=(0.06, -0.05, 0.0), sp_amplitude=40.0, sp_switch_prob=0.03, nsr=0.05)


def _p_cases(key):
    drift_key = jr.key_data(jr.fold_in(key, 7))
    return {
        "P0": ((), (), (), "nothing hidden in the plant"),
        "P1": ((Kano(3.0, 1.0),), (), ("stiction",), "Kano stiction S = 3, J = 1"),
        "P2": ((DeadTime(2),), (), ("dead_time",), "dead time +2 samples"),
        "P3": ((EqualPercentage(30.0),), (), ("valve_characteristic",), "equal-percentage valve, R = 30"),
        "P4": ((TravelLimits(hi=52.5),), (), ("saturation",), "valve travel limited at 52.5 %"),
        "P5": ((), (Sinusoid(5.0, 50.0),), ("external_oscillation",),
               "sinusoidal output disturbance, amplitude 5, period 50 samples, no stiction"),
        "P6": ((Deadband(3.0),), (), ("deadband",), "deadband (backlash) 3 %"),
        "P7": ((), (Quantiser(2.0),), ("quantization",), "sensor quantisation, step 2.0"),
        "P8": ((), (Drift(0.3, drift_key),), ("drift",), "random-walk drift added to PV, step std 0.3"),
        "P9": ((ActuatorLag(0.8),), (), ("actuator_lag",), "first-order actuator lag, a = 0.8"),
        "P10": ((Kano(4.0, 1.0),), (Sinusoid(4.0, 30.0),), ("stiction", "external_oscillation"),
                "Kano stiction S = 4, J = 1 plus sinusoidal disturbance (amplitude 4, period 30)"),
    }


class Scenario(eqx.Module):
    """A named simulated data set with its ground truth.

    - `estimation`, `validation`: [`jaxstiction.LoopRecord`][]s to fit on / judge on;
    - `full`: the whole contiguous run when the two are parts of it (P-cases), else
      `None` (`paper_sim`: two independent runs);
    - `plant`: the true [`jaxstiction.LoopModel`][]; `nominal`: the nominal model
      (linear valve) a diagnosis starts from;
    - `effects`: what the plant hides relative to the nominal model (`()` for none);
    - `experiment`: controller, setpoint and noise level.
    """

    name: str = eqx.field(static=True)
    estimation: LoopRecord
    validation: LoopRecord
    full: LoopRecord | None
    plant: LoopModel
    nominal: LoopModel
    effects: tuple = eqx.field(static=True)
    experiment: Experiment
    description: str = eqx.field(static=True)

    @property
    def effect(self) -> str:
        """The main effect's name (`"none"` when nothing is hidden)."""
        return self.effects[0] if self.effects else "none"


def make_scenario(name: str, *, seed: int = 0) -> Scenario:
    """Build a named scenario deterministically from `seed`.

    - `"paper_sim"`: the paper's Section 4.1 loop (PI 0.31/−0.3, GBN ±20 switching with
      probability 0.05, Kano stiction S = 20, J = 2, 5 % noise power); estimation and
      validation are independent 1500-sample runs from two keys derived from `seed`.
    - `"P0"` … `"P10"`: detuned PI 0.06/−0.05, GBN ±40 (p = 0.03), one hidden effect;
      one contiguous 3000-sample run, estimation = the first 2000 samples, validation =
      the last 1000. All P-cases of one seed share the setpoint and noise draws.

    **Raises:** `ValueError` on an unknown `name`.
    """
    if name not in SCENARIOS:
        raise ValueError(f"Unknown scenario {name!r}; valid names are: {', '.join(SCENARIOS)}.")
    key = jr.PRNGKey(seed)
    nominal = nominal_model()
    if name == "paper_sim":
        plant = nominal_model(chain=(Kano(20.0, 2.0),))
        exp = paper_experiment()
        est = simulate_loop(plant, exp, jr.fold_in(key, 1), PAPER_N)
        val = simulate_loop(plant, exp, jr.fold_in(key, 2), PAPER_N)
        return Scenario(
            name=name, estimation=est, validation=val, full=None, plant=plant, nominal=nominal,
            effects=("stiction",), experiment=exp,
            description="Paper Section 4.1: BJ process, PI 0.31/-0.3, Kano stiction S=20, J=2, GBN +-20 "
            "(p=0.05), 5 % noise power; 1500 + 1500 independent samples",
        )
    chain, output, effects, text = _p_cases(key)[name]
    plant = nominal_model(chain=chain, output=output)
    exp = p_experiment()
    full = simulate_loop(plant, exp, jr.fold_in(key, 3), P_N)
    return Scenario(
        name=name, estimation=full.window(0, P_SPLIT), validation=full.window(P_SPLIT, P_N), full=full,
        plant=plant, nominal=nominal, effects=effects, experiment=exp,
        description=f"{name}: {text}; detuned PI 0.06/-0.05, GBN +-40 (p=0.03), 3000 samples "
        "(fit 2000, judge the last 1000)",
    )
