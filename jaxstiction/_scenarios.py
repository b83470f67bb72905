"""Named simulation scenarios of DESIGN §4: `paper_sim` and the concealed-effect set."""

import copy

import equinox as eqx
import jax.random as jr

from ._simulate import LoopConfig, LoopRecord, simulate_loop


SCENARIOS = (
    "paper_sim",
    "P0",
    "P1",
    "P2",
    "P3",
    "P4",
    "P5",
    "P6",
    "P7",
    "P8",
    "P9",
    "P10",
)

# Concealed-effect loop: paper_sim process and noise, detuned PI, larger/slower GBN.
_P_LOOP = dict(kc=(0.06, -0.05, 0.0), sp_amplitude=40.0, sp_switch_prob=0.03, nsr=0.05)
_P_N, _P_SPLIT = 3000, 2000
_PAPER_N = 1500

# name -> (plant settings, truth, description)
_P_CASES = {
    "P0": ({}, {"effect": "none", "effects": []}, "nothing hidden in the plant"),
    "P1": (
        dict(stiction="kano", S=3.0, J=1.0),
        {
            "effect": "stiction",
            "effects": ["stiction"],
            "model": "kano",
            "S": 3.0,
            "J": 1.0,
        },
        "Kano stiction S = 3, J = 1",
    ),
    "P2": (
        dict(dead_time=2),
        {"effect": "dead_time", "effects": ["dead_time"], "extra_delay": 2},
        "dead time +2 samples",
    ),
    "P3": (
        dict(equal_percentage_R=30.0),
        {
            "effect": "valve_characteristic",
            "effects": ["valve_characteristic"],
            "model": "equal_percentage",
            "R": 30.0,
        },
        "equal-percentage valve, R = 30",
    ),
    "P4": (
        dict(travel_hi=52.5),
        {"effect": "saturation", "effects": ["saturation"], "hi": 52.5},
        "valve travel limited at 52.5 %",
    ),
    "P5": (
        dict(sin_amplitude=5.0, sin_period=50.0),
        {
            "effect": "external_oscillation",
            "effects": ["external_oscillation"],
            "amplitude": 5.0,
            "period": 50.0,
        },
        "sinusoidal output disturbance, amplitude 5, period 50 samples, no stiction",
    ),
    "P6": (
        dict(stiction="deadband", S=3.0),
        {"effect": "deadband", "effects": ["deadband"], "width": 3.0},
        "deadband (backlash) 3 %",
    ),
    "P7": (
        dict(quant_step=2.0),
        {"effect": "quantization", "effects": ["quantization"], "step": 2.0},
        "sensor quantisation, step 2.0",
    ),
    "P8": (
        dict(drift_std=0.3),
        {"effect": "drift", "effects": ["drift"], "step_std": 0.3},
        "random-walk drift added to PV, step std 0.3",
    ),
    "P9": (
        dict(actuator_lag=0.8),
        {"effect": "actuator_lag", "effects": ["actuator_lag"], "a": 0.8},
        "first-order actuator lag, a = 0.8",
    ),
    "P10": (
        dict(stiction="kano", S=4.0, J=1.0, sin_amplitude=4.0, sin_period=30.0),
        {
            "effect": "stiction",
            "effects": ["stiction", "external_oscillation"],
            "model": "kano",
            "S": 4.0,
            "J": 1.0,
            "amplitude": 4.0,
            "period": 30.0,
        },
        "Kano stiction S = 4, J = 1 plus sinusoidal disturbance (amplitude 4, "
        "period 30)",
    ),
}


def _nominal() -> dict:
    """The nominal-model JSON dict of DESIGN §6 (linear valve)."""
    return {
        "Ts": 1.0,
        "process": {"b": [0.0, 1.0, 0.5], "a": [1.0, -1.5, 0.7], "delay": 0},
        "op_offset": 50.0,
        "pv_offset": 0.0,
        "valve": {"model": "linear"},
    }


class Scenario(eqx.Module):
    """A named simulated data set with its ground truth.

    - `name`: scenario name (one of [`jaxstiction.SCENARIOS`][]).
    - `estimation`, `validation`: [`jaxstiction.LoopRecord`][]s to fit on / judge on.
    - `full`: the whole contiguous run when estimation and validation are two parts of
      it (P-cases), else `None` (`paper_sim`: two independent runs).
    - `nominal`: the nominal-model JSON dict of DESIGN §6.
    - `truth`: what is hidden in the plant (`effect`, `effects` and its parameters).
    - `config`: the [`jaxstiction.LoopConfig`][] that generated the data.
    - `description`: one line.
    """

    name: str = eqx.field(static=True)
    estimation: LoopRecord
    validation: LoopRecord
    full: LoopRecord | None
    nominal: dict = eqx.field(static=True)
    truth: dict = eqx.field(static=True)
    config: LoopConfig
    description: str = eqx.field(static=True)


def make_scenario(name: str, *, seed: int = 0) -> Scenario:
    """Build a named scenario of DESIGN §4, deterministically from `seed`.

    - `"paper_sim"`: the paper's Section 4.1 loop (PI 0.31/−0.3, GBN ±20 with switch
      probability 0.05, Kano stiction S = 20, J = 2, 5 % noise power); estimation and
      validation are independent 1500-sample runs from two keys derived from `seed`.
    - `"P0"` … `"P10"`: detuned PI 0.06/−0.05, GBN ±40 (p = 0.03), one hidden effect
      (see `Scenario.truth`); one contiguous 3000-sample run (`full`), estimation = the
      first 2000 samples, validation = the last 1000 (with their own times `t`). All
      P-cases of one seed share the setpoint, noise and drift draws.

    **Raises:** `ValueError` on an unknown `name`.
    """
    if name not in SCENARIOS:
        raise ValueError(
            f"Unknown scenario {name!r}; valid names are: {', '.join(SCENARIOS)}."
        )
    key = jr.PRNGKey(seed)
    nominal = _nominal()
    if name == "paper_sim":
        config = LoopConfig(stiction="kano", S=20.0, J=2.0)
        est = simulate_loop(config, jr.fold_in(key, 1), _PAPER_N)
        val = simulate_loop(config, jr.fold_in(key, 2), _PAPER_N)
        truth = {
            "effect": "stiction",
            "effects": ["stiction"],
            "model": "kano",
            "S": 20.0,
            "J": 2.0,
        }
        description = (
            "Paper Section 4.1: BJ process, PI 0.31/-0.3, Kano/Choudhury stiction "
            "S=20, J=2, GBN +-20 (p=0.05), 5 % noise power; 1500 + 1500 independent "
            "samples"
        )
        return Scenario(
            name=name,
            estimation=est,
            validation=val,
            full=None,
            nominal=nominal,
            truth=truth,
            config=config,
            description=description,
        )
    plant, truth, description = _P_CASES[name]
    config = LoopConfig(**_P_LOOP, **plant)
    full = simulate_loop(config, jr.fold_in(key, 3), _P_N)
    return Scenario(
        name=name,
        estimation=full.window(0, _P_SPLIT),
        validation=full.window(_P_SPLIT, _P_N),
        full=full,
        nominal=nominal,
        truth=copy.deepcopy(truth),
        config=config,
        description=f"{name}: {description}; detuned PI 0.06/-0.05, GBN +-40 (p=0.03), "
        "3000 samples (fit 2000, judge the last 1000)",
    )
