"""The benchmark's truth trajectories on the real earth, and sensors simulated through it.

Placement. Each ADS-B truth (``benchmarks/data/truth``) gives ``(x, z)`` in metres north and
east of the radar it was converted for, and ``h``. Here ``(x, z)`` are taken as coordinates in
the oblique stereographic plane (:class:`solver.frames.LocalFrame`) about a reference point
chosen so that the track's centroid lies where the flight really was (:data:`PLACES`, the area
of each ``traffic`` sample), and ``h`` as the height above the WGS-84 ellipsoid. The reference
is the original radar position, so the first site (slot 0) is the radar the truth was built
around (ranges 21-189 km); the second (slot 1) is the first of :data:`SECOND_SITE_CANDIDATES`
(bearing and distance from the centroid) at least :data:`MIN_SITE_SEPARATION_M` from the first
site from which the whole track stays between :data:`RANGE_LIMITS_M`.

Simulation (:func:`simulate_sensor`). A radar's plots are PROJ's exact slant range and
azimuth of the 3-D truth from its site (:meth:`solver.sensors.RadarSensor.measure`: geodetic
point from the plane, topocentric frame of the site), plus systematic offsets and Gaussian
noise; a position sensor's are the truth's latitude and longitude after a Gaussian
displacement in the plane. Scan times ``t0 + phase + k T``; each plot kept with probability
``Pd`` and outside the sensor's gaps. A time offset ``dt`` means a plot stamped ``t`` measured
the aircraft at ``t - dt`` (the stamp is late by ``dt``). Every draw comes from
``default_rng((seed, crc32(truth), crc32(profile), crc32(sensor)))`` (the offsets from the
stream of ``sensor + "/bias"``, so that a profile with offsets has the same scans and noise as
one without).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache

import numpy as np
from pyproj import Geod

from solver.frames import LocalFrame
from solver.inputs import FloatArray
from solver.plots import PlotTable
from solver.results import StateSeries
from solver.sensors import PositionSensor, RadarSensor, Sensor, Site

from .simulate import MANOEUVRE_RATE
from .truth import Truth, load_truth

GEOD = Geod(ellps="WGS84")

PLACES: dict[str, tuple[float, float]] = {
    "calibration__ajaccio": (41.92, 8.80),          # Ajaccio, Corsica
    "calibration__bornholm": (55.07, 14.75),        # Bornholm, Denmark
    "calibration__kiruna": (67.82, 20.34),          # Kiruna, Sweden
    "calibration__vienna": (48.11, 16.57),          # Vienna Schwechat
    "featured__belevingsvlucht": (52.17, 5.35),     # the Netherlands
    "surveys__ign_fontainebleau": (48.40, 2.70),    # Fontainebleau forest, France
}
"""Where each truth's centroid is placed (latitude, longitude in degrees): the area the flight
of the ``traffic`` sample was recorded in."""

SECOND_SITE_CANDIDATES: tuple[tuple[float, float], ...] = (
    (135.0, 80.0), (315.0, 80.0), (90.0, 90.0), (180.0, 90.0), (0.0, 90.0), (270.0, 90.0),
    (45.0, 100.0), (135.0, 110.0), (315.0, 110.0))
"""(bearing from the track's centroid in degrees, distance in km) of the second site, in order of
preference."""
SITE_HEIGHTS_M = (320.0, 870.0)
"""Heights above the ellipsoid of the sites in slot 0 and 1 (a lowland and a hill-top radar)."""
RANGE_LIMITS_M = (20e3, 200e3)
MIN_SITE_SEPARATION_M = 60e3


@dataclass(frozen=True)
class EarthTruth:
    """A truth placed on the earth: its plane (``truth.x``/``truth.z`` are plane coordinates)
    and the sensor sites (slot index -> :class:`Site`)."""

    truth: Truth
    frame: LocalFrame
    sites: tuple[Site, ...]

    def geodetic(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(lat_deg, lon_deg, h above the ellipsoid)`` of the truth at times ``t``."""
        s = self.truth.at(t)
        lat, lon = self.frame.to_geodetic(s.x, s.z)
        return lat, lon, self.truth.altitude_at(t)

    def site_plane(self, slot: int) -> tuple[float, float]:
        """Plane position ``(x, z)`` of the site in ``slot``."""
        site = self.sites[slot]
        x, z = self.frame.to_plane(np.array([site.lat_deg]), np.array([site.lon_deg]))
        return float(x[0]), float(z[0])


def _centroid(truth: Truth) -> tuple[float, float]:
    return float(np.mean(truth.x)), float(np.mean(truth.z))


def reference_for(truth: Truth) -> LocalFrame:
    """The plane about the point from which the truth's centroid lies where :data:`PLACES` puts
    it (the truth's own origin: its original radar)."""
    lat_c, lon_c = PLACES[truth.name]
    xc, zc = _centroid(truth)
    az = float(np.degrees(np.arctan2(-zc, -xc)))
    lon0, lat0, _ = GEOD.fwd(lon_c, lat_c, az, float(np.hypot(xc, zc)))
    return LocalFrame(round(float(lat0), 6), round(float(lon0), 6))


def _ranges_ok(frame: LocalFrame, truth: Truth, site: Site) -> bool:
    lat, lon = frame.to_geodetic(truth.x, truth.z)
    _, _, d = GEOD.inv(np.full(lat.shape, site.lon_deg), np.full(lat.shape, site.lat_deg),
                       lon, lat)
    d = np.asarray(d)
    return bool(d.min() >= RANGE_LIMITS_M[0] and d.max() <= RANGE_LIMITS_M[1])


@cache
def place(truth_name: str) -> EarthTruth:
    """The truth of that name on the earth with its two sites (see the module docstring)."""
    truth = load_truth(truth_name)
    frame = reference_for(truth)
    first = Site(frame.lat_deg, frame.lon_deg, SITE_HEIGHTS_M[0])
    lat_c, lon_c = frame.to_geodetic(*map(np.atleast_1d, _centroid(truth)))
    for bearing, dist_km in SECOND_SITE_CANDIDATES:
        lon2, lat2, _ = GEOD.fwd(float(lon_c[0]), float(lat_c[0]), bearing, dist_km * 1e3)
        second = Site(round(float(lat2), 6), round(float(lon2), 6), SITE_HEIGHTS_M[1])
        _, _, sep = GEOD.inv(first.lon_deg, first.lat_deg, second.lon_deg, second.lat_deg)
        if sep >= MIN_SITE_SEPARATION_M and _ranges_ok(frame, truth, second):
            return EarthTruth(truth, frame, (first, second))
    raise ValueError(f"no second site keeps {truth.name} within {RANGE_LIMITS_M} m")


# ------------------------------------------------------------------------------ sensors


@dataclass(frozen=True)
class Bias:
    """True systematic offsets of a radar: range (m), azimuth (rad), time (s, see the module
    docstring)."""

    range_m: float = 0.0
    azimuth_rad: float = 0.0
    time_s: float = 0.0


@dataclass(frozen=True)
class BiasDraw:
    """Offsets drawn per run: magnitudes uniform in the ranges, random signs."""

    range_m: tuple[float, float] = (0.0, 0.0)
    azimuth_deg: tuple[float, float] = (0.0, 0.0)
    time_s: tuple[float, float] = (0.0, 0.0)

    def draw(self, rng: np.random.Generator) -> Bias:
        def one(lo: float, hi: float) -> float:
            return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi)) if hi > 0 else 0.0
        return Bias(one(*self.range_m), float(np.deg2rad(one(*self.azimuth_deg))),
                    one(*self.time_s))


