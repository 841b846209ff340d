"""Baselines users run today, from the libraries they know, on the product's plots.

Measurements: every plot is converted to a Cartesian position (the plot point: ground range if the
altitude is known, else the slant range, along the azimuth) with its converted covariance
``B^2 e_r e_r^T + A^2 e_c e_c^T``, ``B = sigma_r r / d`` along the ray and ``A = sigma_psi d``
across it (``solver.geometry.statistical_ellipses``). A linear measurement model keeps the
Kalman/RTS recursion exact, which is why it is preferred over Stone Soup's
``CartesianToBearingRange`` EKF (at these ranges the conversion bias ``d (1 - e^{-sigma_psi^2/2})``
is below 10 m).

- ``ss_cv_kf`` / ``ss_cv_rts``: Stone Soup nearly-constant-velocity model (``ConstantVelocity``
  per axis, white-acceleration spectral density ``q`` m^2/s^3), ``KalmanPredictor``,
  ``KalmanUpdater``, and ``KalmanSmoother`` (Rauch-Tung-Striebel) for the smoothed track.
- ``fp_imm``: Stone Soup 1.9 has no IMM, so FilterPy's ``IMMEstimator`` mixes two filters on the
  state ``(x, vx, z, vz, omega)``: nearly constant velocity (``omega`` held at 0) and a coordinated
  turn with unknown rate (EKF prediction, ``omega`` a random walk).
- ``imm_smoother``: the strongest smoother a surveillance engineer can build from the textbook,
  and neither library has one, so it is the product's own ``solver.estimation.imm_smoother`` (IMM
  of constant velocity and right/left coordinated turns, EKF polar update, backward pass per mode
  pair) with the per-profile tuning below instead of the product's single default.

Both start from a diffuse prior updated with the first plot (velocity 0 +- 300 m/s per axis).
Tuning values per profile come from ``python -m benchmarks.tune`` (a grid search on the dev set,
see :data:`TUNED`) and are frozen here.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from datetime import datetime, timedelta

import numpy as np
from filterpy.kalman import IMMEstimator, KalmanFilter

from solver.geometry import statistical_ellipses
from solver.inputs import FloatArray, Plots, Radar
from solver.results import StateSeries

EPOCH = datetime(2000, 1, 1)


@dataclass(frozen=True)
class ImmTuning:
    """IMM tuning: CV and CT acceleration densities (m^2/s^3), turn-rate random walk
    (rad^2/s^3), mean sojourn time in each mode (s)."""

    q_cv: float = 1.0
    q_ct: float = 10.0
    q_omega: float = 1e-6
    sojourn_s: float = 120.0


@dataclass(frozen=True)
class ImmSmootherTuning:
    """IMM smoother tuning (``solver.estimation.imm_smoother`` parameters): CV and turn
    white-acceleration densities (m^2/s^3), the turn models' rate (deg/s), mean sojourn times in
    CV and in a turn (s); ``future_modes=False``: Kim's backward mode weights (faster, less
    accurate). Defaults: the product's."""

    q_cv: float = 3.0
    q_ct: float = 30.0
    omega_deg: float = 1.0
    tau_cv: float = 600.0
    tau_ct: float = 60.0
    future_modes: bool = True


@dataclass(frozen=True)
class Tuning:
    """Frozen tuning of the baselines for one radar profile: white-acceleration densities
    ``q`` (m^2/s^3) of the CV filter and of the CV smoother (tuned separately: the smoother
    affords a stiffer model), the IMM's and the IMM smoother's."""

    q_kf: float = 30.0
    q_rts: float = 30.0
    imm: ImmTuning = ImmTuning()
    imm_smoother: ImmSmootherTuning = ImmSmootherTuning()
    imm_smoother_kim: ImmSmootherTuning = ImmSmootherTuning(future_modes=False)


