"""Several sensors, one trajectory (issue 15's benchmarks): the real ADS-B truths on the real earth,
simulated through the curved earth by every sensor of a profile, and every estimator on the same
plots.

    python -m benchmarks.multisensor                # full run, seeds 0..2 -> results/multisensor.md
    python -m benchmarks.multisensor --seeds 2      # held-out seeds 0, 1
    python -m benchmarks.multisensor --quick        # < 2 min: 2 tracks cut to 1200 s, 1 seed
    python -m benchmarks.multisensor --tune         # the anchor's q on the dev seeds 100, 101

Placement and simulation: ``benchmarks/earth.py``. Profiles: :data:`MULTI_PROFILES`.

Estimators (names as in the report), all on the same :class:`solver.plots.PlotTable`:

- ``ss-ekf-rts`` (the anchor): Stone Soup's nearly-constant-velocity EKF + RTS smoother fed every
  sensor's plots at their own times, each with its own measurement model: a radar's
  ``CartesianToBearingRange`` with ``translation_offset`` at the site's position in the plane, a
  position sensor's ``LinearGaussian``. A radar plot enters as the plane bearing and plane
  distance from the site of the point the plot places the aircraft at through the curved earth
  (PROJ, :meth:`RadarSensor.positions`) at its Mode C height or, without one, at the site's
  height (the product's own convention); the plane bearing is the radar's azimuth turned by the
  meridian convergence at the site (:meth:`LocalFrame.north_azimuth`) up to the geodesic's
  curvature in the plane, which the exact placement includes. Noise: ``sigma_psi`` in bearing,
  ``sigma_r r / d`` in plane distance. White-acceleration density ``q`` tuned per profile on the
  dev seeds (:data:`TUNED_Q`, ``--tune``). The update uses the Joseph form of the covariance
  (``use_joseph_cov``): the plain ``P - K S K^T`` loses the covariance to cancellation when
  ``S`` mixes radians and metres with precise plots (tested on a noise-free track).
- ``recon`` (the product): ``solver.reconstruct.reconstruct(table)`` over all sensors.
- ``recon-alone[<id>]`` / ``ss-ekf-rts-alone[<id>]``: the same on one sensor's plots only, scored
  on that sensor's plot times; ``recon@<id>`` / ``ss-ekf-rts@<id>``: the fused estimates scored
  at that sensor's plot times (the single-radar targets compare on the same plots).
- ``filter-<name>``: the product's recursive filters on the whole table
  (``solver.estimation.run_filter(name, table)``; seed 004's fusion filters among them once they
  exist), and on the ``seed004`` profile ``filter-alpha_beta-alone[<id>]``: seed 004's own
  filter on each source alone, for its ordering target.

Metrics (``metrics.py``) against the truth at every plot's time stamp in the table's plane, pooled
over tracks and seeds; registration: each estimated offset against the simulated one within its
reported 3 sigma.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import shlex
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

from solver.inputs import FloatArray
from solver.plots import PlotTable
from solver.results import StateSeries
from solver.sensors import PositionSensor, RadarSensor

from .baselines import EPOCH, prior
from .earth import BiasDraw, MultiTrack, SensorSpec, place, simulate_multi, sub_table
from .metrics import RunErrors, errors, rms, summarize
from .profiles import PROFILES, RadarProfile
from .run import RESULTS_DIR, environment, publish
from .truth import SYNTHETIC, truth_names

DEV_SEEDS = (100, 101)
Q_GRID = (1.0, 3.0, 10.0, 30.0, 100.0)
QUICK_TRUTHS = ("calibration__vienna", "calibration__kiruna")
QUICK_T_MAX = 1200.0


# ------------------------------------------------------------------------------ profiles


def radar_spec(id: str, profile: RadarProfile, slot: int, **kw: Any) -> SensorSpec:
    """A radar of one of the single-radar profiles (``profiles.PROFILES``) at site ``slot``."""
    base = dict(id=id, kind="radar", scan_s=profile.scan_s, pd=profile.pd, slot=slot,
                sigma_r=profile.sigma_r, sigma_psi=profile.sigma_psi, eps_r=profile.eps_r,
                eps_psi=profile.eps_psi, h_max=profile.h_max, alpha_max=profile.alpha_max)
    return SensorSpec(**{**base, **kw})


@dataclass(frozen=True)
class MultiProfile:
    """Sensors of one multi-sensor setting; ``similar``: two radars of similar quality overlap
    (issue 15's 0.65x target applies)."""

    name: str
    description: str
    sensors: tuple[SensorSpec, ...]
    similar: bool = False

    @property
    def radars(self) -> tuple[SensorSpec, ...]:
        return tuple(s for s in self.sensors if s.kind == "radar")

    @property
    def without_mode_c(self) -> bool:
        """At least two radars and one of them without Mode C (the 'never worse' target)."""
        return len(self.radars) >= 2 and any(not s.mode_c for s in self.radars)

    @property
    def registration(self) -> bool:
        return any(s.estimate_bias for s in self.sensors)


P000, P001, PSSR = PROFILES["seed000"], PROFILES["seed001"], PROFILES["ssr"]
REG_BIAS = BiasDraw(range_m=(50.0, 200.0), azimuth_deg=(0.1, 0.3))

MULTI_PROFILES: dict[str, MultiProfile] = {p.name: p for p in (
    MultiProfile("2x-seed001", "two radars of seed 001's kind (10 s, 400 m, 0.01 rad) at two "
                 "sites, no altitude", (radar_spec("R1", P001, 0), radar_spec("R2", P001, 1)),
                 similar=True),
    MultiProfile("seed000+ssr", "seed 000's radar (19 s, 167 m, 0.5 deg, Pd 0.9, no altitude) "
                 "and an SSR with Mode C (4.8 s, 50 m, 0.08 deg)",
                 (radar_spec("PSR", P000, 0), radar_spec("SSR", PSSR, 1, mode_c=True))),
    MultiProfile("2x-ssr", "two SSRs without Mode C at two sites",
                 (radar_spec("SSR1", PSSR, 0), radar_spec("SSR2", PSSR, 1)), similar=True),
    MultiProfile("2x-ssr+modec", "two SSRs with Mode C at two sites",
                 (radar_spec("SSR1", PSSR, 0, mode_c=True),
                  radar_spec("SSR2", PSSR, 1, mode_c=True)), similar=True),
    MultiProfile("seed004", "seed 004's setting: an accurate slow source (SSR, 10 s, Mode C) and "
                 "a coarse source ten times faster (position fixes every 1 s, 300 m per axis, "
                 "Pd 0.95)",
                 (radar_spec("ACC", PSSR, 0, scan_s=10.0, mode_c=True),
                  SensorSpec("FAST", "position", scan_s=1.0, pd=0.95, sigma_pos=300.0))),
    MultiProfile("radar+adsb", "seed 000's radar and ADS-B (every 2 s, 30 m per axis, Pd 0.95) "
                 "with outages (1.5 per hour, 200-900 s each)",
                 (radar_spec("PSR", P000, 0),
                  SensorSpec("ADSB", "position", scan_s=2.0, pd=0.95, sigma_pos=30.0,
                             gaps_per_hour=1.5, gap_s=(200.0, 900.0)))),
    MultiProfile("registration", "two SSRs with Mode C, each with a range offset of 50-200 m and "
                 "an azimuth offset of 0.1-0.3 deg (random signs, drawn per run), estimated",
                 (radar_spec("SSR1", PSSR, 0, mode_c=True, bias=REG_BIAS, estimate_bias=True),
                  radar_spec("SSR2", PSSR, 1, mode_c=True, bias=REG_BIAS, estimate_bias=True)),
                 similar=True),
)}

# Frozen by `python -m benchmarks.multisensor --tune` (dev seeds 100, 101, the six ADS-B tracks;
# results/multisensor_tuning.json): the anchor's white-acceleration density q (m^2/s^3), the
# pooled-RMS minimum over Q_GRID (registration's offsets were then drawn from the plots' own
# stream, an earlier version of earth.py; its scores are flat in q: 167.7-170.6 m).
TUNED_Q: dict[str, float] = {"2x-seed001": 30.0, "seed000+ssr": 10.0, "2x-ssr": 3.0,
                             "2x-ssr+modec": 3.0, "seed004": 10.0, "radar+adsb": 30.0,
                             "registration": 3.0}
DEFAULT_Q = 10.0


# ------------------------------------------------------------------------------ the anchor


def _radar_measurements(table: PlotTable, k: int, rows: np.ndarray
                        ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray,
                                   tuple[float, float]]:
    """Plane bearing and distance from the site of radar ``k``'s plots (placed through the curved
    earth at the Mode C height, else at the site's height), their sigmas, and the site's plane
    position."""
    sensor = table.sensors[k]
    assert isinstance(sensor, RadarSensor) and table.frame is not None
    frame = table.frame
    lat_s, lon_s, h_s = sensor.site_in(frame)
    xs, zs = (float(v[0]) for v in frame.to_plane(np.array([lat_s]), np.array([lon_s])))
    r, psi = table.range_m[rows], table.azimuth_rad[rows]
    h = np.where(np.isfinite(table.altitude_m[rows]), table.altitude_m[rows], h_s)
    x, z = sensor.positions(frame, r, psi, h)
    bearing = np.arctan2(z - zs, x - xs)
    dist = np.hypot(x - xs, z - zs)
    ground = np.sqrt(np.maximum(r**2 - (h - h_s) ** 2, 1.0))
    sig_d = sensor.sigma_r * r / np.maximum(ground, 0.1 * r)
    sig_b = np.full(rows.size, sensor.sigma_psi)
    return bearing, dist, sig_b, sig_d, (xs, zs)


def stonesoup_fused(table: PlotTable, q: float, smooth: bool = True) -> StateSeries:
    """The anchor (module docstring): Stone Soup CV EKF (+ RTS smoother) over every sensor's
    plots in time order; states in table row order."""
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.measurement.nonlinear import CartesianToBearingRange
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantVelocity,
    )
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.smoother.kalman import KalmanSmoother
    from stonesoup.types.angle import Bearing
    from stonesoup.types.array import StateVector
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.prediction import GaussianStatePrediction
    from stonesoup.types.track import Track
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    assert table.frame is not None
    n = len(table)
    points = np.zeros((n, 2))
    models: list[Any] = [None] * n
    vectors: list[Any] = [None] * n
    for k, s in enumerate(table.sensors):
        rows = np.flatnonzero(table.sensor == k)
        if isinstance(s, RadarSensor):
            b, d, sb, sd, (xs, zs) = _radar_measurements(table, k, rows)
            offset = StateVector([xs, zs])
            for j, i in enumerate(rows):
                models[i] = CartesianToBearingRange(
                    ndim_state=4, mapping=(0, 2), noise_covar=np.diag([sb[j] ** 2, sd[j] ** 2]),
                    translation_offset=offset)
                vectors[i] = StateVector([Bearing(b[j]), d[j]])
            points[rows] = np.column_stack([xs + d * np.cos(b), zs + d * np.sin(b)])
        else:
            assert isinstance(s, PositionSensor)
            x, z = table.frame.to_plane(table.lat_deg[rows], table.lon_deg[rows])
            model = LinearGaussian(ndim_state=4, mapping=(0, 2),
                                   noise_covar=np.eye(2) * s.position_sigma_m**2)
            for j, i in enumerate(rows):
                models[i] = model
                vectors[i] = StateVector([x[j], z[j]])
            points[rows] = np.column_stack([x, z])
    order = table.time_order()
    transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])
    predictor = KalmanPredictor(transition)
    updater = ExtendedKalmanUpdater(measurement_model=None, use_joseph_cov=True)
    x0, P0 = prior(points[order[:1]])
    t = table.t
    state: Any = GaussianStatePrediction(x0.reshape(-1, 1), P0,
                                         timestamp=EPOCH + timedelta(seconds=float(t[order[0]])))
    track = Track()
    for step, i in enumerate(order):
        det = Detection(vectors[i], timestamp=EPOCH + timedelta(seconds=float(t[i])),
                        measurement_model=models[i])
        prediction = state if step == 0 else predictor.predict(state, timestamp=det.timestamp)
        state = updater.update(SingleHypothesis(prediction, det))
        track.append(state)
    if smooth and n > 1:
        track = KalmanSmoother(transition).smooth(track)
    means = np.empty((n, 4))
    covs = np.empty((n, 4, 4))
    for s_, i in zip(track, order, strict=True):
        means[i] = np.asarray(s_.state_vector, dtype=float).ravel()
        covs[i] = np.asarray(s_.covar, dtype=float)
    perm = [0, 2, 1, 3]  # (x, vx, z, vz) -> (x, z, vx, vz)
    return StateSeries.from_states(t.copy(), means[:, perm], covs[:, perm][:, :, perm])


