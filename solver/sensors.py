"""Sensor (measurement) models: what a sensor measures of an aircraft, and how sure it is.

One class per kind, as Stone Soup's measurement models:

- :class:`RadarSensor`: slant range and azimuth from a site on WGS-84 (or, for the seed's single
  radar, from the origin of a flat plane), with the a priori errors and sigmas of
  :class:`solver.inputs.Radar`; optional Mode C / geometric altitude per plot; optional
  systematic biases (range, azimuth, time offsets) estimated with the trajectory.
- :class:`PositionSensor`: ADS-B / WAM-like latitude and longitude with a horizontal sigma per
  axis, optional altitude.

``measure`` turns a state (plane position and height) into the predicted measurement;
``fixes`` turns measurements into positions in the local plane with their one-sigma ellipses
(the weights of the reconstruction's criterion), and, for radar plots whose altitude is unknown,
the exact dependence of that position on the altitude (:class:`PlaneFixes`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from .frames import LocalFrame, check_lat_lon, radar_plot_position, slant_and_azimuth
from .geometry import Ellipses, ground_range_error, height_error
from .inputs import MAX_RANGE_ERROR_M, FloatArray, InputError, Radar

ALTITUDE_RANGE_M = (-500.0, 20_000.0)
"""Heights above the ellipsoid an unknown altitude may take (m) when it is estimated: up to
FL650, the top of controlled airspace (15 km cut business jets at FL510: 0.5-3 km low and
kilometres off, a tester measured). Known altitudes widen it for their track, for the
estimated height and every plot's reach alike (:meth:`solver.plots.PlotTable.heights`)."""
KNOWN_ALTITUDE_MARGIN_M = 500.0
"""The heights may go this far (plus 5 sigmas) beyond the track's known altitudes."""
ALTITUDE_SIGMA_RADAR_M = 30.0
"""m: a radar plot's reported altitude (Mode C: 100-ft steps, 25 ft with Mode S; pressure,
not geometric, altitude) as a measurement of the height in the altitude-estimating variant,
when its radar's ``altitude_sigma_m`` is 0 (exact for the plot's placement); else that."""
MAX_ELEVATION_FRACTION = 0.96
"""A plot's reach: the heights within ``0.96 r`` of its radar's at slant range ``r`` (elevations
within 74 deg: an aircraft at 10 km passing 3 km from the radar), where its centre follows the
height (:func:`reach`)."""
REACH_SOFTNESS_M = 10.0
"""Width (m) of the smooth ends of a plot's reach (:func:`reach`), at most 1/400 of its half."""
REACH_MARGIN = 12.0
"""The smooth ends start this many widths beyond the reach's (``h`` is itself within it to
``b log(1 + e^-12)``, 0.06 mm)."""
MAX_ELEVATION_DEG = float(np.degrees(np.arcsin(MAX_ELEVATION_FRACTION)))
ALTITUDE_FIT_DEGREE = 5


def reach(h: Any, h_mid: Any, h_half: Any, lib: Any = np) -> Any:
    """Height ``h`` clamped smoothly to a plot's reach ``h_mid -+ h_half``::

        lo + sp(h - lo) - sp(h - hi),   sp(x) = max(x, 0) + b log(1 + exp(-|x| / b)),
        [lo, hi] = h_mid -+ (h_half + 12 b),  b = min(10 m, h_half / 400)

    (:data:`REACH_SOFTNESS_M`, :data:`REACH_MARGIN`): ``h`` itself within the reach (to
    0.1 mm), and no further than ``12 b`` beyond it (3 % of its half: within the slant range,
    as the reach's ends are at most 0.96 of it). A plot's centre follows the height only that
    far, so a plot that cannot reach the track's height (a wild plot at 1 km under an aircraft
    at 10 km; an aircraft overhead above the elevation cap) stops moving with it and is
    weighed as wild, instead of bounding the track's height. ``lib``: ``numpy`` or
    ``casadi``."""
    b, lo, hi = _reach_ends(h_mid, h_half, lib)

    def sp(x: Any) -> Any:
        return lib.fmax(x, 0) + b * lib.log1p(lib.exp(-lib.fabs(x) / b))

    return lo + sp(h - lo) - sp(h - hi)


