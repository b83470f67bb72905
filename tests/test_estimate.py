"""End-to-end tests of `estimate` on small simulated stiction loops (no external data):
the fit itself, the batched contract (vmap over padded loops == single calls),
padding invariance, no retracing, data codes under vmap, the host API."""

import collections
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import jaxstiction as js
from jaxstiction.internal import choose_family, estimate_traced, held_out_note, nominal_model, paper_experiment


# Reduced settings: the same pipeline with smaller grids and fewer candidates (one knot
# count: each count is its own traced branch, and compilation is most of this file's
# time; several counts, and the wider interval grid, are tested in test_stages), so
# the suite stays fast. (The full settings are exercised by the benchmarks and CLI
# tests.)
SMALL = js.Settings(
    spline=js.SplineSettings(arx_order=5, knot_counts=(4,), max_order=2, max_delay=2, welch_segment=64,
                             relax_steps=150, polish_steps=20),
    physical=js.PhysicalSettings(num_S=61, num_J=6, starts=4, refine=9, refine_S=41, final=3, line=21, rounds=2,
                                 polish_starts=3, init_count=3, oe_steps=20, interval_span=0.0),
    score=js.ScoreSettings(init_count=20),
    validate=0.25,
)
TRUE_S, TRUE_J = 10.0, 2.0


def code(r):
    """The integer value of a RESULTS item (batched or not)."""
    return np.asarray(r._value)


def _loop(seed: int, n: int) -> js.Loop:
    plant = nominal_model(chain=(js.Kano(TRUE_S, TRUE_J),))
    rec = js.simulate_loop(plant, paper_experiment(), jr.PRNGKey(seed), n)
    return rec.loop


@pytest.fixture(scope="module")
def loops():
    return [_loop(1, 700), _loop(2, 800), _loop(3, 800)]  # two lengths: each is a compilation of its own


@pytest.fixture(scope="module")
def singles(loops):
    return [js.estimate(lp, SMALL) for lp in loops]


NO_SPLINE = dataclasses.replace(SMALL, use_spline=False)


@pytest.fixture(scope="module")
def no_spline(loops):
    """The first loop fitted with the screen's profile (no spline family)."""
    return js.estimate(loops[0], NO_SPLINE)


def test_synthetic_fit_finds_the_valve(singles):
    """A stiction loop built by the simulator: the physical model is chosen, S and J
    are near the truth, and the held-out simulation fitness is high."""
    for f in singles:
        assert code(f.result) == code(js.RESULTS.successful)
        assert int(f.kind) == 1
        assert abs(float(f.S) - TRUE_S) < 1.0
        assert abs(float(f.J) - TRUE_J) < 1.0
        assert float(f.fitness) > 60.0
        assert float(f.band_percent) == pytest.approx(float(f.S))
        # the validation split: a quarter of the samples, rounded
        n = f.n_estimation + f.n_validation
        assert int(f.n_validation) == round(0.25 * int(n))


def _close(a, b, rtol=1e-6, atol=1e-8):
    for x, y in zip(jax.tree.leaves(eqx.filter(a, eqx.is_array)), jax.tree.leaves(eqx.filter(b, eqx.is_array))):
        x, y = np.asarray(x), np.asarray(y)
        if x.dtype.kind in "iub":
            np.testing.assert_array_equal(x, y)
        else:
            np.testing.assert_allclose(x, y, rtol=rtol, atol=atol, equal_nan=True)


def test_vmap_over_stacked_loops_equals_single_calls(loops, singles):
    """The batched contract: filter_vmap(estimate)(stack(loops)) member i == the single
    call on loop i, fitness and band included, although the loops differ in length."""
    batch = js.stack(loops)
    fits = eqx.filter_vmap(lambda lp: js.estimate(lp, SMALL))(batch)
    for i, f in enumerate(singles):
        member = jax.tree.map(lambda t: t[i], fits)
        for name in ("fitness", "fitness_estimation", "band_percent", "S", "J", "kind"):
            np.testing.assert_allclose(np.asarray(getattr(member, name)), np.asarray(getattr(f, name)),
                                       rtol=1e-6, atol=1e-8, err_msg=name)
        assert code(member.result) == code(f.result)
        _close(member.model, f.model)


def test_padding_does_not_change_the_answer(loops, singles):
    """A loop padded with masked samples gives the unpadded answer (to rounding)."""
    padded = js.stack([loops[0]], length=loops[2].op.shape[0])
    f = js.estimate(jax.tree.map(lambda t: t[0], padded), SMALL)
    ref = singles[0]
    for name in ("fitness", "fitness_estimation", "band_percent", "S", "J", "kind", "n_validation"):
        np.testing.assert_allclose(np.asarray(getattr(f, name)), np.asarray(getattr(ref, name)), rtol=1e-6, atol=1e-8,
                                   err_msg=name)
    assert code(f.result) == code(ref.result)


