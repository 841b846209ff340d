"""IMM smoother (``solver.estimation.imm_smoother``) against independent references: the CV Kalman
filter + RTS smoother when only CV can happen or all models are the same, per-model RTS smoothers
when the mode never switches, ``scipy.linalg.expm`` for the switching matrix, the 5-state
coordinated-turn map for the turn transitions; accuracy and mode probabilities on a manoeuvring
track; consistency on tracks drawn from its own model; degenerate inputs; the API."""

import imm_reference
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.stats import chi2
from tracks import held, make_track

from solver import FilterEstimate, Plots, Radar
from solver.estimation import FILTER_NAMES, run_filter
from solver.estimation import imm_smoother as ims
from solver.estimation.cv_rts import run_cv_rts
from solver.estimation.kalman import filter_track, rts_smoother
from solver.estimation.measurements import PolarPlots, SensorPlots
from solver.estimation.models import ct_predict

SIGMA_R, SIGMA_PSI = 120.0, np.deg2rad(0.3)
RADAR = Radar(3 * SIGMA_R, 3 * SIGMA_PSI, range_sigma_m=SIGMA_R, azimuth_sigma_rad=SIGMA_PSI)
# straight, a 2 deg/s right turn of 90 deg, straight, a 2 deg/s left turn of 120 deg, straight
V = 200.0
A_TURN = V * np.deg2rad(2.0)
LEGS = [(300.0, 0.0, 0.0), (45.0, A_TURN, 0.0), (300.0, 0.0, 0.0), (60.0, -A_TURN, 0.0),
        (300.0, 0.0, 0.0)]
START = (-40_000.0, 60_000.0, np.deg2rad(30.0), V)


def noisy_track(seed: int, scan_s: float = 5.0):
    return make_track(LEGS, START, scan_s=scan_s, sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI,
                      drop_in_turns=False, seed=seed)


def rms(states, tr) -> float:
    return float(np.sqrt(np.mean((states.x - tr.x) ** 2 + (states.z - tr.z) ** 2)))


def test_registered_under_its_name():
    assert "imm_smoother" in FILTER_NAMES
    est = run_filter("imm_smoother", noisy_track(0).plots, RADAR)
    assert isinstance(est, FilterEstimate) and est.name == "imm_smoother"
    n = len(est.states)
    assert est.info["model_probabilities"].shape == (n, 3)
    assert est.info["filtered_model_probabilities"].shape == (n, 3)
    assert est.info["filtered"].shape == (n, 4) and est.info["turn_rate"].shape == (n,)
    assert "warning" not in est.info


def test_switching_matrix_is_expm_of_the_generator():
    dt = np.array([0.0, 1e-9, 0.5, 4.8, 19.0, 300.0, 1e6])
    for tau_cv, tau_ct in ((120.0, 40.0), (30.0, 300.0), (np.inf, 40.0), (60.0, np.inf)):
        a, b = 1 / tau_cv, 1 / tau_ct
        G = np.array([[-a, a / 2, a / 2], [b, -b, 0.0], [b, 0.0, -b]])
        Pi = ims.switching_matrices(dt, tau_cv, tau_ct)
        ref = np.array([expm(G * T) for T in dt])
        np.testing.assert_allclose(Pi, ref, atol=1e-12)
        np.testing.assert_allclose(Pi.sum(-1), 1.0, atol=1e-14)
        # the stationary distribution is left invariant
        pi0 = ims.stationary(tau_cv, tau_ct)
        np.testing.assert_allclose(pi0 @ Pi[3], pi0, atol=1e-14)