# Frozen by `python -m benchmarks.tune` (dev set: the six ADS-B tracks; see the report).
TUNED: dict[str, Tuning] = {
    "seed000": Tuning(q_kf=30, q_rts=30, imm=ImmTuning(q_cv=0.3, q_ct=30.0, q_omega=1e-06,
                                                       sojourn_s=300.0)),
    "seed001": Tuning(q_kf=30, q_rts=30, imm=ImmTuning(q_cv=0.3, q_ct=100.0, q_omega=1e-05,
                                                       sojourn_s=300.0)),
    "ssr": Tuning(q_kf=30, q_rts=10, imm=ImmTuning(q_cv=0.3, q_ct=10.0, q_omega=1e-05,
                                                   sojourn_s=60.0)),
}
# Frozen by `python -m benchmarks.tune imm_smoother` (+ `--fine`, `--kim`): each profile's best
# point over the stages (results/tuning_imm_smoother*.json, dev seeds 100 and 101).
_IMM_SMOOTHER = {"seed000": ImmSmootherTuning(3.0, 30.0, 1.0, 600.0, 60.0),
                 "seed001": ImmSmootherTuning(3.0, 30.0, 1.0, 600.0, 60.0),
                 "ssr": ImmSmootherTuning(1.0, 10.0, 1.0, 200.0, 60.0)}
_IMM_SMOOTHER_KIM = {"seed000": ImmSmootherTuning(10.0, 30.0, 2.0, 200.0, 60.0, False),
                     "seed001": ImmSmootherTuning(10.0, 30.0, 2.0, 200.0, 60.0, False),
                     "ssr": ImmSmootherTuning(3.0, 10.0, 1.0, 200.0, 60.0, False)}
TUNED = {p: replace(t, imm_smoother=_IMM_SMOOTHER[p], imm_smoother_kim=_IMM_SMOOTHER_KIM[p])
         for p, t in TUNED.items()}


def converted_measurements(plots: Plots, radar: Radar) -> tuple[FloatArray, FloatArray]:
    """Plot points ``(n, 2)`` as ``(x, z)`` and their converted covariances ``(n, 2, 2)``."""
    e = statistical_ellipses(plots, radar)
    c, s = np.cos(e.psi), np.sin(e.psi)
    er = np.stack([c, s], axis=1)
    ec = np.stack([-s, c], axis=1)
    cov = (e.B**2)[:, None, None] * er[:, :, None] * er[:, None, :] \
        + (e.A**2)[:, None, None] * ec[:, :, None] * ec[:, None, :]
    return np.column_stack([e.cx, e.cz]), cov


V_PRIOR = 300.0  # m/s: standard deviation of the velocity prior (about v_max of the bounds)
P_PRIOR = 1e5  # m: standard deviation of the position prior (diffuse; the first plot decides)


def _start(z: FloatArray, R: FloatArray) -> tuple[FloatArray, FloatArray]:
    """State ``(x, vx, z, vz)`` at the first plot and its covariance after that plot: position
    the first plot point with its converted covariance, velocity 0 +- ``V_PRIOR`` per axis (a
    weak prior, so each plot is used exactly once)."""
    x0 = np.array([z[0, 0], 0.0, z[0, 1], 0.0])
    P0 = np.diag([0.0, V_PRIOR**2, 0.0, V_PRIOR**2])
    P0[np.ix_([0, 2], [0, 2])] = R[0]
    return x0, P0