def test_no_retracing_for_new_data_of_one_shape(loops, singles):
    """New data of an already-seen shape reuses the compiled estimate."""
    before = eqx.debug.get_num_traces(estimate_traced)
    other = _loop(9, loops[0].op.shape[0])
    js.estimate(other, SMALL)
    js.estimate(jax.tree.map(lambda t: t + 1.0, other), SMALL)
    assert eqx.debug.get_num_traces(estimate_traced) == before


@pytest.mark.parametrize(
    "spoil, name",
    [
        (lambda lp: eqx.tree_at(lambda t: t.pv, lp, lp.pv.at[100].set(jnp.nan)), "nonfinite_data"),
        (lambda lp: eqx.tree_at(lambda t: t.op, lp, jnp.full_like(lp.op, 42.0)), "constant_op"),
        (lambda lp: eqx.tree_at(lambda t: t.pv, lp, jnp.full_like(lp.pv, 3.0)), "constant_pv"),
        (lambda lp: eqx.tree_at(lambda t: t.mask, lp, lp.mask.at[120:].set(0.0)), "too_short"),
    ],
)
def test_bad_member_gets_its_code_and_spoils_nothing(loops, singles, spoil, name):
    """Under vmap, a bad loop gets its own data code and the good ones are unchanged.
    (Three loops of the batched-contract test's shape: its compiled program serves.)"""
    bad = spoil(loops[2])
    fits = eqx.filter_vmap(lambda lp: js.estimate(lp, SMALL))(js.stack([loops[0], loops[1], bad]))
    got = code(fits.result)
    assert got[2] == code(getattr(js.RESULTS, name))
    for i in (0, 1):
        assert got[i] == code(js.RESULTS.successful)
        np.testing.assert_allclose(float(fits.fitness[i]), float(singles[i].fitness), rtol=1e-6)


def test_predict_delegates_to_the_model(loops, singles):
    f, lp = singles[0], loops[0]
    np.testing.assert_allclose(f.predict(lp.op), f.model.simulate(lp.op))
    k1 = f.predict(lp.op, lp.pv, k=1)
    assert k1.shape == lp.op.shape and bool(jnp.all(jnp.isfinite(k1)))
    # one-step prediction beats simulation (the noise model is used)
    sim = f.predict(lp.op, lp.pv)
    assert float(jnp.mean((lp.pv - k1) ** 2)) < float(jnp.mean((lp.pv - sim) ** 2))