# ------------------------------------------------------------------------------ estimators


@dataclass
class Output:
    """An estimator's states at the rows it was given, and the per-sensor report if any."""

    states: StateSeries
    sensors: list[Any] = field(default_factory=list)


@dataclass(frozen=True)
class MultiEstimator:
    """``run(table, profile) -> Output`` on the rows ``rows(track)`` of a simulated run (None:
    all of them)."""

    name: str
    kind: str
    run: Callable[[PlotTable, str], Output] = field(compare=False)
    sensor: str | None = None

    def rows(self, track: MultiTrack) -> np.ndarray | None:
        return None if self.sensor is None else track.rows_of(self.sensor)


def _anchor(table: PlotTable, profile: str) -> Output:
    return Output(stonesoup_fused(table, TUNED_Q.get(profile, DEFAULT_Q)))


def _recon(table: PlotTable, profile: str) -> Output:
    from solver.config import ReconstructionConfig
    from solver.reconstruct import reconstruct
    rec = reconstruct(table, ReconstructionConfig())  # type: ignore[arg-type]
    return Output(rec.at_plots, list(getattr(rec, "sensors", []) or []))


def _filter(name: str) -> Callable[[PlotTable, str], Output]:
    def run(table: PlotTable, profile: str) -> Output:
        from solver.estimation import run_filter
        return Output(run_filter(name, table).states)  # type: ignore[call-arg]
    return run


