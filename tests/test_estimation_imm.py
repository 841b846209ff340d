"""The causal IMM (``solver.estimation.imm``) with its step compiled (``imm_ct_step``) against
the plain-numpy filter it replaced (``tests/imm_reference.py``): polar plots (EKF and
converted), polar plots mixed with position fixes and simultaneous plots (several sensors),
long scans that push the turn rate to its bound, and a track flown at a turn rate of zero
(the turn terms' series)."""

import imm_reference
import numpy as np
import pytest
from tracks import make_track

from solver import Radar
from solver.estimation import imm_ct_step
from solver.estimation.imm import OMEGA_MAX, run_imm
from solver.estimation.measurements import PolarPlots, SensorPlots

SIGMA_R, SIGMA_PSI = 120.0, np.deg2rad(0.3)
RADAR = Radar(3 * SIGMA_R, 3 * SIGMA_PSI, range_sigma_m=SIGMA_R, azimuth_sigma_rad=SIGMA_PSI)
V = 200.0
A_TURN = V * np.deg2rad(2.0)
LEGS = [(300.0, 0.0, 0.0), (45.0, A_TURN, 0.0), (300.0, 0.0, 0.0), (60.0, -A_TURN, 0.0),
        (300.0, 0.0, 0.0)]
START = (-40_000.0, 60_000.0, np.deg2rad(30.0), V)


def _polar(seed: int, scan_s: float = 4.0, legs=LEGS) -> PolarPlots:
    tr = make_track(legs, START, scan_s=scan_s, sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI,
                    drop_in_turns=False, seed=seed)
    return PolarPlots.from_plots(tr.plots, RADAR)


def _sensors(polar: PolarPlots, simultaneous: bool) -> SensorPlots:
    """Every third plot a position fix (ADS-B-like, a full covariance); with ``simultaneous``
    every fifth plot also repeated at its own time by a second radar (a zero-length step)."""
    n = len(polar)
    fix = np.arange(n) % 3 == 2
    centre, cov = polar.points(), polar.converted_cov()
    rng = np.random.default_rng(4)
    L = rng.normal(0, 20, (n, 2, 2))
    cov[fix] = (L @ np.swapaxes(L, -1, -2) + 100 * np.eye(2))[fix]
    rows = np.arange(n)
    if simultaneous:
        rows = np.sort(np.concatenate([rows, rows[(rows % 5 == 0) & ~fix]]))
    return SensorPlots(t=polar.t[rows], rows=np.arange(rows.size), sensor=fix[rows].astype(int),
                       n_sensors=2, polar=~fix[rows],
                       d=np.where(fix, np.nan, polar.d)[rows],
                       sigma_d=np.where(fix, np.nan, polar.sigma_d)[rows],
                       psi=np.where(fix, np.nan, polar.psi)[rows],
                       sigma_psi=np.where(fix, np.nan, polar.sigma_psi)[rows],
                       centre=centre[rows], cov=cov[rows])


@pytest.mark.parametrize("case", ["ekf", "converted", "sensors", "simultaneous", "long_scans",
                                  "bound", "straight"])
def test_compiled_step_equals_the_numpy_reference(case):
    measurement = "converted" if case == "converted" else "ekf"
    omega_max = np.deg2rad(0.5) if case == "bound" else OMEGA_MAX
    if case in ("sensors", "simultaneous"):
        meas = _sensors(_polar(1), simultaneous=case == "simultaneous")
    elif case == "long_scans":  # 19-s scans (the bound keeps omega T below pi)
        meas = _polar(2, scan_s=19.0)
    elif case == "straight":  # no turn: omega T stays in the series' range
        meas = _polar(3, legs=[(900.0, 0.0, 0.0)])
    else:
        meas = _polar(1)
    got = run_imm(meas, measurement=measurement, omega_max=omega_max)
    want = imm_reference.run_imm(meas, measurement=measurement, omega_max=omega_max)
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
        assert np.median(omega) * 4.0 < imm_ct_step.SERIES_WT


def test_the_step_is_compiled_when_a_compiler_is_at_hand():
    from solver import compiled

    imm_ct_step.build()
    if compiled.jit_command() is None:
        pytest.skip("no C compiler and no compiled-object cache here")
    assert compiled.is_compiled("imm_ct_ekf") and compiled.is_compiled("imm_ct_converted")
