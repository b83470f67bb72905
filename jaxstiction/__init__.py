"""jaxstiction: find sticky control valves and the process behind them from
closed-loop OP/PV data, in JAX. See README.md."""

import importlib.metadata

from ._blocks import (
    actuator_lag as actuator_lag,
    choudhury as choudhury,
    dead_time as dead_time,
    deadband as deadband,
    equal_percentage as equal_percentage,
    he_stiction as he_stiction,
    kano as kano,
    kano_init as kano_init,
    kano_step as kano_step,
    quantize as quantize,
    random_walk as random_walk,
    rate_limit as rate_limit,
    sinusoid as sinusoid,
    travel_limits as travel_limits,
)
from ._checks import check_loop as check_loop, LoopDataError as LoopDataError
from ._filters import (
    fitness as fitness,
    freq_response as freq_response,
    lagged as lagged,
    lfilter as lfilter,
    step_response as step_response,
)
from ._fit import fit as fit, FitSettings as FitSettings, LoopFit as LoopFit
from ._hammerstein import (
    CandidateFit as CandidateFit,
    fit_spline_candidates as fit_spline_candidates,
    HammersteinModel as HammersteinModel,
    SplineSettings as SplineSettings,
)
from ._io import (
    find_loop_files as find_loop_files,
    LoopData as LoopData,
    NominalModel as NominalModel,
    read_loop as read_loop,
    read_nominal as read_nominal,
    simulate_nominal as simulate_nominal,
)
from ._physical import (
    fit_physical as fit_physical,
    PhysicalFit as PhysicalFit,
    PhysicalSettings as PhysicalSettings,
)
from ._reduce import (
    asymptotic_weight as asymptotic_weight,
    fit_noise_model as fit_noise_model,
    LowOrder as LowOrder,
    reduce_model as reduce_model,
)
from ._relax import (
    ARXHammerstein as ARXHammerstein,
    relax as relax,
    relax_loss as relax_loss,
    relax_problem as relax_problem,
    relax_sweep as relax_sweep,
    RelaxProblem as RelaxProblem,
    RelaxSolution as RelaxSolution,
)
from ._scenarios import make_scenario as make_scenario, Scenario as Scenario, SCENARIOS as SCENARIOS
from ._simulate import LoopConfig as LoopConfig, LoopRecord as LoopRecord, simulate_loop as simulate_loop
from ._spline import (
    direction as direction,
    hysteresis_regressors as hysteresis_regressors,
    noise_threshold as noise_threshold,
    scale_input as scale_input,
    spline_basis as spline_basis,
    uniform_knots as uniform_knots,
    valve_curves as valve_curves,
)


try:
    __version__ = importlib.metadata.version("jaxstiction")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"
