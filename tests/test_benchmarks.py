"""The benchmark scripts still start: each parses `--help`, and one screens a loop.

The scripts are not run in full here (minutes each); these checks catch what broke
`calibrate_verdict.py` for a session unnoticed: a script whose options fell out of
step with the library it calls."""

import dataclasses
import json
import pathlib
import runpy
import sys

import numpy as np
import pytest


BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py") if not p.name.startswith("_"))


def _run(monkeypatch, script, *argv):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the scripts import `_args` from there
    monkeypatch.setattr(sys, "argv", [str(BENCHMARKS / script), *argv])
    runpy.run_path(str(BENCHMARKS / script), run_name="__main__")


def test_every_script_is_listed():
    assert len(SCRIPTS) >= 9 and "calibrate_verdict.py" in SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_script_help(script, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exit_:
        _run(monkeypatch, script, "--help")
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage:") and script in out


@pytest.mark.slow
def test_calibrate_verdict_screens_a_loop(monkeypatch, capsys):
    # one healthy loop through the screen's settings as the script builds them
    _run(monkeypatch, "calibrate_verdict.py", "--seeds", "0", "--kinds", "none")
    out = capsys.readouterr().out
    assert "balanced accuracy" in out and "none-0" in out


@pytest.mark.parametrize("text, seeds", [("0-3", [0, 1, 2, 3]), ("1,4,7", [1, 4, 7]), ("7", [7]),
                                         ("0-2,30-31,40", [0, 1, 2, 30, 31, 40])])
def test_seeds_round_trip(text, seeds, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    from _args import seeds_arg, seeds_text

    assert seeds_arg(text) == seeds and seeds_text(seeds) == text


def test_drift_power_runs(monkeypatch, capsys):
    # two seeds of P0 and P8, P8's own step: the statistics exist and the rule's
    # threshold is the one `diagnose` uses (eight families at alpha 0.05)
    _run(monkeypatch, "drift_power.py", "--seeds", "0-1", "--steps", "0.3", "--json")
    out = json.loads(capsys.readouterr().out)
    assert 3.0 < out["rule_threshold"] < 3.3
    row = out["steps"]["0.3"]
    assert set(row) >= {"rule_power", "glr_power_0.01", "oracle_power_0.05"}
    assert all(0.0 <= v <= 1.0 for v in row.values())


def test_compare_screens_names_what_differs(monkeypatch, capsys, tmp_path):
    loops = [{"name": "a", "verdict": "stiction", "stiction_probability": 0.9, "status": "ok", "crossval": [1.0, 2.0]},
             {"name": "b", "verdict": "no_stiction", "stiction_probability": 0.1, "status": "ok", "S": 1.0}]
    other = [dict(loops[0]), {**loops[1], "S": 1.5}]
    for name, entries in (("one.json", loops), ("two.json", other)):
        (tmp_path / name).write_text(json.dumps({"loops": entries}))
    _run(monkeypatch, "compare_screens.py", str(tmp_path / "one.json"), str(tmp_path / "two.json"))
    out = capsys.readouterr().out
    assert "2 loops: 1 identical in every field" in out
    assert "verdict: the same on every loop" in out and "b: 1 fields differ, e.g. S 1.0 / 1.5" in out


@pytest.mark.parametrize("balanced", [True, False])
def test_calibration_weights(balanced, monkeypatch):
    # the real records carry `REAL_SHARE` of the weight; balanced, each class half of its part
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import calibrate_probability as cp

    monkeypatch.setattr(cp, "BALANCED", balanced)
    sim, real = [1, 0, 0, 0, 0], [1, 1, 0]
    w = cp.weights(sim, real)
    ws, wr = w[:5], w[5:]
    assert ws.sum() == pytest.approx(5.0)
    assert wr.sum() / w.sum() == pytest.approx(cp.REAL_SHARE)
    for part, y in ((ws, sim), (wr, real)):
        sticky = part[[bool(v) for v in y]].sum() / part.sum()
        assert sticky == pytest.approx(0.5 if balanced else sum(y) / len(y))
    assert cp.weights(sim, []).sum() == pytest.approx(5.0)


def test_verdict_oracle(monkeypatch, capsys):
    # the oracle's power is the non-central chi-square's, and a valve path equal to
    # OP carries nothing beyond it (lambda 0 with the gain free)
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    from scipy.stats import ncx2
    from verdict_oracle import oracle_lambdas, power

    from jaxstiction.internal import fleet_draw, realistic_fleet

    for lam, t in ((0.5, 3.84), (9.0, 3.84), (40.0, 17.0)):
        assert abs(float(power(lam, t)) - ncx2.sf(t, 1, lam)) < 1e-9
    loop = realistic_fleet([3], "stiction")[0]
    params = fleet_draw(3, "stiction")[0]
    free, known = oracle_lambdas(loop, params)
    assert free > 25.0 and known > 25.0
    linear = dataclasses.replace(loop, valve=loop.op)
    assert oracle_lambdas(linear, params)[0] < 1e-6
    _run(monkeypatch, "verdict_oracle.py", "--seeds", "0-19")
    out = capsys.readouterr().out
    assert "oracle, free gain" in out and "oracle, known gain" in out


def test_split_half(monkeypatch, capsys):
    # each split judges half of the sticky and half of the healthy valves, fitted on
    # the rest; a perfect caller reaches 0.80 on every split, one that never calls
    # sticky on none, and then every sticky recording is listed as judged wrong
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import calibrate_probability as cp

    real = [{"set": "plant", "name": f"L{i}", "valve": f"V{i // 2}", "label": i < 6} for i in range(16)]
    real.append({"set": "isdb", "name": "CHEM1", "valve": "CHEM1", "label": True})
    fitted = []
    monkeypatch.setattr(cp, "fit", lambda sim, train: fitted.append(train) or None)
    monkeypatch.setattr(cp, "called", lambda e, cal: e["label"])
    cp.split_half([], real, 10)
    out = capsys.readouterr().out
    assert "8 labelled plant valves (3 sticky)" in out
    assert "10 of 10 splits reach 0.80" in out and "right on" not in out
    for train in fitted:
        assert any(e["set"] == "isdb" for e in train)
        assert len({e["valve"] for e in train if e["set"] == "plant" and e["label"]}) in (1, 2)
        assert len({e["valve"] for e in train if e["set"] == "plant" and not e["label"]}) in (2, 3)
    monkeypatch.setattr(cp, "called", lambda e, cal: False)
    cp.split_half([], real, 10)
    out = capsys.readouterr().out
    assert "0 of 10 splits reach 0.80" in out and "L0     V0" in out and "right on 0.00" in out


def test_the_shipped_probability_weighs_the_indicators_only(monkeypatch, capsys):
    # the written calibration gives the unweighed model-based features no weight,
    # as `--write` fits it; `--write` refuses any other set of features
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import calibrate_probability as cp

    from jaxstiction.internal import CALIBRATION, FEATURES

    assert set(cp.UNWEIGHED) < set(FEATURES) and cp.DROPPED == frozenset(cp.UNWEIGHED)
    weights = dict(zip(CALIBRATION.names, np.asarray(CALIBRATION.weights)))
    assert all(weights[k] == 0 for k in cp.UNWEIGHED)
    assert all(weights[k] != 0 for k in FEATURES if k not in cp.UNWEIGHED)
    with pytest.raises(SystemExit) as exit_:
        _run(monkeypatch, "calibrate_probability.py", "--write", "--drop", "none")
    assert exit_.value.code == 2 and "cannot be combined with --write" in capsys.readouterr().err