def test_turn_transitions_match_the_coordinated_turn_map():
    """``Phi`` of the fixed-rate turns moves a state as ``models.ct_predict`` (5-state CT with the
    rate in the state) does, and ``Q`` is the integral of the noise through ``Phi`` (quadrature)."""
    dt = np.array([0.3, 4.8, 19.0, 200.0])
    omega, q = np.deg2rad(2.5), 7.0
    Phi, Q = ims.transitions(dt, 1.0, q, omega)
    x = np.array([1000.0, -2000.0, 150.0, -80.0])
    for k, T in enumerate(dt):
        for m, w in ((1, omega), (2, -omega)):
            f, _ = ct_predict(np.append(x, w), T)
            np.testing.assert_allclose(Phi[k, m] @ x, f[:4], rtol=1e-12, atol=1e-9)
        # CV: constant velocity
        np.testing.assert_allclose(Phi[k, 0] @ x, [x[0] + T * x[2], x[1] + T * x[3], x[2], x[3]])
    # Q(T) = int_0^T Phi(s) G q G^T Phi(s)^T ds, Gauss-Legendre on the turn map
    T = 19.0
    nodes, weights = np.polynomial.legendre.leggauss(40)
    s = 0.5 * T * (nodes + 1)
    Ps = ims.transitions(s, 1.0, q, omega)[0][:, 1, :, 2:]  # Phi(s) G at every node
    ref = 0.5 * T * q * np.einsum("k,kab,kcb->ac", weights, Ps, Ps)
    np.testing.assert_allclose(Q[2, 1], ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("measurement", ["ekf", "converted"])
def test_only_cv_possible_equals_cv_kalman_rts(measurement):
    """CV absorbing (``tau_cv = inf``): the turn models never get probability, and the smoother is
    the CV Kalman filter + RTS smoother of ``cv_rts`` with the same noise density."""
    meas = PolarPlots.from_plots(noisy_track(1).plots, RADAR)
    a = ims.run_imm_smoother(meas, q_cv=20.0, tau_cv=np.inf, measurement=measurement)
    b = run_cv_rts(meas, q=20.0, measurement=measurement)
    np.testing.assert_allclose(a.states.states, b.states.states, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.states.cov, b.states.cov, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(a.info["filtered"], b.info["filtered"], rtol=0, atol=1e-6)
    assert np.all(a.info["model_probabilities"][:, 1:] == 0.0)


def test_identical_models_equal_cv_kalman_rts():
    """Three copies of one CV model with switching among them: a mixture of equal Gaussians is
    that Gaussian, so mixing, moment matching and the pair-wise backward pass must reproduce the
    single-model smoother exactly (while every mode keeps a non-trivial probability)."""
    meas = PolarPlots.from_plots(noisy_track(2).plots, RADAR)
    a = ims.run_imm_smoother(meas, q_cv=15.0, q_ct=15.0, omega_deg=0.0, tau_cv=50.0, tau_ct=20.0)
    b = run_cv_rts(meas, q=15.0)
    np.testing.assert_allclose(a.states.states, b.states.states, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.states.cov, b.states.cov, rtol=1e-9, atol=1e-6)
    assert a.info["model_probabilities"][:, 1:].min() > 0.1


def test_no_switching_gives_each_model_its_own_rts_smoother():
    """With ``Pi = I`` the IMM is a bank of independent filters; the backward pass must give each
    model its own Kalman + RTS smoother (``kalman.filter_track`` / ``kalman.rts_smoother``) and
    keep the final filtered mode probabilities at every time. Without the gate: the IMM leaves
    out a plot that no mode expects, a lone filter one that it does not (the 2 deg/s turn model
    on this track's straight legs)."""
    meas = PolarPlots.from_plots(noisy_track(3).plots, RADAR)
    dt = np.diff(meas.t)
    Phi, Q = ims.transitions(dt, 2.0, 20.0, np.deg2rad(2.0))
    Pi = np.repeat(np.eye(3)[None], dt.size, 0)
    fw = ims.imm_forward(meas, Phi, Q, Pi, np.full(3, 1 / 3), gate=None)
    xf, mu = fw.x, fw.mu
    xs, Ps, mus = ims.imm_backward(fw, Phi, Q)
    x0, P0 = ims._prior(meas)
    for m in range(3):
        rf, rP, rxp, rPp, _, _ = filter_track(x0, P0, Phi[:, m], Q[:, m], meas, (0, 1), "ekf",
                                              gate=None)
        np.testing.assert_allclose(xf[:, m], rf, rtol=0, atol=1e-6)
        rs, rPs = rts_smoother(rf, rP, rxp, rPp, Phi[:, m])
        np.testing.assert_allclose(xs[:, m], rs, rtol=0, atol=1e-6)
        np.testing.assert_allclose(Ps[:, m], rPs, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(mus, np.repeat(mu[-1:], len(meas), 0), atol=1e-12)


def test_smoother_beats_the_forward_imm_and_cv_smoother_on_a_manoeuvring_track():
    fwd, smo, imm, cvr = [], [], [], []
    for seed in range(3):
        tr = noisy_track(seed)
        fwd.append(rms(run_filter("imm_smoother", tr.plots, RADAR, smooth=False).states, tr))
        smo.append(rms(run_filter("imm_smoother", tr.plots, RADAR).states, tr))
        imm.append(rms(run_filter("imm", tr.plots, RADAR).states, tr))
        cvr.append(rms(run_filter("cv_rts", tr.plots, RADAR).states, tr))
    fwd_m, smo_m, imm_m, cvr_m = (float(np.mean(v)) for v in (fwd, smo, imm, cvr))
    assert smo_m < 0.8 * fwd_m and smo_m < 0.8 * imm_m, (smo_m, fwd_m, imm_m)
    assert smo_m < cvr_m, (smo_m, cvr_m)


def test_mode_probabilities_follow_the_turns():
    tr = noisy_track(4)
    est = run_filter("imm_smoother", tr.plots, RADAR)
    mu = est.info["model_probabilities"]
    assert np.all(mu >= 0) and np.allclose(mu.sum(1), 1.0, atol=1e-12)
    t = tr.t
    right = (t > 310) & (t < 340)  # inside the right turn (300-345 s)
    left = (t > 655) & (t < 700)  # inside the left turn (645-705 s)
    straight = ((t > 60) & (t < 280)) | ((t > 400) & (t < 620)) | (t > 780)
    assert mu[right, 1].mean() > 0.6, mu[right].mean(0)
    assert mu[left, 2].mean() > 0.6, mu[left].mean(0)
    assert mu[straight, 0].mean() > 0.6, mu[straight].mean(0)
    # the smoothed turn rate has the turns' signs (clockwise positive)
    assert est.info["turn_rate"][right].mean() > 0 > est.info["turn_rate"][left].mean()


def sample_own_model(rng, t, q_cv, q_ct, omega, tau_cv, tau_ct):
    """A track from the smoother's own model: Markov modes, exact linear transitions."""
    dt = np.diff(t)
    Phi, Q = ims.transitions(dt, q_cv, q_ct, omega)
    Pi = ims.switching_matrices(dt, tau_cv, tau_ct)
    x = np.array([50_000.0, 30_000.0, -120.0, 150.0])
    m = rng.choice(3, p=ims.stationary(tau_cv, tau_ct))
    out = [x]
    for k in range(dt.size):
        m = rng.choice(3, p=Pi[k, m])
        x = Phi[k, m] @ x + rng.multivariate_normal(np.zeros(4), Q[k, m])
        out.append(x)
    return np.array(out)


def test_consistent_on_tracks_from_its_own_model():
    """Mean NEES of the smoothed states near the chi-square band (the IMM smoother is an
    approximation, so a 25 % margin) and 95 % ellipses that hold about 95 % of the truth."""
    rng = np.random.default_rng(7)
    params = {"q_cv": 0.5, "q_ct": 2.0, "omega_deg": 2.5, "tau_cv": 120.0, "tau_ct": 40.0}
    t = np.arange(60) * 5.0
    nees, inside = [], []
    for _ in range(30):
        truth = sample_own_model(rng, t, params["q_cv"], params["q_ct"],
                                 np.deg2rad(params["omega_deg"]), params["tau_cv"],
                                 params["tau_ct"])
        r = np.hypot(truth[:, 0], truth[:, 1]) + rng.normal(0, SIGMA_R, t.size)
        psi = np.arctan2(truth[:, 1], truth[:, 0]) + rng.normal(0, SIGMA_PSI, t.size)
        est = run_filter("imm_smoother", Plots.from_arrays(t, r, psi), RADAR, **params).states
        e = (est.states - truth)[3:]
        nees.append(np.einsum("ki,kij,kj->k", e, np.linalg.inv(est.cov[3:]), e))
        ep = e[:, :2]
        d2 = np.einsum("ki,kij,kj->k", ep, np.linalg.inv(est.cov[3:, :2, :2]), ep)
        inside.append(d2 <= chi2.ppf(0.95, 2))
    m = float(np.mean(nees))
    cover = float(np.mean(inside))
    lo, hi = chi2.ppf(0.025, 4 * 30) / 30, chi2.ppf(0.975, 4 * 30) / 30
    assert 0.75 * lo <= m <= 1.25 * hi, m
    assert 0.90 <= cover <= 0.99, cover


@pytest.mark.parametrize("case", ["one", "two", "gap", "burst", "same_point", "far"])
def test_degenerate_inputs_stay_finite(case):
    t, r, psi = {
        "one": ([0.0], [50_000.0], [0.3]),
        "two": ([0.0, 4.8], [50_000.0, 50_900.0], [0.3, 0.31]),
        "gap": ([0.0, 5.0, 10.0, 86_410.0, 86_415.0], [5e4, 5.1e4, 5.2e4, 9e4, 9.1e4],
                [0.3, 0.3, 0.3, 2.0, 2.0]),
        "burst": ([0.0, 1e-6, 2e-6, 3e-6, 10.0], [5e4, 5e4, 5e4 + 1, 5e4, 5.1e4],
                  [0.3, 0.3, 0.3, 0.3, 0.31]),
        "same_point": (list(np.arange(20) * 5.0), [5e4] * 20, [0.3] * 20),
        "far": ([0.0, 10.0, 20.0, 30.0], [30.0, 400_000.0, 400_100.0, 20.0],
                [3.0, 6.2, 6.2, 0.0]),
    }[case]
    plots = Plots.from_arrays(np.array(t), np.array(r), np.array(psi))
    meas = PolarPlots.from_plots(plots, RADAR)
    for smooth in (True, False):
        est = ims.run_imm_smoother(meas, smooth=smooth)  # directly: no fallback in between
        s = est.states
        assert np.all(np.isfinite(s.states)) and np.all(np.isfinite(s.cov)), case
        assert np.all(np.linalg.eigvalsh(s.cov) > 0), case
        mu = est.info["model_probabilities"]
        assert np.all(np.isfinite(mu)) and np.allclose(mu.sum(1), 1.0), case
    if case == "one":
        np.testing.assert_allclose(est.states.states[0, :2], meas.points()[0])


def test_bad_parameters_raise():
    plots = noisy_track(0).plots
    for kw in ({"q_cv": 0.0}, {"q_ct": -1.0}, {"tau_ct": 0.0}, {"omega_deg": np.nan},
               {"measurement": "ukf"}):
        with pytest.raises(ValueError):
            run_filter("imm_smoother", plots, RADAR, **kw)
    with pytest.raises(TypeError):
        run_filter("imm_smoother", plots, RADAR, q=3.0)


def test_future_mode_likelihood_against_a_pseudo_measurement():
    """When the later plots' information about ``x_{k+1}`` is a linear measurement
    ``z = H x + N(0, I)`` of the first two states (``Ps^-1 = Pp^-1 + H^T H``), the pair likelihood
    is ``N(z; H x^{ij}, H P^{ij} H^T + I)`` in closed form: the backward mode weights must be
    ``W_ij`` times it, normalised over ``i``."""
    rng = np.random.default_rng(3)

    def spd(scale):
        A = rng.normal(size=(4, 4))
        return scale * (A @ A.T + np.eye(4))

    H = np.eye(4)[:2]
    Pp = np.array([spd(2.0) for _ in range(3)])
    xp = rng.normal(size=(3, 4))
    z = rng.normal(size=(3, 2))
    Ps = np.linalg.inv(np.linalg.inv(Pp) + H.T @ H)
    xs = np.einsum("jab,jb->ja", Ps, np.einsum("jab,jb->ja", np.linalg.inv(Pp), xp) + z @ H)
    xpair = xs[None] + rng.normal(size=(3, 3, 4))
    Ppair = np.array([[spd(1.0) for _ in range(3)] for _ in range(3)])
    W = rng.dirichlet(np.ones(3), size=3).T  # columns sum to 1
    white = np.linalg.inv(np.linalg.cholesky(Pp))
    b = imm_reference.future_weights(W, xs, Ps, xp, white, xpair, Ppair)
    lik = np.array([[mvn_pdf(z[j], H @ xpair[i, j], H @ Ppair[i, j] @ H.T + np.eye(2))
                     for j in range(3)] for i in range(3)])
    ref = W * lik / (W * lik).sum(0)
    np.testing.assert_allclose(b, ref, rtol=1e-9, atol=1e-12)


def mvn_pdf(x, mean, cov):
    d = x - mean
    return float(np.exp(-0.5 * d @ np.linalg.solve(cov, d))
                 / np.sqrt(np.linalg.det(2 * np.pi * cov)))


def test_future_mode_likelihood_ignores_negative_information():
    """Where the smoothed covariance exceeds the prediction (the mixture approximations do that),
    the quotient would reward a pair prediction for being far away; those directions carry no
    information: the weights stay finite, and moving a prediction away along them changes
    nothing."""
    Pp = np.repeat((np.eye(4) * 100.0)[None], 3, 0)
    Ps = np.repeat(np.diag([50.0, 50.0, 400.0, 400.0])[None], 3, 0)  # velocities: "negative"
    xs = np.zeros((3, 4))
    xp = np.zeros((3, 4))
    W = np.full((3, 3), 1 / 3)
    Ppair = np.repeat(np.repeat((np.eye(4) * 10.0)[None], 3, 0)[None], 3, 0)
    near = np.zeros((3, 3, 4))
    far = near.copy()
    far[1, :, 2:] = 1e4  # mode 1's predictions far off in velocity
    args = (xs, Ps, xp, np.linalg.inv(np.linalg.cholesky(Pp)))
    b_near = imm_reference.future_weights(W, *args, near, Ppair)
    b_far = imm_reference.future_weights(W, *args, far, Ppair)
    np.testing.assert_allclose(b_near, 1 / 3)
    np.testing.assert_allclose(b_far, b_near)
    far[1, :, :2] = 100.0  # and far off in position, where there is information: less weight
    b_pos = imm_reference.future_weights(W, *args, far, Ppair)
    assert np.all(b_pos[1] < 0.01) and np.allclose(b_pos.sum(0), 1.0)


def test_benchmark_baseline_is_the_smoother_with_its_profile_tuning():
    """``imm-smoother`` in the benchmark is a baseline (the report's strongest-baseline column)
    running this smoother with the per-profile tuning frozen in ``baselines.TUNED``."""
    from dataclasses import asdict

    from benchmarks.baselines import TUNED
    from benchmarks.estimators import registry

    reg = registry()
    assert reg["imm-smoother"].kind == reg["imm-smoother-kim"].kind == "baseline"
    assert reg["imm-smoother+alt"].with_altitude
    assert "filter-imm_smoother" in reg
    tr = noisy_track(5)
    got = reg["imm-smoother"].run(tr.plots, RADAR, "ssr").states
    tuning = asdict(TUNED["ssr"].imm_smoother)
    ref = run_filter("imm_smoother", tr.plots, RADAR, **tuning).states
    np.testing.assert_array_equal(got.states, ref.states)
    assert tuning["future_modes"] and not TUNED["ssr"].imm_smoother_kim.future_modes



def mixed_sensor_plots(polar: PolarPlots, simultaneous: bool = False) -> SensorPlots:
    """Every third plot a position fix (ADS-B-like, a full covariance); with ``simultaneous``
    every fifth radar plot also repeated at its own time (a zero-length step)."""
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
                       n_sensors=2, polar=~fix[rows], d=np.where(fix, np.nan, polar.d)[rows],
                       sigma_d=np.where(fix, np.nan, polar.sigma_d)[rows],
                       psi=np.where(fix, np.nan, polar.psi)[rows],
                       sigma_psi=np.where(fix, np.nan, polar.sigma_psi)[rows],
                       centre=centre[rows], cov=cov[rows])


@pytest.mark.parametrize("case", ["ekf", "converted", "sensors", "kim", "gap"])
def test_compiled_passes_equal_the_numpy_reference(case):
    """The passes' steps as compiled CasADi functions (``imm_step``) give what the plain-numpy
    passes they replaced give (``tests/imm_reference.py``: one ``kalman.position_update`` per
    mode, the future-mode weights as tested above): polar plots (EKF and converted), polar plots
    mixed with position fixes (``SensorPlots``), Kim's weights, a long gap after which the EKF
    update iterates."""
    measurement, future = ("converted" if case == "converted" else "ekf"), case != "kim"
    if case == "sensors":
        meas = mixed_sensor_plots(PolarPlots.from_plots(noisy_track(1, scan_s=4.0).plots, RADAR))
    elif case == "gap":
        meas = held(PolarPlots.from_plots(noisy_track(1, scan_s=4.0).plots, RADAR))
    else:
        meas = PolarPlots.from_plots(noisy_track(1, scan_s=4.0).plots, RADAR)
    dt = np.diff(meas.t)
    Phi, Q = ims.transitions(dt, ims.Q_CV, ims.Q_CT, np.deg2rad(ims.OMEGA_DEG))
    Pi = ims.switching_matrices(dt, ims.TAU_CV, ims.TAU_CT)
    mu0 = ims.stationary(ims.TAU_CV, ims.TAU_CT)
    got = ims.imm_forward(meas, Phi, Q, Pi, mu0, measurement)
    want = imm_reference.imm_forward(meas, Phi, Q, Pi, mu0, measurement)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(b).max()))
    got_s = ims.imm_backward(got, Phi, Q, future)
    want_s = imm_reference.imm_backward(want, Phi, Q, future)
    for a, b in zip(got_s, want_s, strict=True):
        assert np.isfinite(a).all()
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-8 * max(1.0, np.abs(b).max()))


def test_threads_share_the_compiled_steps_safely():
    """The compiled steps are built once per process and called through a buffer per pass:
    smoothing different tracks on four threads at once gives each track's sequential answer."""
    from concurrent.futures import ThreadPoolExecutor

    tracks = [noisy_track(seed, scan_s=scan).plots for seed, scan in ((1, 4.0), (2, 5.0), (3, 8.0))]
    alone = [run_filter("imm_smoother", p, RADAR).states.states for p in tracks]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda p: run_filter("imm_smoother", p, RADAR).states.states,
                                 tracks * 4))
    for a, b in zip(alone * 4, together, strict=True):
        np.testing.assert_array_equal(a, b)