def filter_names() -> tuple[str, ...]:
    from solver.estimation import FILTER_NAMES
    return tuple(FILTER_NAMES)


FUSION_FILTER_PATTERNS = ("fusion*", "async*", "*kf_rts*", "cv_rts")


def estimators_for(profile: MultiProfile, quick: bool) -> list[MultiEstimator]:
    """Every estimator run on ``profile``'s plots (quick: the fusion filters and ``cv_rts``
    only among the product's filters)."""
    est = [MultiEstimator("ss-ekf-rts", "anchor", _anchor),
           MultiEstimator("recon", "recon", _recon)]
    singles = profile.sensors if len(profile.sensors) > 1 else ()
    for s in singles:
        est.append(MultiEstimator(f"recon-alone[{s.id}]", "recon-alone", _recon, s.id))
        est.append(MultiEstimator(f"ss-ekf-rts-alone[{s.id}]", "anchor-alone", _anchor, s.id))
    names = filter_names()
    if quick:
        names = tuple(n for n in names if any(fnmatch.fnmatch(n, p)
                                              for p in FUSION_FILTER_PATTERNS))
    est += [MultiEstimator(f"filter-{n}", "filter", _filter(n)) for n in names]
    if profile.name == "seed004":
        est += [MultiEstimator(f"filter-alpha_beta-alone[{s.id}]", "filter-alone",
                               _filter("alpha_beta"), s.id) for s in profile.sensors]
    return est