def test_predict_scored(loops, singles):
    """k-step prediction scored like a simulation: from an estimated initial state, on
    the marked samples; a horizon as long as the record is the simulation's score, and
    a one-step prediction scores higher."""
    f, lp = singles[0], loops[0]
    n = lp.op.shape[0]
    w = lp.mask * (jnp.arange(n) >= n // 3)
    sim = float(js.score(f.model, lp.op, lp.pv, w))
    assert float(js.predict_scored(f.model, lp.op, lp.pv, w, n)) == pytest.approx(sim, abs=1e-8)
    assert float(js.predict_scored(f.model, lp.op, lp.pv, w, 1)) > sim


def test_held_out_note_flags_a_model_that_does_not_carry_to_new_data():
    """A note only when the held-out simulation is worse than the data's mean while
    the estimation part's is not (PAP7's spline model: -399 % against 8.1 %)."""
    note = held_out_note(-399.3, 8.1, 4700)
    assert "-399.3 %" in note and "8.1 %" in note
    assert held_out_note(-399.3, 8.1, 0) == ""  # nothing held out: the score is the estimation one
    assert held_out_note(-5.0, -20.0, 100) == ""  # no worse than on the data it was fitted on
    assert held_out_note(40.0, 80.0, 100) == "" and held_out_note(np.nan, 80.0, 100) == ""


def test_host_fit_rejects_bad_input(loops):
    lp = loops[0]
    op = np.asarray(lp.op).copy()
    op[5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        js.fit(op, np.asarray(lp.pv), settings=SMALL)
    with pytest.raises(ValueError, match="too short|at least"):
        js.fit(np.asarray(lp.op)[:100], np.asarray(lp.pv)[:100], settings=SMALL)


@pytest.mark.slow
def test_host_fit_reports(loops):
    lp = loops[0]
    r = js.fit(np.asarray(lp.op), np.asarray(lp.pv), validate=0.25, settings=SMALL, name="syn")
    d = r.to_json()
    assert d["status"] == "ok" and d["model"]["kind"] == "physical"
    assert d["stiction"]["S"] == pytest.approx(float(r.S), abs=1e-3)
    # the family with the lower BIC is the one chosen
    fam = r.candidates["families"]
    assert fam["physical"]["bic"] is not None and fam["physical"]["foe"] > 0
    assert fam["spline"]["bic"] is None or fam["physical"]["bic"] < fam["spline"]["bic"]
    assert d["note"] == "; ".join(r.notes)


@pytest.mark.slow
def test_exported_program_cache(loops, no_spline, tmp_path, monkeypatch):
    """`fit`'s on-disk cache of exported `estimate` programs: the first call exports
    and saves, a new process (here: the in-memory table cleared) loads the file
    without tracing `estimate` again, a corrupt file is rebuilt, without the cache
    the programs are kept in memory and nothing is written, and every route gives
    what `estimate` gives. (With the screen's profile, the smaller program: the
    cache does not depend on the settings.)"""
    from jaxstiction.internal import programs

    # (the suite's conftest turns on XLA's persistent compilation cache, as the
    # command line does, so the loaded and the rebuilt program are not compiled again)
    monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
    programs.use_program_cache(tmp_path)
    try:
        first = programs.estimate_cached(loops[0], NO_SPLINE)
        (path,) = tmp_path.glob("estimate-*.jaxexport")
        exports = []
        real_export = programs._export
        monkeypatch.setattr(programs, "_export", lambda *a: exports.append(1) or real_export(*a))
        monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
        loaded = programs.estimate_cached(loops[0], NO_SPLINE)
        assert exports == []
        path.write_bytes(b"not a program")
        monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
        rebuilt = programs.estimate_cached(loops[0], NO_SPLINE)
        assert exports == [1]
    finally:
        programs.use_program_cache(None)
    # without the cache (the API's `fit`): the same programs, kept in memory only,
    # and only for the most recently used shapes (here one: a stale entry goes)
    monkeypatch.setattr(programs, "_loaded", collections.OrderedDict(stale=None))
    monkeypatch.setattr(programs, "_KEEP", 1)
    files = sorted(tmp_path.iterdir())
    in_memory = programs.estimate_cached(loops[0], NO_SPLINE)
    assert exports == [1, 1] and sorted(tmp_path.iterdir()) == files
    assert list(programs._loaded) == [programs._key(loops[0], NO_SPLINE)]
    reference = programs.simulations_of(no_spline, loops[0].op, loops[0].pv, loops[0].mask, NO_SPLINE.score)
    for got, sims in (first, loaded, rebuilt, in_memory):
        for sim, ref in zip(sims, reference):
            np.testing.assert_allclose(sim, ref, rtol=1e-9, atol=1e-9)
        for name in ("fitness", "fitness_linear", "fitness_deadband", "S", "J", "band_percent"):
            np.testing.assert_allclose(getattr(got, name), getattr(no_spline, name), rtol=1e-9)
        assert code(got.result) == code(no_spline.result)


def test_a_linear_valve_is_chosen_when_no_stiction_model_beats_it():
    """A loop with a linear valve: the Kano fit nests it (S = J = 0) but costs two more
    parameters, so BIC chooses the linear valve; the chosen model's band is 0 and its
    scores are the linear valve's. (The same length and settings as `no_spline`: no
    new compilation.)"""
    rec = js.simulate_loop(nominal_model(), paper_experiment(), jr.PRNGKey(5), 700)
    f = js.estimate(rec.loop, NO_SPLINE)
    assert code(f.result) == code(js.RESULTS.successful)
    assert int(f.kind) == 2 and float(f.bic_linear) < float(f.bic_physical)
    assert float(f.band_percent) == 0.0
    assert float(f.fitness) == pytest.approx(float(f.fitness_linear))
    assert float(f.fitness_estimation) == pytest.approx(float(f.fitness_linear_estimation))


def test_family_choice_needs_a_simulation_as_good_as_the_linear_valve():
    """The least BIC wins, but a stiction family whose scored simulation of the
    estimation part is worse than the linear valve's (which it nests) is not eligible,
    nor is a linear valve that simulates worse than the data's mean when a stiction
    family does not."""
    choose = lambda b, f: int(choose_family(jnp.asarray(b), jnp.asarray(f)))  # noqa: E731
    assert choose([10.0, 5.0, 20.0], [80.0, 75.0, 70.0]) == 1
    assert choose([10.0, 5.0, 20.0], [80.0, 60.0, 70.0]) == 0  # the Kano model simulates worse
    assert choose([10.0, 5.0, 20.0], [65.0, 60.0, 70.0]) == 2
    assert choose([np.nan, 5.0, 20.0], [np.nan, 75.0, 70.0]) == 1
    assert choose([10.0, 5.0, 20.0], [np.nan, np.nan, 70.0]) == 2  # scores that failed
    assert choose([10.0, 5.0, 20.0], [80.0, 60.0, np.nan]) == 1  # no linear score to compare with
    # a linear valve whose simulation is further from the data than their mean gives
    # way to a stiction family that scores at least 0, whatever the BIC
    assert choose([30.0, 25.0, 20.0], [10.0, 40.0, -5.0]) == 1
    assert choose([30.0, 45.0, 20.0], [10.0, 40.0, -5.0]) == 0
    assert choose([30.0, 25.0, 20.0], [-10.0, -1.0, -5.0]) == 2  # no family sound: BIC decides
    assert choose([np.inf, np.inf, 20.0], [10.0, 40.0, -5.0]) == 2  # the sound ones failed


def test_chosen_family_simulates_at_least_as_well_as_the_linear_valve(singles, no_spline):
    for f in (*singles, no_spline):
        if int(f.kind) != 2:
            assert float(f.fitness_estimation) >= float(f.fitness_linear_estimation)


def test_without_the_spline_family(no_spline, singles):
    """`use_spline=False` (the screen's profile) leaves the Kano model and the
    verdict's nulls exactly as the full estimator fits them; the spline fields are
    NaN and the physical model is the chosen one. Both families off is an error."""
    got = no_spline
    for name in ("S", "J", "fitness_physical", "fitness_physical_estimation", "fitness_linear",
                 "fitness_linear_estimation", "fitness_deadband", "fitness_deadband_estimation"):
        np.testing.assert_allclose(getattr(got, name), getattr(singles[0], name), rtol=1e-9)
    assert np.isnan(float(got.fitness_spline)) and np.isnan(float(got.fitness_paper))
    assert int(got.kind) == 1 and float(got.fitness) == pytest.approx(float(got.fitness_physical))
    with pytest.raises(ValueError, match="use_spline"):
        js.Settings(use_spline=False, use_physical=False)


@pytest.mark.parametrize("make, named", [
    (lambda: js.SplineSettings(compression="lu"), "compression"),
    (lambda: js.SplineSettings(knot_counts=()), "knot_counts"),
    (lambda: js.SplineSettings(knot_counts=(4, 1)), "knot_counts"),
    (lambda: js.SplineSettings(relax_steps=0), "relax_steps"),
    (lambda: js.PhysicalSettings(num_S=0), "num_S"),
    (lambda: js.PhysicalSettings(oe_steps=2.5), "oe_steps"),
    (lambda: js.PhysicalSettings(rounds=-1), "rounds"),
    (lambda: js.PhysicalSettings(max_band=0.0), "max_band"),
    (lambda: js.ScoreSettings(init_fraction=1.5), "init_fraction"),
    (lambda: js.ScoreSettings(init_count=True), "init_count"),
    (lambda: js.ScreenSettings(chunk=-1), "chunk"),
    (lambda: js.VerdictSettings(prediction_horizon=0), "prediction_horizon"),
    (lambda: js.VerdictSettings(trend_degree=-1), "trend_degree"),
])
def test_bad_settings_are_named(make, named):
    """A settings field that cannot work (a grid of no points, an unknown method) is
    a `ValueError` naming it when the settings are made, not a failure deep in a
    trace."""
    with pytest.raises(ValueError, match=named):
        make()


def test_units_of_op_and_pv_do_not_change_the_fit(loops, no_spline):
    """Real loops record OP and PV in any units (%, fractions, mA, signed, reverse
    acting). An affine change of PV's units (here with a sign flip) and a change of
    OP's scale and zero leave the fit the same: S, J and the band move with OP's
    units, the fitness and the family do not."""
    lp = loops[0]
    got = js.estimate(eqx.tree_at(lambda t: (t.op, t.pv), lp, (2.0 * lp.op + 64.0, 250.0 - 4.0 * lp.pv)), NO_SPLINE)
    assert code(got.result) == code(no_spline.result)
    assert int(got.kind) == int(no_spline.kind)
    for name in ("S", "J", "band_percent"):
        np.testing.assert_allclose(getattr(got, name), 2.0 * getattr(no_spline, name), rtol=1e-6)
    for name in ("fitness", "fitness_estimation", "fitness_linear", "fitness_deadband"):
        np.testing.assert_allclose(getattr(got, name), getattr(no_spline, name), rtol=1e-6, atol=1e-6)
