"""The command line: one-line errors with exit 2, and the JSON contract (the documented contract)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import run

import jaxstiction as js


def _csv(path, op, pv, header="t,OP,PV"):
    rows = [header] + [f"{i},{a},{b}" for i, (a, b) in enumerate(zip(op, pv))]
    path.write_text("\n".join(rows) + "\n")
    return path


def _good(n=800):
    rng = np.random.default_rng(1)
    op = 50 + 10 * np.sin(np.arange(n) / 25) + rng.normal(0, 0.3, n)
    pv = np.convolve(op - 50, [0, 0.5, 0.3])[:n] + rng.normal(0, 0.1, n)
    return op, pv


def _assert_one_line_error(res, match):
    assert res.returncode == 2, res.stderr
    assert res.stdout == ""
    # progress lines may precede it; the error itself is exactly one line, last
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error: ")]
    assert len(errors) == 1 and errors[0] == lines[-1], res.stderr
    assert match in errors[0], errors[0]
    assert "Traceback" not in res.stderr


def test_missing_column(tmp_path):
    op, pv = _good()
    f = tmp_path / "x.csv"
    f.write_text("t,OP\n" + "\n".join(f"{i},{a}" for i, a in enumerate(op)) + "\n")
    _assert_one_line_error(run("fit", str(f), "--json"), "PV")


def test_nan(tmp_path):
    op, pv = _good()
    pv[10] = np.nan
    _assert_one_line_error(run("fit", str(_csv(tmp_path / "x.csv", op, pv)), "--json"), "NaN")


def test_constant_op(tmp_path):
    op, pv = _good()
    _assert_one_line_error(run("fit", str(_csv(tmp_path / "x.csv", 0 * op + 30, pv)), "--json"), "constant")


def test_too_short(tmp_path):
    op, pv = _good(80)
    _assert_one_line_error(run("fit", str(_csv(tmp_path / "x.csv", op, pv))), "at least")


def test_uneven_time_column_is_a_one_line_warning(tmp_path):
    """The reader's warning reaches stderr as one `warning: ...` line (here before the
    record is rejected as too short, so that nothing is fitted)."""
    op, pv = _good(40)
    t = np.arange(40.0)
    t[25:] += 3.0
    rows = ["t,OP,PV"] + [f"{a},{b},{c}" for a, b, c in zip(t, op, pv)]
    (tmp_path / "gap.csv").write_text("\n".join(rows) + "\n")
    res = run("fit", str(tmp_path / "gap.csv"), "--json")
    _assert_one_line_error(res, "at least")
    (warning,) = [ln for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
    assert "`t` in" in warning and "gap.csv" in warning and "not evenly spaced" in warning
    assert "Warning" not in res.stderr  # not Python's multi-line warning format


def test_unreadable_and_missing_file(tmp_path):
    f = tmp_path / "junk.csv"
    f.write_bytes(bytes(range(256)) * 4)
    _assert_one_line_error(run("fit", str(f), "--json"), "junk.csv")
    _assert_one_line_error(run("fit", str(tmp_path / "nope.csv")), "nope.csv")


@pytest.mark.parametrize("cmd,option", [("fit", "--max-delay"), ("screen", "--max-delay"), ("fit", "--decimate"),
                                        ("screen", "--decimate"), ("diagnose", "--decimate"), ("screen", "--threads"),
                                        ("screen", "--window")])
def test_counts_must_be_positive(tmp_path, cmd, option):
    res = run(cmd, str(tmp_path / "x.csv"), option, "0")
    assert res.returncode == 2 and option in res.stderr and "positive whole number" in res.stderr


@pytest.mark.parametrize("value", ["1.5", "-0.1", "nan"])
def test_validate_is_checked_before_the_file_is_read(tmp_path, value):
    """A held-out fraction outside [0, 1) is refused in one line naming the option,
    before the record is read (the file does not exist) or anything is logged."""
    res = run("fit", str(tmp_path / "x.csv"), "--validate", value)
    _assert_one_line_error(res, "--validate")
    assert "x.csv" not in res.stderr and "fitting" not in res.stderr


def test_decimate_shortens_the_record(tmp_path):
    """`--decimate 10` fits the block means: 800 samples become 80, too short (so
    nothing is fitted), and the log says the record was decimated; with a nominal
    model `diagnose` refuses it in one line."""
    op, pv = _good()
    f = _csv(tmp_path / "x.csv", op, pv)
    res = run("fit", str(f), "--decimate", "10", "--json")
    _assert_one_line_error(res, "at least")
    assert "fit: x: 80 samples, Ts = 10 s (decimated by 10)" in res.stderr
    nominal = tmp_path / "nominal.json"
    nominal.write_text(json.dumps({"Ts": 1.0, "process": {"b": [0, 0.5], "a": [1, -0.5], "delay": 0},
                                   "op_offset": 50.0, "pv_offset": 0.0, "valve": {"model": "linear"}}))
    _assert_one_line_error(run("diagnose", str(f), "--model", str(nominal), "--decimate", "2"),
                           "--decimate cannot be used with --model")


def test_long_record_note(tmp_path):
    """A record longer than `LONG_RECORD` is announced with its cost and the way to
    shorten it before any fitting (here the fit then stops at the constant OP); a
    shorter one is not."""
    from jaxstiction.internal import LONG_RECORD

    n = LONG_RECORD + 10
    f = _csv(tmp_path / "long.csv", np.full(n, 50.0), np.sin(np.arange(n) / 50.0))
    res = run("fit", str(f), "--json")
    _assert_one_line_error(res, "constant")
    assert f"fit: note: {n} samples is a long record" in res.stderr and "--decimate K" in res.stderr
    res = run("fit", str(f), "--decimate", "2", "--json")
    assert "long record" not in res.stderr and res.returncode == 2


@pytest.mark.slow
def test_fit_json_contract_on_chem23(isdb, tmp_path):
    """CHEM23 by the paper's protocol (validated on its estimation data; the paper
    reports 75.67 %, >= 77 % is asked), through the command line's JSON contract."""
    res = run("fit", str(isdb / "CHEM23.csv"), "--validate", "0", "--json", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)  # exactly one JSON object on stdout
    assert out["fitness"] >= 77.0
    assert {"fitness", "model", "stiction", "converged"} <= set(out)
    assert out["converged"] and out["samples"] == {"estimation": 1500, "validation": 0}
    st = out["stiction"]
    assert 0 < st["band_percent"] < 100 and st["S_interval"][0] <= st["S"] <= st["S_interval"][1]
    saved = json.loads((tmp_path / "report.json").read_text())
    assert saved["fitness"] == out["fitness"]
    # on the estimation data BIC prefers the Kano model (77.3 %; the spline: 78.75 %)
    assert out["model"]["kind"] == "physical" and out["model"]["knots"] == 0
    assert out["stiction"]["band_percent"] == out["stiction"]["S"]
    for name in ("report.json", "valve_curve.png", "model_fit.png", "step_response.png"):
        assert (tmp_path / name).stat().st_size > 0, name