# ------------------------------------------------------------------------------ running


@dataclass
class Registration:
    """One estimated offset against the simulated one."""

    profile: str
    truth: str
    seed: int
    sensor: str
    quantity: str
    true: float
    estimate: float | None
    sigma: float | None

    @property
    def within_3sigma(self) -> bool | None:
        if self.estimate is None or self.sigma is None or not np.isfinite(self.sigma):
            return None
        return bool(abs(self.estimate - self.true) <= 3 * self.sigma)


@dataclass
class MultiResult:
    errors: dict[tuple[str, str], list[RunErrors]] = field(default_factory=dict)
    failures: list[dict[str, Any]] = field(default_factory=list)
    registration: list[Registration] = field(default_factory=list)
    n_plots: dict[str, list[int]] = field(default_factory=dict)
    elapsed_s: float = 0.0
    summary: dict[str, dict[str, dict[str, float]]] | None = None  # set: re-rendered from json

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> MultiResult:
        """The pooled metrics, offsets and failures of a results json (to re-render it)."""
        regs = [Registration(**{k: v for k, v in r.items() if k != "within_3sigma"})
                for r in data["registration"]]
        return cls(failures=data["failures"], registration=regs,
                   elapsed_s=float(data["elapsed_s"]), summary=data["overall"])


def _get(report: Any, key: str) -> Any:
    return report.get(key) if isinstance(report, dict) else getattr(report, key, None)


def _registration(track: MultiTrack, sensors: list[Any], profile: MultiProfile, truth: str
                  ) -> list[Registration]:
    out = []
    by_id = {_get(r, "id"): r for r in sensors}
    for spec in profile.sensors:
        if not spec.estimate_bias:
            continue
        rep = by_id.get(spec.id)
        bias = track.biases[spec.id]
        for q, true, est_key, sig_key in (
                ("range_m", bias.range_m, "range_bias_m", "range_bias_sigma_m"),
                ("azimuth_deg", np.degrees(bias.azimuth_rad), "azimuth_bias_rad",
                 "azimuth_bias_sigma_rad"),
                ("time_s", bias.time_s, "time_bias_s", "time_bias_sigma_s")):
            est = None if rep is None else _get(rep, est_key)
            sig = None if rep is None else _get(rep, sig_key)
            if q == "azimuth_deg" and est is not None and sig is not None:
                est, sig = float(np.degrees(est)), float(np.degrees(sig))
            out.append(Registration(profile.name, truth, track.seed, spec.id, q, float(true),
                                    None if est is None else float(est),
                                    None if sig is None else float(sig)))
    return out


def _warm_up(estimators: list[MultiEstimator], profile: MultiProfile) -> None:
    track = simulate_multi(place(QUICK_TRUTHS[0]), profile.sensors, profile.name, 10_000, 300.0)
    for est in estimators:
        rows = est.rows(track)
        try:
            est.run(track.table if rows is None else sub_table(track.table, rows), profile.name)
        except Exception:  # the timed run records it
            pass