@dataclass(frozen=True)
class SensorSpec:
    """One sensor of a multi-sensor profile.

    ``kind`` ``radar``: at site ``slot``, scan period ``scan_s``, noise ``sigma_r`` (m),
    ``sigma_psi`` (rad), a priori errors ``eps_r``/``eps_psi`` and ``h_max``/``alpha_max`` (as
    :class:`benchmarks.profiles.RadarProfile`), ``mode_c``: plots carry the true height;
    ``bias``: true offsets drawn per run; ``estimate_bias``: the product is asked to estimate
    them. ``kind`` ``position``: ``sigma_pos`` per horizontal axis (m); ``gaps``: number of
    outages per hour and their length range (s)."""

    id: str
    kind: str
    scan_s: float
    pd: float = 1.0
    slot: int = 0
    sigma_r: float = 0.0
    sigma_psi: float = 0.0
    eps_r: float = 0.0
    eps_psi: float = 0.0
    h_max: float = 0.0
    alpha_max: float = 0.0
    mode_c: bool = False
    bias: BiasDraw = field(default_factory=BiasDraw)
    estimate_bias: bool = False
    sigma_pos: float = 0.0
    gaps_per_hour: float = 0.0
    gap_s: tuple[float, float] = (0.0, 0.0)

    def sensor(self, site: Site) -> Sensor:
        """The product's sensor model, as an operator would configure it."""
        if self.kind == "position":
            return PositionSensor(self.id, self.sigma_pos)
        return RadarSensor(self.eps_r, self.eps_psi, range_sigma_m=self.sigma_r,
                           azimuth_sigma_rad=self.sigma_psi, max_altitude_m=self.h_max,
                           max_elevation_rad=self.alpha_max, id=self.id, site=site,
                           estimate_bias=self.estimate_bias)


