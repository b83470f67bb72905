"""The realistic simulated fleet: every drawn loop is a loop under control."""

import numpy as np

from jaxstiction._fleet import _draw, _poles, _tune, KINDS, realistic_fleet


def test_every_draw_is_stable_and_tight_loops_are_lightly_damped():
    for seed in range(400):
        p, *_, truth = _draw(seed, None)
        rho, osc = _poles(p["a"], p["b"], p["delay"], p["kp"], p["ki"])
        assert rho < 1.0, (seed, rho)
        assert p["kp"] > 0 and p["ki"] > 0
        if truth["kind"] == "tight":
            assert 0.93 <= osc <= 0.985, (seed, osc)


def test_tune_lowers_the_gain_only_when_the_loop_is_unstable():
    # a slow integrating loop whose slowest pole sits near 1: controlled as tuned
    lag = 0.5
    a = np.array([1.0, -(1.0 + lag), lag, 0.0])
    b = np.array([0.01 * (1.0 - lag), 0.0, 0.0])
    kp, ratio = 2.0, 1.0 / 400.0
    rho, _ = _poles(a, b, 10, kp, kp * ratio)
    assert 0.99 < rho < 1.0
    assert _tune(a, b, 10, kp, ratio, tight=False) == kp
    # ten times that gain is unstable: lowered until stable, not to nothing
    rho, _ = _poles(a, b, 10, 40 * kp, 40 * kp * ratio)
    assert rho > 1.0
    tuned = _tune(a, b, 10, 40 * kp, ratio, tight=False)
    assert _poles(a, b, 10, tuned, tuned * ratio)[0] < 1.0
    assert tuned > kp


def test_tune_reaches_the_tight_window_from_either_side():
    p1 = np.exp(-1.0 / 8.0)
    a = np.array([1.0, -p1, 0.0, 0.0])
    b = np.array([1.0 - p1, 0.0, 0.0])
    for kp in (0.01, 1.0, 100.0):
        tuned = _tune(a, b, 3, kp, 0.1, tight=True)
        rho, osc = _poles(a, b, 3, tuned, 0.1 * tuned)
        assert rho < 1.0 and 0.93 <= osc <= 0.985, (kp, tuned, rho, osc)


def test_the_controller_moves_op_in_every_kind():
    for kind in KINDS:
        for lp in realistic_fleet(range(8), kind):
            assert np.std(lp.op) > 1e-3, (kind, lp.seed)