def run_multi(truths: list[str], profiles: list[str], seeds: list[int], quick: bool = False,
              t_max: float | None = None, patterns: list[str] | None = None,
              progress: bool = True) -> MultiResult:
    """Every (profile, truth, seed) simulated once; every estimator on its plots."""
    res = MultiResult()
    start = time.perf_counter()
    for pname in profiles:
        profile = MULTI_PROFILES[pname]
        ests = estimators_for(profile, quick)
        if patterns:
            ests = [e for e in ests if any(fnmatch.fnmatchcase(e.name, p) for p in patterns)]
        _warm_up(ests, profile)
        for tname in truths:
            for seed in seeds:
                track = simulate_multi(place(tname), profile.sensors, pname, seed, t_max)
                res.n_plots.setdefault(pname, []).append(len(track.table))
                for est in ests:
                    rows = est.rows(track)
                    table = track.table if rows is None else sub_table(track.table, rows)
                    sel = np.arange(len(track.table)) if rows is None else rows
                    truth = StateSeries(track.truth.t[sel], track.truth.x[sel],
                                        track.truth.z[sel], track.truth.vx[sel],
                                        track.truth.vz[sel])
                    try:
                        t0, c0 = time.perf_counter(), time.process_time()
                        out = est.run(table, pname)
                        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                        run_err = errors(out.states, truth, track.manoeuvre[sel], wall, cpu)
                    except Exception as exc:  # recorded; the run goes on
                        msg = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                        res.failures.append({"estimator": est.name, "profile": pname,
                                             "truth": tname, "seed": seed, "error": msg[:300]})
                        continue
                    res.errors.setdefault((pname, est.name), []).append(run_err)
                    if rows is None and est.kind in ("recon", "anchor", "filter") \
                            and len(ests) > 1:
                        for spec in profile.sensors if len(profile.sensors) > 1 else ():
                            res.errors.setdefault((pname, f"{est.name}@{spec.id}"), []).append(
                                _subset(run_err, track.rows_of(spec.id)))
                    if est.kind == "recon" and profile.registration:
                        res.registration += _registration(track, out.sensors, profile, tname)
                    if progress:
                        print(f"{pname:13s} {tname[:24]:24s} s{seed} {est.name:34s} "
                              f"{np.sqrt(np.mean(run_err.pos ** 2)):8.1f} m {wall:6.2f} s",
                              file=sys.stderr, flush=True)
    res.elapsed_s = time.perf_counter() - start
    return res


def _subset(err: RunErrors, rows: np.ndarray) -> RunErrors:
    """A fused estimate's errors at one sensor's plots (no timing of its own)."""
    return RunErrors(err.pos[rows], err.speed[rows], err.manoeuvre[rows], err.inside95[rows],
                     float("nan"), int(rows.size))


def overall(res: MultiResult) -> dict[str, dict[str, dict[str, float]]]:
    if res.summary is not None:
        return res.summary
    out: dict[str, dict[str, dict[str, float]]] = {}
    for (p, e), runs in res.errors.items():
        out.setdefault(p, {})[e] = summarize(runs)
    return out


# ------------------------------------------------------------------------------ targets


@dataclass
class Target:
    profile: str
    target: str
    measured: str
    limit: str
    met: bool | None


def _rms(m: dict[str, dict[str, float]], name: str) -> float:
    return m.get(name, {}).get("rms_pos", float("nan"))