@dataclass
class SensorPlots:
    """One sensor's simulated plots (time order) and the truth at their time stamps."""

    spec: SensorSpec
    sensor: Sensor
    t: FloatArray
    range_m: FloatArray | None
    azimuth_rad: FloatArray | None
    lat_deg: FloatArray | None
    lon_deg: FloatArray | None
    altitude_m: FloatArray | None
    bias: Bias


def rng_for(truth: str, profile: str, sensor: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(truth.encode()), zlib.crc32(profile.encode()),
                                  zlib.crc32(sensor.encode())])


def _gap_mask(rng: np.random.Generator, t: FloatArray, t0: float, t1: float,
              per_hour: float, length: tuple[float, float]) -> np.ndarray:
    """True where ``t`` falls in none of the outages (Poisson count, uniform start/length)."""
    keep = np.ones(t.shape, bool)
    if per_hour <= 0:
        return keep
    for _ in range(int(rng.poisson(per_hour * (t1 - t0) / 3600.0))):
        start = rng.uniform(t0, t1)
        keep &= ~((t >= start) & (t < start + rng.uniform(*length)))
    return keep


def simulate_sensor(et: EarthTruth, spec: SensorSpec, profile: str, seed: int,
                    t_max: float | None = None, noise_scale: float = 1.0) -> SensorPlots:
    """One sensor's plots of ``et`` (see the module docstring); deterministic per
    (truth, profile, sensor id, seed). ``noise_scale`` multiplies the random errors (0: exact
    plots, the sensor keeps its sigmas)."""
    truth = et.truth
    rng = rng_for(truth.name, profile, spec.id, seed)
    t_end = truth.t[-1] if t_max is None else min(truth.t[-1], truth.t[0] + t_max)
    bias_rng = rng_for(truth.name, profile, spec.id + "/bias", seed)  # its own stream: the
    bias = spec.bias.draw(bias_rng) if spec.kind == "radar" else Bias()  # same plots otherwise
    phase = rng.uniform(0.0, spec.scan_s)
    t = np.arange(truth.t[0] + phase + max(bias.time_s, 0.0), t_end + min(bias.time_s, 0.0),
                  spec.scan_s)
    n = t.size
    keep = rng.uniform(size=n) < spec.pd
    keep &= _gap_mask(rng, t, float(truth.t[0]), float(t_end), spec.gaps_per_hour, spec.gap_s)
    site = et.sites[spec.slot]
    sensor = spec.sensor(site)
    t_meas = t - bias.time_s  # when the aircraft was where the plot says
    state = truth.at(t_meas)
    h = truth.altitude_at(t_meas)
    if isinstance(sensor, RadarSensor):
        r, psi = sensor.measure(et.frame, state.x, state.z, h)
        r = r + bias.range_m + noise_scale * rng.normal(0.0, spec.sigma_r, n)
        psi = psi + bias.azimuth_rad + noise_scale * rng.normal(0.0, spec.sigma_psi, n)
        psi = np.mod(psi, 2 * np.pi)
        return SensorPlots(spec, sensor, t[keep], r[keep], psi[keep], None, None,
                           h[keep] if spec.mode_c else None, bias)
    dx = noise_scale * rng.normal(0.0, spec.sigma_pos, n)
    dz = noise_scale * rng.normal(0.0, spec.sigma_pos, n)
    lat, lon = et.frame.to_geodetic(state.x + dx, state.z + dz)
    return SensorPlots(spec, sensor, t[keep], None, None, lat[keep], lon[keep], None, bias)