def prior(z: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Diffuse prior at the first plot's time, before its update: centred on the first plot,
    ``P_PRIOR`` on positions, ``V_PRIOR`` on velocities."""
    return (np.array([z[0, 0], 0.0, z[0, 1], 0.0]),
            np.diag([P_PRIOR**2, V_PRIOR**2, P_PRIOR**2, V_PRIOR**2]))


def _series(t: FloatArray, means: FloatArray, covs: FloatArray) -> StateSeries:
    """StateSeries from ``(x, vx, z, vz)``-ordered means and covariances."""
    order = [0, 2, 1, 3]
    return StateSeries.from_states(t, means[:, order], covs[:, order][:, :, order])


def stonesoup_cv(plots: Plots, radar: Radar, q: float = 30.0,
                 smooth: bool = True) -> StateSeries:
    """Stone Soup CV Kalman filter (``smooth=False``) or its RTS smoother on converted plots."""
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantVelocity,
    )
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.smoother.kalman import KalmanSmoother
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.prediction import GaussianStatePrediction
    from stonesoup.types.track import Track
    from stonesoup.updater.kalman import KalmanUpdater

    t = plots.t
    z, R = converted_measurements(plots, radar)
    transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])
    predictor = KalmanPredictor(transition)
    updater = KalmanUpdater(measurement_model=None)
    x0, P0 = prior(z)
    state = GaussianStatePrediction(x0.reshape(-1, 1), P0,
                                    timestamp=EPOCH + timedelta(seconds=t[0]))
    track = Track()
    for i in range(len(t)):
        model = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=R[i])
        det = Detection(z[i].reshape(-1, 1), timestamp=EPOCH + timedelta(seconds=t[i]),
                        measurement_model=model)
        prediction = state if i == 0 else predictor.predict(state, timestamp=det.timestamp)
        state = updater.update(SingleHypothesis(prediction, det))
        track.append(state)
    if smooth and len(t) > 1:
        track = KalmanSmoother(transition).smooth(track)
    means = np.array([np.asarray(s.state_vector, dtype=float).ravel() for s in track])
    covs = np.array([np.asarray(s.covar, dtype=float) for s in track])
    return _series(t, means, covs)


def _cv_matrices(dt: float, q: float) -> tuple[FloatArray, FloatArray]:
    """Transition and process noise of one axis of the white-acceleration CV model."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return F, Q


class _ImmCv(KalmanFilter):
    """CV model on ``(x, vx, z, vz, omega)``; ``omega`` is reset to 0 (nearly zero variance)."""

    def __init__(self, q: float):
        super().__init__(dim_x=5, dim_z=2)
        self.q = q
        self.H = np.array([[1.0, 0, 0, 0, 0], [0, 0, 1.0, 0, 0]])
        self.dt = 1.0

    def predict(self, u=None, B=None, F=None, Q=None):
        Fa, Qa = _cv_matrices(self.dt, self.q)
        F5 = np.zeros((5, 5))
        Q5 = np.zeros((5, 5))
        for k in (0, 2):
            F5[k:k + 2, k:k + 2] = Fa
            Q5[k:k + 2, k:k + 2] = Qa
        Q5[4, 4] = 1e-12
        super().predict(F=F5, Q=Q5)


class _ImmCt(KalmanFilter):
    """Coordinated turn with unknown rate ``omega`` (clockwise positive), EKF prediction:
    ``vx' = -omega vz``, ``vz' = omega vx``; white acceleration ``q`` and rate random walk."""

    def __init__(self, q: float, q_omega: float):
        super().__init__(dim_x=5, dim_z=2)
        self.q, self.q_omega = q, q_omega
        self.H = np.array([[1.0, 0, 0, 0, 0], [0, 0, 1.0, 0, 0]])
        self.dt = 1.0

    def predict(self, u=None, B=None, F=None, Q=None):
        dt = self.dt
        x, vx, z, vz, w = self.x.ravel()
        wt = w * dt
        if abs(wt) < 1e-6:
            s_w, c_w = dt * (1 - wt * wt / 6), dt * wt / 2  # sin(wt)/w, (1-cos wt)/w
            ds, dc = -dt * dt * wt / 3, dt * dt / 2          # d/dw of the two
        else:
            s_w, c_w = np.sin(wt) / w, (1 - np.cos(wt)) / w
            ds = (dt * np.cos(wt) - s_w) / w
            dc = (dt * np.sin(wt) - c_w) / w
        cw, sw = np.cos(wt), np.sin(wt)
        nx = x + s_w * vx - c_w * vz
        nz = z + c_w * vx + s_w * vz
        nvx = cw * vx - sw * vz
        nvz = sw * vx + cw * vz
        J = np.eye(5)
        J[0, 1], J[0, 3], J[0, 4] = s_w, -c_w, ds * vx - dc * vz
        J[2, 1], J[2, 3], J[2, 4] = c_w, s_w, dc * vx + ds * vz
        J[1, 1], J[1, 3], J[1, 4] = cw, -sw, dt * (-sw * vx - cw * vz)
        J[3, 1], J[3, 3], J[3, 4] = sw, cw, dt * (cw * vx - sw * vz)
        _, Qa = _cv_matrices(dt, self.q)
        Q5 = np.zeros((5, 5))
        for k in (0, 2):
            Q5[k:k + 2, k:k + 2] = Qa
        Q5[4, 4] = self.q_omega * dt
        self.x = np.array([nx, nvx, nz, nvz, w]).reshape(-1, 1)
        self.P = J @ self.P @ J.T + Q5
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()


def filterpy_imm(plots: Plots, radar: Radar, tuning: ImmTuning | None = None) -> StateSeries:
    """FilterPy IMM (CV + coordinated turn) on converted plots; Markov switching with mean
    sojourn ``tuning.sojourn_s`` seconds, re-evaluated for every step's ``dt``."""
    tuning = tuning or ImmTuning()
    t = plots.t
    z, R = converted_measurements(plots, radar)
    x0, P0 = _start(z, R)
    filters = [_ImmCv(tuning.q_cv), _ImmCt(tuning.q_ct, tuning.q_omega)]
    for f in filters:
        f.x = np.append(x0, 0.0).reshape(-1, 1)
        f.P = np.zeros((5, 5))
        f.P[:4, :4] = P0
        f.P[4, 4] = np.deg2rad(3.0) ** 2
        f.R = R[0]
    imm = IMMEstimator(filters, np.array([0.8, 0.2]), _markov(1.0, tuning.sojourn_s))
    means = np.empty((len(t), 5))
    covs = np.empty((len(t), 5, 5))
    means[0], covs[0] = imm.x.ravel(), imm.P
    for i in range(1, len(t)):
        dt = t[i] - t[i - 1]
        imm.M = _markov(dt, tuning.sojourn_s)
        imm._compute_mixing_probabilities()  # mixing for this step's dt (FilterPy keeps M fixed)
        for f in filters:
            f.dt = dt
            f.R = R[i]
        imm.predict()
        imm.update(z[i].reshape(-1, 1))
        means[i], covs[i] = imm.x.ravel(), imm.P
    return _series(t, means[:, :4], covs[:, :4, :4])


def imm_smoother(plots: Plots, radar: Radar, tuning: ImmSmootherTuning | None = None
                 ) -> StateSeries:
    """The product's IMM fixed-interval smoother with a baseline's tuning (per profile)."""
    from solver.estimation import run_filter

    return run_filter("imm_smoother", plots, radar, **asdict(tuning or ImmSmootherTuning())).states


def _markov(dt: float, sojourn_s: float) -> FloatArray:
    """Two-mode switching matrix over ``dt`` for exponential sojourn times."""
    p = 1 - np.exp(-dt / sojourn_s)
    return np.array([[1 - p, p], [p, 1 - p]])


def raw_plots(plots: Plots, radar: Radar) -> StateSeries:
    """The plot points themselves (no velocity: NaN), the floor every estimator must beat."""
    z, R = converted_measurements(plots, radar)
    n = len(plots)
    cov = np.zeros((n, 4, 4))
    cov[:, :2, :2] = R
    cov[:, 2:, 2:] = np.nan
    nan = np.full(n, np.nan)
    return StateSeries(plots.t.copy(), z[:, 0], z[:, 1], nan, nan.copy(), cov)