def targets(res: MultiResult) -> list[Target]:
    """Issue 15's targets against the measurements (None: not measurable in this run)."""
    summ = overall(res)
    out: list[Target] = []

    def check(profile: str, target: str, num: float, den: float, limit: float,
              what: str) -> None:
        ratio = num / den if np.isfinite(num) and np.isfinite(den) and den > 0 else float("nan")
        met = None if not np.isfinite(ratio) else bool(ratio <= limit)
        out.append(Target(profile, target, f"{num:.1f} / {den:.1f} m = {ratio:.3f}x ({what})",
                          f"<= {limit:g}x", met))

    for pname, m in summ.items():
        profile = MULTI_PROFILES[pname]
        fused = _rms(m, "recon")
        check(pname, "fused reconstruction vs fused Stone Soup smoother", fused,
              _rms(m, "ss-ekf-rts"), 0.85, "recon / ss-ekf-rts")
        singles = {s.id: _rms(m, f"recon-alone[{s.id}]") for s in profile.radars}
        finite = {k: v for k, v in singles.items() if np.isfinite(v)}
        best = min(finite, key=finite.__getitem__) if finite else None
        best_rms = finite[best] if best else float("nan")
        at_best = _rms(m, f"recon@{best}")  # the fused track at the better radar's plots
        what = f"recon@{best} / recon-alone[{best}], at {best}'s plots"
        if profile.similar and len(profile.radars) >= 2:
            check(pname, "fused vs the better single-radar reconstruction (similar radars)",
                  at_best, best_rms, 0.65, what)
        if profile.without_mode_c:
            check(pname, "without Mode C: never worse than the better single radar", at_best,
                  best_rms, 1.0, what)
        if pname == "seed004":
            # at each source's own plots: a filter's state between its steps is a prediction,
            # so the fused filters are scored where the source alone is
            alone = {s.id: _rms(m, f"filter-alpha_beta-alone[{s.id}]") for s in profile.sensors}
            acc, fast = alone.get("ACC", float("nan")), alone.get("FAST", float("nan"))
            c_acc, c_fast = _rms(m, "filter-fusion_c@ACC"), _rms(m, "filter-fusion_c@FAST")
            a_acc = _rms(m, "filter-fusion_a@ACC")
            r1, r2 = c_acc / acc, c_fast / fast
            met = None if not (np.isfinite(r1) and np.isfinite(r2)) else bool(r1 < 1 and r2 < 1)
            missing = ("not measured in this run (needs filter-fusion_c@ACC/@FAST and "
                       "filter-alpha_beta-alone[*]: --profiles seed004 --estimators 'filter-*')")
            out.append(Target(pname, "seed 004: C better than either source alone "
                              "(alpha-beta alone; at each source's plots)",
                              missing if met is None else
                              f"ACC's plots {c_acc:.1f} / {acc:.1f} m = {r1:.2f}x, FAST's plots "
                              f"{c_fast:.1f} / {fast:.1f} m = {r2:.2f}x", "< 1x both", met))
            ok = None if not (np.isfinite(a_acc) and np.isfinite(acc)) else bool(a_acc > acc)
            out.append(Target(pname, "seed 004: A worse than the accurate source alone (at its "
                              "plots)", missing if ok is None else
                              f"{a_acc:.1f} vs {acc:.1f} m (filter-fusion_a@ACC vs "
                              "filter-alpha_beta-alone[ACC])", "A > ACC alone", ok))
    if any(MULTI_PROFILES[p].registration for p in summ):
        for target, quantities in (
                ("range (50-200 m) and azimuth (0.1-0.3 deg) offsets within their reported "
                 "3 sigma", ("range_m", "azimuth_deg")),
                ("time offsets (also estimated; true 0 s) within their reported 3 sigma",
                 ("time_s",))):
            regs = [r for r in res.registration if r.quantity in quantities]
            judged = [r for r in regs if r.within_3sigma is not None]
            n_in = sum(bool(r.within_3sigma) for r in judged)
            out.append(Target("registration", target, f"{n_in} of {len(judged)} offsets "
                              f"({len(regs) - len(judged)} not reported)", "all",
                              None if not regs or len(judged) < len(regs)
                              else n_in == len(judged)))
    return out


# ------------------------------------------------------------------------------ report


