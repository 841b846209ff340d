"""The causal IMM (``solver.estimation.imm``) with its step compiled (``imm_ct_step``) against
the plain-numpy filter it replaced (``tests/imm_reference.py``), on the IMM smoother tests'
turning track: polar plots (EKF and converted), polar plots mixed with position fixes and
simultaneous plots (several sensors), 19-s scans, the turn rate at its bound, a straight
track (the turn terms' series) and a long gap (the iterated EKF update)."""

import imm_reference
import numpy as np
import pytest
from test_estimation_imm_smoother import (
    LEGS,
    RADAR,
    SIGMA_PSI,
    SIGMA_R,
    START,
    mixed_sensor_plots,
)
from tracks import held, make_track

from solver.estimation import imm_ct_step, imm_step
from solver.estimation.imm import OMEGA_MAX, run_imm
from solver.estimation.measurements import PolarPlots
from solver.estimation.models import TURN_SERIES_WT


def _polar(seed: int, scan_s: float = 4.0, legs=LEGS) -> PolarPlots:
    tr = make_track(legs, START, scan_s=scan_s, sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI,
                    drop_in_turns=False, seed=seed)
    return PolarPlots.from_plots(tr.plots, RADAR)


@pytest.mark.parametrize("case", ["ekf", "converted", "sensors", "simultaneous", "long_scans",
                                  "bound", "straight", "gap"])
def test_compiled_step_equals_the_numpy_reference(case, monkeypatch):
    measurement = "converted" if case == "converted" else "ekf"
    omega_max = np.deg2rad(0.5) if case == "bound" else OMEGA_MAX
    if case in ("sensors", "simultaneous"):
        meas = mixed_sensor_plots(_polar(1), simultaneous=case == "simultaneous")
    elif case == "long_scans":  # 19-s scans (the bound keeps omega T below pi)
        meas = _polar(2, scan_s=19.0)
    elif case == "straight":  # no turn: omega T stays in the series' range
        meas = _polar(3, legs=[(900.0, 0.0, 0.0)])
    elif case == "gap":
        meas = held(_polar(1))
    else:
        meas = _polar(1)
    got = run_imm(meas, measurement=measurement, omega_max=omega_max)
    want = imm_reference.run_imm(meas, measurement=measurement, omega_max=omega_max)
    if case == "gap":  # the iterations ran: one pass each leaves the plot after the gap far
        monkeypatch.setattr(imm_step, "MAX_LINEARISATIONS", 1)
        once = run_imm(meas, measurement=measurement, omega_max=omega_max)
        plot = meas.points()[31]
        assert np.hypot(*(once.states.states[31, :2] - plot)) > 5_000.0
        assert np.hypot(*(got.states.states[31, :2] - plot)) < 200.0
    scale = np.abs(want.states.states).max()
    np.testing.assert_allclose(got.states.states, want.states.states, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(got.states.cov, want.states.cov, rtol=1e-7,
                               atol=1e-9 * np.abs(want.states.cov).max())
    for key in ("model_probabilities", "turn_rate"):
        np.testing.assert_allclose(got.info[key], want.info[key], rtol=0, atol=1e-9)
    omega = np.abs(got.info["turn_rate"])
    if case == "bound":  # 2 deg/s turns against a bound of 0.5 deg/s: projected on it
        assert 0.9 * omega_max < omega.max() <= omega_max * (1 + 1e-12)
    if case == "straight":  # most steps in the turn terms' series (|omega T| < 1e-3)
        assert np.median(omega) * 4.0 < TURN_SERIES_WT


def test_the_step_is_compiled_when_a_compiler_is_at_hand():
    from solver import compiled

    imm_ct_step.build()
    if compiled.jit_command() is None:
        pytest.skip("no C compiler and no compiled-object cache here")
    assert compiled.is_compiled("imm_ct_ekf") and compiled.is_compiled("imm_ct_converted")
