"""jaxstiction: find sticky control valves and the process behind them from
closed-loop OP/PV data, in JAX. See README.md.

This is what a user calls; `jaxstiction.internal` holds the stages and helpers
that research code, benchmarks and tests take from inside."""

from importlib.metadata import PackageNotFoundError as _PackageNotFoundError, version as _version

from ._blocks import (
    AbstractBlock as AbstractBlock,
    ActuatorLag as ActuatorLag,
    block_name as block_name,
    BLOCKS as BLOCKS,
    Choudhury as Choudhury,
    Deadband as Deadband,
    DeadTime as DeadTime,
    Drift as Drift,
    EqualPercentage as EqualPercentage,
    He as He,
    Kano as Kano,
    make_block as make_block,
    NarrowBand as NarrowBand,
    Quantiser as Quantiser,
    RateLimit as RateLimit,
    run_chain as run_chain,
    Sinusoid as Sinusoid,
    TravelLimits as TravelLimits,
)
from ._checks import check_loop as check_loop, LoopDataError as LoopDataError, LoopDataWarning as LoopDataWarning
from ._control.closedloop import Knocker as Knocker
from ._control.controller import Controller as Controller, identify_controller as identify_controller
from ._criteria import (
    predict_scored as predict_scored,
    score as score,
    ScoreSettings as ScoreSettings,
    simulate_scored as simulate_scored,
)
from ._diagnose.diagnose import diagnose as diagnose, Diagnosis as Diagnosis
from ._diagnose.heldout import Finding as Finding
from ._diagnose.settings import DiagnoseSettings as DiagnoseSettings, VERDICTS as VERDICTS
from ._estimate.estimate import estimate as estimate, min_length as min_length
from ._estimate.report import fit as fit, FitReport as FitReport, report as report
from ._estimate.result import LoopFit as LoopFit, RESULTS as RESULTS
from ._estimate.settings import (
    PhysicalSettings as PhysicalSettings,
    Settings as Settings,
    SplineSettings as SplineSettings,
)
from ._filters import (
    fitness as fitness,
    fitness_trend_free as fitness_trend_free,
    freq_response as freq_response,
    lfilter as lfilter,
    step_response as step_response,
)
from ._io.nominal import nominal_to_dict as nominal_to_dict, nominal_ts as nominal_ts, read_nominal as read_nominal
from ._io.read import (
    find_loop_files as find_loop_files,
    list_loops as list_loops,
    loop_name as loop_name,
    read_loop as read_loop,
)
from ._io.read_mat import list_mat_loops as list_mat_loops
from ._io.tags import read_tags as read_tags
from ._loop import decimate as decimate, Loop as Loop, make_loop as make_loop, stack as stack, unstack as unstack
from ._models import (
    InitialState as InitialState,
    LinearProcess as LinearProcess,
    LoopModel as LoopModel,
    NoiseModel as NoiseModel,
    SplineValve as SplineValve,
)
from ._scenarios import make_scenario as make_scenario, Scenario as Scenario, SCENARIOS as SCENARIOS
from ._screen.outputs import write_screen_outputs as write_screen_outputs
from ._screen.screen import rank as rank, screen as screen, screen_loops as screen_loops, ScreenReport as ScreenReport
from ._screen.settings import ScreenSettings as ScreenSettings
from ._screen.valves import valve_verdicts as valve_verdicts
from ._simulate import Experiment as Experiment, LoopRecord as LoopRecord, simulate_loop as simulate_loop
from ._verdict.settings import VerdictSettings as VerdictSettings
from ._verdict.verdict import CAUSES as CAUSES, Verdict as Verdict, verdict as verdict
from ._whatif.compensate import Compensation as Compensation
from ._whatif.settings import (
    CompensateSettings as CompensateSettings,
    KnockerGrid as KnockerGrid,
    WhatIfSettings as WhatIfSettings,
)
from ._whatif.stats import LoopStats as LoopStats
from ._whatif.trend import valve_trend as valve_trend
from ._whatif.whatif import compensate as compensate, WhatIf as WhatIf, whatif as whatif


try:
    __version__ = _version("jaxstiction")
except _PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"