def _fmt(v: float, digits: int = 1) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def render(res: MultiResult, settings: dict[str, Any], env: dict[str, str]) -> list[str]:
    summ = overall(res)
    md = ["# Multi-sensor benchmark (issue 15)", "",
          f"Command: `{settings['command']}`  ", f"Commit {env['commit']}, {env['date_utc']}, "
          f"{env['machine']} x{env['cpus']}, Python {env['python']}, Stone Soup "
          f"{env['stonesoup']}; run time {res.elapsed_s:.0f} s.  ",
          f"Truths: {', '.join(settings['truths'])}"
          + (f" (cut to {settings['t_max']:.0f} s)" if settings["t_max"] else "")
          + f"; held-out seeds {settings['seeds']} (the anchor's q is tuned on seeds "
          f"{list(DEV_SEEDS)}).", "",
          "Truths placed on the earth and simulated through it by `benchmarks/earth.py`; "
          "estimators and profiles in `benchmarks/multisensor.py` (module docstrings).", "",
          "## Targets (issue 15)", "",
          "| profile | target | measured | limit | met |", "|---|---|---|---|---|"]
    for t in targets(res):
        met = "n/a" if t.met is None else ("yes" if t.met else "**no**")
        md.append(f"| {t.profile} | {t.target} | {t.measured} | {t.limit} | {met} |")
    md += ["", "## Profiles", "", "| profile | sensors | anchor q (m²/s³) |", "|---|---|---:|"]
    for p in settings["profiles"]:
        mp = MULTI_PROFILES[p]
        md.append(f"| {p} | {mp.description} | {TUNED_Q.get(p, DEFAULT_Q):g}"
                  f"{'' if p in TUNED_Q else ' (untuned)'} |")
    md += ["", "Sites (slot 0 is the truth's own origin; heights above WGS-84):", "",
           "| truth | plane reference = site 0 (lat, lon, h) | site 1 (lat, lon, h) |",
           "|---|---|---|"]
    for tn in settings["truths"]:
        et = place(tn)
        s0, s1 = et.sites
        md.append(f"| {tn} | {s0.lat_deg:.4f}, {s0.lon_deg:.4f}, {s0.height_m:.0f} m | "
                  f"{s1.lat_deg:.4f}, {s1.lon_deg:.4f}, {s1.height_m:.0f} m |")
    md += ["", "## Results", "", "RMS horizontal position and ground-speed error against the truth "
           "at the plot times (pooled over tracks and seeds), 95th percentile of the position "
           "error, share of truth positions inside the 95 % ellipse, plots per CPU-second. "
           "`*-alone[id]` rows are scored on that sensor's plots only, `recon@id` and "
           "`ss-ekf-rts@id` are the fused estimates scored at that sensor's plots (the "
           "single-sensor targets compare these on the same plots).", ""]
    for p, m in summ.items():
        n = res.n_plots.get(p, [])
        total, runs = ((sum(n), len(n)) if n else
                       (int(m["ss-ekf-rts"]["n_plots"]), int(m["ss-ekf-rts"]["n_runs"]))
                       if "ss-ekf-rts" in m else (0, 0))
        md += [f"### {p}", "", f"{MULTI_PROFILES[p].description}; {total} plots in {runs} "
               "runs.", "",
               "| estimator | RMS pos (m) | p95 pos (m) | RMS speed (m/s) | 95 % coverage | "
               "plots / CPU-s | plots |", "|---|---:|---:|---:|---:|---:|---:|"]
        for name, s in sorted(m.items(), key=lambda kv: kv[1]["rms_pos"]):
            cov = s["coverage95"]
            md.append(f"| {name} | {_fmt(s['rms_pos'])} | {_fmt(s['p95_pos'])} | "
                      f"{_fmt(s['rms_speed'], 2)} | "
                      f"{'–' if not np.isfinite(cov) else f'{100 * cov:.0f} %'} | "
                      f"{_fmt(s['plots_per_cpu_s'], 0)} | {s['n_plots']} |")
        md.append("")
    if res.registration:
        md += ["## Registration", "", "Per offset: RMS of (estimate - true), median reported "
               "sigma, share within the reported 3 sigma (a wide sigma makes the last easy: read "
               "it with the second).", "",
               "| offset | n | RMS error | median sigma | within 3 sigma |",
               "|---|---:|---:|---:|---:|"]
        for q in ("range_m", "azimuth_deg", "time_s"):
            rs = [r for r in res.registration if r.quantity == q and r.estimate is not None]
            if not rs:
                continue
            err = np.array([r.estimate - r.true for r in rs])  # type: ignore[operator]
            sig = np.array([np.nan if r.sigma is None else r.sigma for r in rs])
            within = [r.within_3sigma for r in rs if r.within_3sigma is not None]
            md.append(f"| {q} | {len(rs)} | {rms(err):.3f} | {np.nanmedian(sig):.3f} | "
                      f"{sum(within)} of {len(within)} |")
        md += ["", "| truth | seed | sensor | offset | true | estimate | "
               "3 sigma | within |", "|---|---:|---|---|---:|---:|---:|---|"]
        for r in res.registration:
            w = r.within_3sigma
            md.append(f"| {r.truth} | {r.seed} | {r.sensor} | {r.quantity} | {r.true:.3f} | "
                      f"{_fmt(r.estimate, 3)} | "
                      f"{_fmt(None if r.sigma is None else 3 * r.sigma, 3)} | "
                      f"{'n/a' if w is None else ('yes' if w else '**no**')} |")
        md.append("")
    if res.failures:
        md += ["## Failures", "", f"{len(res.failures)} estimator runs raised (first of each "
               "estimator and profile):", ""]
        seen = set()
        for f in res.failures:
            key = (f["estimator"], f["profile"])
            if key in seen:
                continue
            seen.add(key)
            n_f = sum(1 for g in res.failures if (g["estimator"], g["profile"]) == key)
            md.append(f"- `{f['estimator']}` on {f['profile']} ({n_f}x): `{f['error']}`")
        md.append("")
    return md


def to_json(res: MultiResult, settings: dict[str, Any], env: dict[str, str]) -> dict[str, Any]:
    return {"settings": settings, "environment": env, "elapsed_s": res.elapsed_s,
            "tuned_q": TUNED_Q, "overall": overall(res),
            "targets": [asdict(t) for t in targets(res)],
            "registration": [{**asdict(r), "within_3sigma": r.within_3sigma}
                             for r in res.registration],
            "failures": res.failures}


# ------------------------------------------------------------------------------ tuning


