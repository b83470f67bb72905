"""What research code, benchmarks and tests take from inside jaxstiction.

`jaxstiction` is what a user calls. This module is the one door to the rest: the
estimator's stages, each a pure JAX function that can be jitted, vmapped and
(where smooth) differentiated on its own, so that a researcher can build another
estimator from them; the diagnosis's statistics; the screen's batching; the
scenarios' parts; and the helpers of the command line. Nothing outside the package
imports a private module. These names may change between versions.

Importing this module also imports the command line and the pictures
(matplotlib), which `import jaxstiction` does not. A few modules are here as
modules, for tests that patch their state: `programs` (the table of exported
`estimate` programs), `causes` (the `diagnose` that `screen --diagnose` calls) and
`cli` (the command line's compiler switch).
"""

from . import _cli as cli
from ._blocks import _levels as levels
from ._cli import (
    _cache_folder as cache_folder,
    _lean_compiler as lean_compiler,
    _xla_cache as xla_cache,
    build_parser as build_parser,
    LONG_RECORD as LONG_RECORD,
    screen_settings as screen_settings,
)
from ._control.closedloop import (
    chain_gain as chain_gain,
    closed_loop as closed_loop,
    closed_loop_stable as closed_loop_stable,
    ClosedLoopRun as ClosedLoopRun,
    SmoothKano as SmoothKano,
    with_valve as with_valve,
)
from ._criteria import bic as bic, family_criteria as family_criteria, foe as foe, predicted as predicted
from ._demo import paper_sim_case as paper_sim_case
from ._diagnose.candidates import _quantisation as quantisation, _refit_b as refit_b
from ._diagnose.characteristic import (
    characteristic_statistics as characteristic_statistics,
    RANGEABILITIES as RANGEABILITIES,
    rangeability_profile as rangeability_profile,
)
from ._diagnose.diagnose import _ranked as ranked, _screen_policy as screen_policy, _valve_demoted as valve_demoted
from ._diagnose.drift import _neg_loglik as neg_loglik, drift_noise_model as drift_noise_model, drift_test as drift_test
from ._diagnose.heldout import _band_statistics as band_statistics
from ._diagnose.joint import _slip_on_proven_band as slip_on_proven_band
from ._diagnose.locate import (
    cross_correlation as cross_correlation,
    segment_power as segment_power,
    spectrum_lines as spectrum_lines,
    whiteness as whiteness,
)
from ._diagnose.settings import (
    ACCEPTANCE_RULES as ACCEPTANCE_RULES,
    INPUT_FAMILIES as INPUT_FAMILIES,
    JOINT_ESTIMATE as JOINT_ESTIMATE,
    OUTPUT_FAMILIES as OUTPUT_FAMILIES,
    REJECTION_RULES as REJECTION_RULES,
)
from ._estimate import programs as programs
from ._estimate.estimate import (
    _estimate_traced as estimate_traced,
    choose_family as choose_family,
    estimation_parts as estimation_parts,
)
from ._estimate.gram import GramProblem as GramProblem, lag_gram as lag_gram
from ._estimate.hammerstein import (
    candidate_knots as candidate_knots,
    CandidateFit as CandidateFit,
    fit_candidate as fit_candidate,
    fit_spline_candidates as fit_spline_candidates,
    HammersteinModel as HammersteinModel,
)
from ._estimate.physical import (
    _arx_design as arx_design,
    arx_loss as arx_loss,
    FIT_BYTES_PER_SAMPLE as FIT_BYTES_PER_SAMPLE,
    fit_oe as fit_oe,
    fit_physical as fit_physical,
    PhysicalFit as PhysicalFit,
    valve_from as valve_from,
)
from ._estimate.programs import simulations_of as simulations_of
from ._estimate.reduce import (
    asymptotic_weight as asymptotic_weight,
    fit_noise_model as fit_noise_model,
    LowOrder as LowOrder,
    reduce_model as reduce_model,
    welch as welch,
)
from ._estimate.relax import (
    ARXHammerstein as ARXHammerstein,
    relax as relax,
    relax_init as relax_init,
    relax_loss as relax_loss,
    relax_problem as relax_problem,
    relax_sweep as relax_sweep,
    RelaxProblem as RelaxProblem,
    RelaxSolution as RelaxSolution,
)
from ._estimate.result import delay_note as delay_note, held_out_note as held_out_note
from ._estimate.settings import FULL_SEARCH_ESTIMATE as FULL_SEARCH_ESTIMATE, SCREEN_ESTIMATE as SCREEN_ESTIMATE
from ._filters import lagged as lagged, steady_state as steady_state
from ._fleet import (
    _draw as fleet_draw,
    FleetLoop as FleetLoop,
    KINDS as FLEET_KINDS,
    realistic_fleet as realistic_fleet,
    RUN_IN as FLEET_RUN_IN,
)
from ._linalg import is_stable as is_stable, lstsq as lstsq
from ._loop import (
    bucket_length as bucket_length,
    pad as pad,
    recording_of as recording_of,
    window_name as window_name,
    windows as windows,
)
from ._misc import (
    chunked_vmap as chunked_vmap,
    coarse as coarse,
    default_threads as default_threads,
    first_min as first_min,
    MAX_THREADS as MAX_THREADS,
    release_programs_near_map_limit as release_programs_near_map_limit,
    thread_map as thread_map,
)
from ._models import pad_to as pad_to, scaled_loop_model as scaled_loop_model
from ._plots import (
    _model_fit as model_fit_figure,
    write_diagnosis_figures as write_diagnosis_figures,
    write_fit_figures as write_fit_figures,
)
from ._programs import exported_call as exported_call, source_hash as source_hash
from ._scenarios import (
    nominal_model as nominal_model,
    p_experiment as p_experiment,
    P_N as P_N,
    P_SPLIT as P_SPLIT,
    paper_experiment as paper_experiment,
)
from ._screen import causes as causes
from ._screen.batch import (
    _record as screen_entry,
    auto_batch as auto_batch,
    chunk_size as chunk_size,
    MAX_CHUNK as MAX_CHUNK,
    run_chunk as run_chunk,
    SCREEN_BYTES_PER_SAMPLE as SCREEN_BYTES_PER_SAMPLE,
)
from ._screen.causes import diagnose_causes as diagnose_causes
from ._screen.screen import read_items as read_items
from ._spline import (
    direction as direction,
    hysteresis_regressors as hysteresis_regressors,
    noise_threshold as noise_threshold,
    scale_input as scale_input,
    spline_basis as spline_basis,
    uniform_knots as uniform_knots,
    valve_curves as valve_curves,
)
from ._verdict.calibration import CALIBRATION as CALIBRATION
from ._verdict.crossval import crossval_gain as crossval_gain, kstep_prediction as kstep_prediction
from ._verdict.gate import (
    gate_measures as gate_measures,
    GateMeasures as GateMeasures,
    GATES as GATES,
    HARD as HARD,
    hard_gated as hard_gated,
)
from ._verdict.indicators import (
    autocorrelation as autocorrelation,
    bicoherence as bicoherence,
    control_error as control_error,
    cycle as cycle,
    dominant_period as dominant_period,
    horch_phase as horch_phase,
    Indicators as Indicators,
    indicators as indicators,
    lowpass as lowpass,
    oscillation as oscillation,
    shape_index as shape_index,
    stuck_share as stuck_share,
)
from ._verdict.limitcycle import (
    limit_cycle as limit_cycle,
    LimitCycle as LimitCycle,
)
from ._verdict.probability import Calibration as Calibration, fit_calibration as fit_calibration
from ._verdict.verdict import (
    decide as decide,
    FEATURES as FEATURES,
    features as features,
    gate as gate,
    residual_line as residual_line,
    runaway as runaway,
    usable as usable,
    VERDICTS as VERDICTS,
)
from ._whatif.compensate import (
    design_knocker as design_knocker,
    grid_knockers as grid_knockers,
    smooth_objective as smooth_objective,
)
from ._whatif.refine import (
    ar_residual as ar_residual,
    arx_criterion as arx_criterion,
    arx_starts as arx_starts,
    polish_valve as polish_valve,
    refine_process as refine_process,
    refit_for_replay as refit_for_replay,
)
from ._whatif.replay import initial_and_sync as initial_and_sync, Replay as Replay, replay as replay
from ._whatif.report import compensation_json as compensation_json, whatif_json as whatif_json
from ._whatif.stats import count_reversals as count_reversals, loop_stats as loop_stats, settling_time as settling_time
from ._whatif.uncertainty import (
    draw_models as draw_models,
    process_factor as process_factor,
    with_process as with_process,
)
from ._whatif.whatif import chi2_quantile as chi2_quantile, whatif_model as whatif_model