def _reach_ends(h_mid: Any, h_half: Any, lib: Any = np) -> tuple[Any, Any, Any]:
    """:func:`reach`'s width ``b`` and the ends ``lo``, ``hi`` of its smooth clamp."""
    b = lib.fmin(REACH_SOFTNESS_M, h_half / 400)
    return b, h_mid - h_half - REACH_MARGIN * b, h_mid + h_half + REACH_MARGIN * b


def beyond_reach(h: FloatArray, h_mid: FloatArray, h_half: FloatArray) -> np.ndarray:
    """Heights beyond the ends of :func:`reach`'s smooth clamp, where the centre has stopped
    following them."""
    _, lo, hi = _reach_ends(h_mid, h_half)
    return (h < lo) | (h > hi)


def reach_slope(h: FloatArray, h_mid: FloatArray, h_half: FloatArray) -> FloatArray:
    """``d reach / d h = sigma((h - lo) / b) - sigma((h - hi) / b)`` (logistic sigma)."""
    from scipy.special import expit

    b, lo, hi = _reach_ends(h_mid, h_half)
    return expit((h - lo) / b) - expit((h - hi) / b)


@dataclass(frozen=True)
class Site:
    """A sensor's position on WGS-84: latitude, longitude (degrees), height above the
    ellipsoid (m)."""

    lat_deg: float
    lon_deg: float
    height_m: float = 0.0

    def validate(self, loc: tuple[str | int, ...]) -> None:
        check_lat_lon(self.lat_deg, self.lon_deg, loc)
        if not (np.isfinite(self.height_m) and -500.0 <= self.height_m <= 10_000.0):
            raise InputError((*loc, "height_m"), "must be a finite height in [-500, 10000] m")

    @property
    def tuple(self) -> tuple[float, float, float]:
        return (float(self.lat_deg), float(self.lon_deg), float(self.height_m))


@dataclass(frozen=True)
class BiasPrior:
    """Prior standard deviations of a radar's systematic errors (zero mean): range offset
    (m), azimuth offset (rad), time offset (s). Wide enough for the offsets a registration
    finds in practice (tens to hundreds of metres, tenths of a degree, up to a second)."""

    range_m: float = 300.0
    azimuth_rad: float = float(np.deg2rad(0.5))
    time_s: float = 1.0

    @property
    def sigmas(self) -> FloatArray:
        return np.array([self.range_m, self.azimuth_rad, self.time_s])


@dataclass(frozen=True)
class PlaneFixes:
    """Plots as positions in the local plane (``x`` north, ``z`` east, m).

    ``ellipses``: centres at the plot's altitude (known) or at the nominal altitude (unknown,
    see ``altitude_free``), with one-sigma semi-axes along (``B``) and across (``A``) the
    sensor's ray; a position plot has a circle. For a radar plot with unknown altitude the
    centre at height ``h`` is, exactly up to a quintic's fit error (< 0.08 m at 12 km, 0.21 m
    at 20 km, < 2 mm from 30 km; tested)::

        c(h) = ray * sqrt(r^2 - (h' - h_site)^2) + sum_j poly[:, j] * s^j,
        s = (h' - h_mid) / h_half,  h' = reach(h) in [h_lo, h_hi] = h_mid -+ h_half

    (the flat-earth ground distance along the ray, ``ray`` the unit direction times the
    plane's scale at the plot, plus a smooth remainder from the earth's curvature and the
    projection). ``d_range`` and ``d_azimuth`` are the derivatives of the
    centre with respect to the measured slant range and azimuth (for sensor biases).
    """

    ellipses: Ellipses
    altitude_free: np.ndarray  # (n,) bool
    ray: FloatArray  # (n, 2): the unit direction times the plane's scale at the plot
    slant: FloatArray  # (n,)
    site_h: FloatArray  # (n,)
    poly: FloatArray  # (n, 2, ALTITUDE_FIT_DEGREE + 1)
    h_mid: FloatArray
    h_half: FloatArray
    d_range: FloatArray  # (n, 2)
    d_azimuth: FloatArray  # (n, 2)

    def centre_at(self, h: FloatArray) -> FloatArray:
        """``(n, 2)`` centres at heights ``h`` (ignored where the altitude is known)."""
        h = reach(np.broadcast_to(np.asarray(h, float), self.slant.shape), self.h_mid,
                  self.h_half)
        s = (h - self.h_mid) / self.h_half
        powers = s[:, None] ** np.arange(self.poly.shape[2])[None, :]
        c = np.einsum("nij,nj->ni", self.poly, powers)
        g = np.sqrt(np.maximum(self.slant**2 - (h - self.site_h) ** 2, 0.0))
        c = c + self.ray * g[:, None]
        fixed = np.column_stack([self.ellipses.cx, self.ellipses.cz])
        return np.where(self.altitude_free[:, None], c, fixed)