def tune(truths: list[str], profiles: list[str], seeds: list[int]) -> dict[str, Any]:
    """The anchor's q per profile: pooled RMS position error over ``Q_GRID`` on the dev seeds."""
    out: dict[str, Any] = {"seeds": seeds, "truths": truths, "q_grid": Q_GRID, "profiles": {}}
    for pname in profiles:
        profile = MULTI_PROFILES[pname]
        runs: dict[float, list[RunErrors]] = {q: [] for q in Q_GRID}
        for tname in truths:
            for seed in seeds:
                track = simulate_multi(place(tname), profile.sensors, pname, seed)
                for q in Q_GRID:
                    st = stonesoup_fused(track.table, q)
                    runs[q].append(errors(st, track.truth, track.manoeuvre))
        scores = {q: summarize(r)["rms_pos"] for q, r in runs.items()}
        best = min(scores, key=scores.__getitem__)
        out["profiles"][pname] = {"scores": {f"{q:g}": s for q, s in scores.items()},
                                  "best_q": best}
        print(f"{pname}: " + ", ".join(f"q={q:g} {s:.1f} m" for q, s in scores.items())
              + f" -> {best:g}", flush=True)
    return out


# ------------------------------------------------------------------------------ main


def dev_truths() -> list[str]:
    return [n for n in truth_names() if n != SYNTHETIC]


def _dirty() -> str:
    """' (+ uncommitted changes in solver/)' when the product code differs from the commit."""
    import subprocess
    try:
        out = subprocess.run(["git", "status", "--porcelain", "--", "solver"], check=True,
                             capture_output=True, text=True, cwd=Path(__file__).parent).stdout
    except (OSError, subprocess.CalledProcessError):
        return ""
    return " (+ uncommitted changes in solver/)" if out.strip() else ""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.multisensor", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=f"{len(QUICK_TRUTHS)} tracks cut to "
                    f"{QUICK_T_MAX:.0f} s, 1 seed, the fusion filters only (under two minutes)")
    ap.add_argument("--seeds", type=int, default=None, help="held-out seeds 0..N-1 (default 3, "
                    "quick 1)")
    ap.add_argument("--profiles", nargs="+", choices=sorted(MULTI_PROFILES), default=None)
    ap.add_argument("--truths", nargs="+", choices=dev_truths(), default=None)
    ap.add_argument("--estimators", nargs="+", default=None, help="glob patterns")
    ap.add_argument("--t-max", type=float, default=None, help="cut tracks to this many seconds")
    ap.add_argument("--tune", action="store_true", help="tune the anchor's q on the dev seeds")
    ap.add_argument("--out", default=None, help="results name (default multisensor, quick: "
                    "multisensor_quick)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--render", default=None, metavar="JSON",
                    help="re-render the markdown of a results json (targets recomputed)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    profiles = args.profiles or list(MULTI_PROFILES)
    truths = args.truths or (list(QUICK_TRUTHS) if args.quick else dev_truths())
    command = "python -m benchmarks.multisensor " + shlex.join(argv if argv is not None
                                                               else sys.argv[1:])
    dirty = _dirty()  # before the run: the code measured
    if args.render:
        data = json.loads(Path(args.render).read_text())
        res = MultiResult.from_json(data)
        settings, env = data["settings"], data["environment"]
        md = render(res, settings, env)
        md.insert(3, f"(Rendered again from `{Path(args.render).name}` by `{command.strip()}`: "
                  "same measurements, targets recomputed.)  ")
        publish(Path(args.render).with_suffix(".md").name, md)
        data["targets"] = [asdict(t) for t in targets(res)]
        Path(args.render).write_text(json.dumps(data, indent=1, default=float) + "\n")
        return 0
    if args.tune:
        out = tune(truths, profiles, list(DEV_SEEDS))
        out["command"] = command
        path = RESULTS_DIR / "multisensor_tuning.json"
        path.write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {path}; copy best_q into multisensor.TUNED_Q")
        return 0
    n_seeds = args.seeds or (1 if args.quick else 3)
    seeds = list(range(n_seeds))
    t_max = args.t_max if args.t_max is not None else (QUICK_T_MAX if args.quick else None)
    res = run_multi(truths, profiles, seeds, quick=args.quick, t_max=t_max,
                    patterns=args.estimators, progress=not args.no_progress)
    settings = {"command": command.strip(), "profiles": profiles, "truths": truths,
                "seeds": seeds, "t_max": t_max, "quick": args.quick}
    env = environment()
    env["commit"] += dirty
    name = args.out or ("multisensor_quick" if args.quick else "multisensor")
    publish(f"{name}.md", render(res, settings, env))
    (RESULTS_DIR / f"{name}.json").write_text(json.dumps(to_json(res, settings, env), indent=1,
                                                         default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