@pytest.mark.slow
def test_demo_json_contract_and_no_run_away_choice(tmp_path):
    """`demo` end to end (the README's first command) on a seed where FOE preferred a
    spline model whose simulation ran away on the validation record (-67 % against the
    noise-free PV): BIC chooses the Kano model, and the JSON keeps its contract."""
    res = run("demo", "--seed", "11", "--json", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert {"fitness_validation", "fitness_noise_free", "ceiling", "stiction"} <= set(out)
    assert out["fit"]["model"]["kind"] == "physical"
    assert out["fitness_noise_free"] > 75.0
    assert abs(out["stiction"]["S"] - 20.0) < 1.0 and abs(out["stiction"]["J"] - 2.0) < 0.5
    for name in ("report.json", "model_fit.png"):
        assert (tmp_path / name).stat().st_size > 0, name


@pytest.mark.parametrize("cmd", [["--help"], ["fit", "--help"], ["demo", "--help"]])
def test_help(cmd):
    res = run(*cmd)
    assert res.returncode == 0 and "usage" in res.stdout


def test_version():
    """`--version` names the package and the JAX versions its compiled programs depend on."""
    from importlib.metadata import version

    res = run("--version")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == f"jaxstiction {js.__version__} (jax {version('jax')}, jaxlib {version('jaxlib')})"


def test_import_leaves_the_backend_alone():
    """Importing the package (and `jaxstiction.internal`, which imports the command
    line) creates no JAX backend, so the command line can still choose XLA's
    compiler flags, and users their platform."""
    code = ("import jaxstiction, jaxstiction.internal, jax._src.xla_bridge as xb;"
            "print(xb.backends_are_initialized())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_lean_compiler_flag(monkeypatch):
    """The command line adds the fusion-emitter flag to XLA_FLAGS, keeps the user's
    own flags, never overrides the user's own choice of it, and can be turned off."""
    import jaxlib

    from jaxstiction.internal import cli, lean_compiler

    monkeypatch.setattr(cli, "_LEAN_COMPILER_VERIFIED", (jaxlib.__version__,))
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/nowhere")
    lean_compiler()
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/nowhere --xla_cpu_use_fusion_emitters=false"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    lean_compiler()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setenv("JAXSTICTION_LEAN_COMPILER", "off")
    lean_compiler()
    assert os.environ["XLA_FLAGS"] == ""
    monkeypatch.delenv("JAXSTICTION_LEAN_COMPILER")
    monkeypatch.setattr(cli, "_LEAN_COMPILER_VERIFIED", ("0.0.",))
    lean_compiler()
    assert os.environ["XLA_FLAGS"] == ""


def test_screen_search_options_choose_the_estimator_profile():
    """`screen` fits with the light Kano search by default, the full estimator's with
    `--full-search` (both without the spline family), and `--max-delay` applies to
    either."""
    from jaxstiction import Settings
    from jaxstiction.internal import build_parser, SCREEN_ESTIMATE, screen_settings

    def settings(*argv):
        return screen_settings(build_parser().parse_args(["screen", "x.csv", *argv])).estimate

    assert settings() == SCREEN_ESTIMATE
    full = settings("--full-search")
    assert full == Settings(use_spline=False) and full.physical.arx_order > SCREEN_ESTIMATE.physical.arx_order
    assert settings("--full-search", "--max-delay", "6") == Settings(use_spline=False).with_max_delay(6)
    assert settings("--max-delay", "6") == SCREEN_ESTIMATE.with_max_delay(6)


def test_screen_threshold_sets_the_verdicts_probability():
    from jaxstiction.internal import build_parser, screen_settings

    def parsed(*argv):
        return screen_settings(build_parser().parse_args(["screen", "x.csv", *argv])).verdict

    assert parsed() == js.VerdictSettings() and parsed("--threshold", "0.2").threshold == 0.2
    for bad in ("0", "1", "1.5", "x"):
        res = run("screen", "x.csv", "--threshold", bad)
        assert res.returncode == 2 and "--threshold" in res.stderr and "probability" in res.stderr