@dataclass
class MultiTrack:
    """One simulated multi-sensor run: the product's plots table (rows in time order, ties in
    sensor order), the truth at every row's time stamp, and each sensor's true offsets."""

    table: PlotTable
    truth: StateSeries
    altitude: FloatArray
    turn_rate: FloatArray
    biases: dict[str, Bias]
    earth: EarthTruth
    seed: int
    profile: str

    @property
    def manoeuvre(self) -> np.ndarray:
        return np.abs(self.turn_rate) > MANOEUVRE_RATE

    def rows_of(self, sensor_id: str) -> np.ndarray:
        """Row indexes of one sensor's plots."""
        ids = [s.id for s in self.table.sensors]
        return np.flatnonzero(self.table.sensor == ids.index(sensor_id))


def _nan_or(values: FloatArray | None, n: int) -> FloatArray:
    return np.full(n, np.nan) if values is None else values


def simulate_multi(et: EarthTruth, specs: Sequence[SensorSpec], profile: str, seed: int,
                   t_max: float | None = None, noise_scale: float = 1.0) -> MultiTrack:
    """Every sensor's plots of ``et`` merged into one :class:`PlotTable` in the truth's plane."""
    parts = [simulate_sensor(et, s, profile, seed, t_max, noise_scale) for s in specs]
    t = np.concatenate([p.t for p in parts])
    sid = np.concatenate([np.full(p.t.size, k) for k, p in enumerate(parts)])
    cols = {name: np.concatenate([_nan_or(getattr(p, name), p.t.size) for p in parts])
            for name in ("range_m", "azimuth_rad", "lat_deg", "lon_deg", "altitude_m")}
    order = np.lexsort((sid, t))
    table = PlotTable.build([p.sensor for p in parts], t[order], sid[order],
                            reference=et.frame, **{k: v[order] for k, v in cols.items()})
    tt = table.t
    truth_at = et.truth.at(tt)
    return MultiTrack(table, truth_at, et.truth.altitude_at(tt), et.truth.turn_rate_at(tt),
                      {p.spec.id: p.bias for p in parts}, et, seed, profile)


def sub_table(table: PlotTable, rows: np.ndarray) -> PlotTable:
    """The plots of ``rows`` (one or more sensors) as a table of their own, in the same plane;
    sensors without plots in ``rows`` are left out."""
    used = np.unique(table.sensor[rows])
    remap = np.full(len(table.sensors), -1)
    remap[used] = np.arange(used.size)
    return PlotTable.build([table.sensors[k] for k in used], table.t[rows],
                           remap[table.sensor[rows]], table.range_m[rows],
                           table.azimuth_rad[rows], table.lat_deg[rows], table.lon_deg[rows],
                           table.altitude_m[rows], reference=table.frame)