@dataclass(frozen=True)
class RadarSensor(Radar):
    """A radar: the accuracies of :class:`Radar` plus an ``id``, its ``site`` (None: at the
    origin of the plane: on a flat earth when no frame is given, else at the reference point)
    and whether to estimate its systematic biases."""

    id: str = field(default="radar", kw_only=True)
    site: Site | None = field(default=None, kw_only=True)
    estimate_bias: bool = field(default=False, kw_only=True)
    bias_prior: BiasPrior = field(default_factory=BiasPrior, kw_only=True)
    kind: ClassVar[str] = "radar"

    def validate_at(self, loc: tuple[str | int, ...]) -> None:
        """:meth:`Radar.validate` with errors located at ``loc`` (e.g. ``("sensors", 1)``)."""
        try:
            self.validate()
        except InputError as e:
            raise InputError((*loc, *e.loc[1:]), e.message) from None
        if self.site is not None:
            self.site.validate(loc)

    def site_in(self, frame: LocalFrame) -> tuple[float, float, float]:
        """The site as ``(lat, lon, h)``; a radar without a site sits at the reference point."""
        return self.site.tuple if self.site is not None else (frame.lat_deg, frame.lon_deg, 0.0)

    # ----------------------------------------------------------------- measurement model

    def measure(self, frame: LocalFrame | None, x: FloatArray, z: FloatArray, h: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
        """Predicted ``(slant range, azimuth)`` of aircraft at plane ``(x, z)`` and height ``h``
        (flat frame: height above the radar)."""
        if frame is None:
            return np.sqrt(x * x + z * z + h * h), np.mod(np.arctan2(z, x), 2 * np.pi)
        lat, lon = frame.to_geodetic(x, z)
        r, az, _ = slant_and_azimuth(self.site_in(frame), lat, lon, h)
        return r, az

    def positions(self, frame: LocalFrame | None, range_m: FloatArray, azimuth_rad: FloatArray,
                  h: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Plane positions ``(x, z)`` of plots at height ``h`` (flat frame: ground range
        ``sqrt(r^2 - h^2)`` on the ray)."""
        if frame is None:
            d = np.sqrt(np.maximum(range_m**2 - h**2, 0.0))
            return d * np.cos(azimuth_rad), d * np.sin(azimuth_rad)
        lat, lon, _ = radar_plot_position(self.site_in(frame), range_m, azimuth_rad, h)
        return frame.to_plane(lat, lon)

    def fixes(self, frame: LocalFrame | None, range_m: FloatArray, azimuth_rad: FloatArray,
              altitude_m: FloatArray, estimate_altitude: bool,
              heights: tuple[float, float] = ALTITUDE_RANGE_M) -> PlaneFixes:
        """Plots ``(r, psi, h or NaN)`` as plane fixes.

        Known altitude: the exact position at that height. Unknown: at the site's height (the
        slant range taken for the ground range, the seed's convention, whose bias, ``h^2 / 2d``
        flat and ``h^2 / 2d + h d / 2R`` on the earth, a single radar cannot remove), and with
        ``estimate_altitude`` the position as a function of the height (:class:`PlaneFixes`).
        ``heights``: the heights the track may take (:meth:`solver.plots.PlotTable.heights`),
        which bound each plot's reach. One-sigma ellipse: along the ray ``sigma_r |dc/dr|``
        (at most ``sqrt(2 r sigma_r) |dc/dr| d / r`` overhead, :func:`ground_range_error`) and,
        where the altitude is known, the ``hypot`` of that and ``altitude_sigma_m |dc/dh|``
        (:meth:`_height_term`); across ``max(sigma_psi |dc/dpsi|, 1 m)``.
        """
        r = np.asarray(range_m, float)
        psi = np.asarray(azimuth_rad, float)
        n = r.size
        alt = np.asarray(altitude_m, float)
        known = np.isfinite(alt)
        site_h = 0.0 if frame is None else self.site_in(frame)[2]
        h_nom = np.where(known, alt, site_h)
        x0, z0 = self.positions(frame, r, psi, h_nom)
        # central differences: errors O(step^2), far below a millimetre (a step within the
        # slant range: a wild plot 1 m from the radar has a position 0 m from it too)
        dr, dpsi = np.minimum(1.0, 0.5 * r), 1e-6
        xr1, zr1 = self.positions(frame, r + dr, psi, h_nom)
        xr0, zr0 = self.positions(frame, r - dr, psi, h_nom)
        xp1, zp1 = self.positions(frame, r, psi + dpsi, h_nom)
        xp0, zp0 = self.positions(frame, r, psi - dpsi, h_nom)
        d_range = np.column_stack([xr1 - xr0, zr1 - zr0]) / (2 * dr)[:, None]
        d_azimuth = np.column_stack([xp1 - xp0, zp1 - zp0]) / (2 * dpsi)
        len_r = np.hypot(*d_range.T)
        len_c = np.hypot(*d_azimuth.T)
        ray = d_range / np.maximum(len_r, 1e-12)[:, None]
        # ground distance d and the overhead cap of the along-ray error (see ground_range_error)
        d = len_c  # |dc/dpsi| is the ground distance times the plane's scale
        B = ground_range_error(self.sigma_r, r, np.maximum(d, 1e-9)) * len_r * d / r
        B = np.where(len_r * d / r > 0, B, self.sigma_r)
        if self.altitude_sigma_m > 0 and known.any():
            B[known] = np.hypot(B[known], self._height_term(frame, r[known], psi[known],
                                                            alt[known], site_h, d[known],
                                                            (len_r * d / r)[known]))
        A = np.maximum(self.sigma_psi * len_c, 1.0)
        ell = Ellipses(x0, z0, np.arctan2(ray[:, 1], ray[:, 0]), A, np.maximum(B, 1e-3))
        free = ~known & estimate_altitude
        poly = np.zeros((n, 2, ALTITUDE_FIT_DEGREE + 1))
        poly[:, 0, 0], poly[:, 1, 0] = x0, z0
        # the plot's reach: within the track's heights, and within the elevation cap both ways
        # (heights below the site by more than the slant range have no position at all); the
        # general range alone held known heights below -500 m out of every plot's reach (all
        # radar plots dropped as "above 74 deg elevation" at 40-100 km, a tester's)
        h_lo = np.maximum(heights[0], site_h - MAX_ELEVATION_FRACTION * r)
        h_hi = np.minimum(heights[1], site_h + MAX_ELEVATION_FRACTION * r)
        h_hi = np.maximum(h_hi, h_lo + 1e-3)
        h_mid, h_half = (h_hi + h_lo) / 2, (h_hi - h_lo) / 2
        slant = np.where(free, r, 0.0)
        # the exact term's ground distance in plane metres: times the plane's scale there
        # (without it the quintic had to fit (scale - 1) of it: 1-5 m off at 12-20 km from a
        # radar 1,500-2,500 km from the reference, where the docstring promised 0.08-0.21 m;
        # an audit helper)
        ray_k = ray if frame is None else ray * frame.scale(x0, z0)[:, None]
        if free.any():
            poly[free] = _altitude_remainder(self, frame, r[free], psi[free], ray_k[free],
                                             site_h, h_mid[free], h_half[free])
        return PlaneFixes(ell, free, np.where(free[:, None], ray_k, 0.0), slant,
                          np.full(n, site_h), poly, h_mid, h_half, d_range, d_azimuth)

    def _height_term(self, frame: LocalFrame | None, r: FloatArray, psi: FloatArray,
                     h: FloatArray, site_h: float, d: FloatArray, scale: FloatArray
                     ) -> FloatArray:
        """The along-ray sigma of known heights ``h`` with ``altitude_sigma_m``:
        ``sigma_h |dc/dh|``, ``dc/dh`` by central differences (on the earth the curvature
        adds to the height above the radar's horizon), written as :func:`height_error` of the
        effective height ``h_eff = |dc/dh| d_g / scale`` (the flat ``h``; ``d_g`` the ground
        distance) so that it keeps that function's floor overhead."""
        h_rel = h - site_h
        dh = np.clip(0.25 * (r - np.abs(h_rel)), 1e-6, 1.0)
        x1, z1 = self.positions(frame, r, psi, h + dh)
        x0, z0 = self.positions(frame, r, psi, h - dh)
        len_h = np.hypot(x1 - x0, z1 - z0) / (2 * dh)
        safe = np.maximum(scale, 1e-12)
        return height_error(self.altitude_sigma_m, len_h * d / safe**2, d / safe) * scale


def _altitude_remainder(sensor: RadarSensor, frame: LocalFrame | None, r: FloatArray,
                        psi: FloatArray, ray: FloatArray, site_h: float, h_mid: FloatArray,
                        h_half: FloatArray) -> FloatArray:
    """Polynomial (in ``s``, of :data:`ALTITUDE_FIT_DEGREE`) least-squares fit, at ``K + 3``
    Chebyshev nodes, of ``c(h) - ray sqrt(r^2 - (h - h_site)^2)`` per plot: ``(m, 2, K)``
    coefficients of ``s^0 .. s^K-1``."""
    K = ALTITUDE_FIT_DEGREE + 1
    nodes = np.cos(np.pi * (np.arange(K + 3) + 0.5) / (K + 3))
    V = nodes[:, None] ** np.arange(K)[None, :]
    m = r.size
    rem = np.empty((nodes.size, m, 2))
    for j, s in enumerate(nodes):
        h = h_mid + s * h_half
        x, z = sensor.positions(frame, r, psi, h)
        g = np.sqrt(np.maximum(r**2 - (h - site_h) ** 2, 0.0))
        rem[j] = np.column_stack([x, z]) - ray * g[:, None]
    coef, *_ = np.linalg.lstsq(V, rem.reshape(nodes.size, 2 * m), rcond=None)
    return coef.reshape(K, m, 2).transpose(1, 2, 0)


@dataclass(frozen=True)
class PositionSensor:
    """ADS-B / WAM-like positions: latitude, longitude with ``position_sigma_m`` per horizontal
    axis; ``altitude_sigma_m`` for the altitude its plots may carry; ``estimate_bias``: estimate
    its time offset (a report late by ``b_t`` s gives where the aircraft was ``b_t`` s before;
    the latency of ADS-B) against the other sensors, with the prior ``bias_prior.time_s``."""

    id: str
    position_sigma_m: float
    altitude_sigma_m: float = 15.0
    estimate_bias: bool = field(default=False, kw_only=True)
    bias_prior: BiasPrior = field(default_factory=BiasPrior, kw_only=True)
    kind: ClassVar[str] = "position"

    def validate_at(self, loc: tuple[str | int, ...]) -> None:
        for name in ("position_sigma_m", "altitude_sigma_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 1e-3 <= value <= MAX_RANGE_ERROR_M):
                raise InputError((*loc, name), "must be a finite number from 0.001 to "
                                 f"{MAX_RANGE_ERROR_M:g} m")

    def measure(self, frame: LocalFrame, x: FloatArray, z: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
        """Predicted ``(lat_deg, lon_deg)``."""
        return frame.to_geodetic(x, z)

    def fixes(self, frame: LocalFrame, lat_deg: FloatArray, lon_deg: FloatArray) -> PlaneFixes:
        """Plane positions with a circle of radius ``position_sigma_m`` times the plane's scale
        at the plot, in plane metres as the radars' ellipses (taken as 1 it left every
        covariance in ground metres: with the reference 4,300 km away, scale 1.122, the states'
        sigmas grew 1.013 times where x, z, vx, vz grew 1.122 times; a tester's)."""
        x, z = frame.to_plane(lat_deg, lon_deg)
        n = x.size
        sig = float(self.position_sigma_m) * np.asarray(frame.scale(x, z), float)
        ell = Ellipses(x, z, np.zeros(n), sig, sig)
        poly = np.zeros((n, 2, ALTITUDE_FIT_DEGREE + 1))
        poly[:, 0, 0], poly[:, 1, 0] = x, z
        zero2 = np.zeros((n, 2))
        return PlaneFixes(ell, np.zeros(n, bool), zero2, np.zeros(n), np.zeros(n), poly,
                          np.zeros(n), np.ones(n), zero2, zero2.copy())


Sensor = RadarSensor | PositionSensor
