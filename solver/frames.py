"""The earth: WGS-84 geodetic coordinates, a sensor's local east-north-up frame, and the local
conformal plane in which trajectories are reconstructed. All transformations are PROJ's (via
pyproj), none hand-written.

- :class:`LocalFrame`: the oblique stereographic plane (PROJ ``sterea``, the double projection
  ARTAS and TRES use for a system plane) tangent at a reference point; ``x`` north, ``z``
  east in metres, so the single-radar flat frame of the seed is the special case of a radar at
  the reference point with the earth taken flat. Conformal: angles are kept, and the scale
  grows as ``1 + d^2 / (4 R^2)`` with the distance ``d`` from the reference (+1.2e-4 at 175 km).
- :func:`enu_to_geodetic` / :func:`geodetic_to_enu`: a site's topocentric frame (PROJ
  ``topocentric`` over geocentric ``cart``), exact on the ellipsoid: slant range and azimuth of
  a radar plot are measured in it.
- :func:`radar_plot_position`: where a plot ``(slant range, azimuth)`` of a radar at a site
  lies when the aircraft's height above the ellipsoid is ``h`` (the elevation that meets ``h``,
  found by Newton's method on PROJ's exact heights).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from pyproj import CRS, Geod, Proj, Transformer

from .inputs import MAX_LON_DEG, FloatArray, InputError, wrap_lon

_GEOD = Geod(ellps="WGS84")


@cache
def _plane(lat0: float, lon0: float) -> tuple[Transformer, Transformer]:
    """(geodetic -> plane, plane -> geodetic) transformers of the sterea plane at (lat0, lon0)."""
    crs = CRS.from_proj4(f"+proj=sterea +lat_0={lat0!r} +lon_0={lon0!r} +k=1 +x_0=0 +y_0=0 "
                         "+ellps=WGS84 +units=m +no_defs")
    geo = CRS.from_epsg(4326)
    return (Transformer.from_crs(geo, crs, always_xy=True),
            Transformer.from_crs(crs, geo, always_xy=True))


@cache
def _plane_proj(lat0: float, lon0: float) -> Proj:
    """The sterea plane of :func:`_plane` as a ``Proj`` (for its scale factors)."""
    return Proj(_plane(lat0, lon0)[0].target_crs)


@cache
def _topocentric(lat0: float, lon0: float, h0: float) -> Transformer:
    """(lon, lat, h) <-> (east, north, up) about a site (forward: geodetic to ENU)."""
    return Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={h0!r}")


def check_lat_lon(lat: FloatArray | float, lon: FloatArray | float,
                  loc: tuple[str | int, ...]) -> None:
    """Raise :class:`InputError` at ``loc`` (``+ (index,)`` for arrays) for a latitude outside
    [-90, 90] or a longitude outside [-360, 360] (:data:`solver.inputs.MAX_LON_DEG`) or
    non-finite values."""
    lat_a, lon_a = np.atleast_1d(np.asarray(lat, float)), np.atleast_1d(np.asarray(lon, float))
    for name, arr, lo, hi in (("lat_deg", lat_a, -90.0, 90.0),
                              ("lon_deg", lon_a, -MAX_LON_DEG, MAX_LON_DEG)):
        bad = np.flatnonzero(~(np.isfinite(arr) & (arr >= lo) & (arr <= hi)))
        if bad.size:
            where = loc if np.ndim(lat) == 0 else (*loc[:1], int(bad[0]), *loc[1:])
            raise InputError((*where, name), f"must be a finite number in [{lo:g}, {hi:g}] "
                             f"({arr[bad[0]]})")


@dataclass(frozen=True)
class LocalFrame:
    """Oblique stereographic plane tangent to WGS-84 at ``(lat_deg, lon_deg)``; ``x`` north,
    ``z`` east (m). Picklable (the PROJ transformers are rebuilt per process and cached)."""

    lat_deg: float
    lon_deg: float

    def validate(self, loc: tuple[str | int, ...] = ("reference",)) -> None:
        check_lat_lon(self.lat_deg, self.lon_deg, loc)
        if abs(self.lat_deg) > 89.9:
            raise InputError((*loc, "lat_deg"), "must be within 89.9 degrees of the equator "
                             "(the plane is undefined at a pole)")

    def to_plane(self, lat_deg: FloatArray, lon_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Geodetic degrees -> plane ``(x north, z east)`` (m)."""
        east, north = _plane(self.lat_deg, self.lon_deg)[0].transform(lon_deg, lat_deg)
        return np.asarray(north, float), np.asarray(east, float)

    def to_geodetic(self, x: FloatArray, z: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Plane ``(x north, z east)`` -> geodetic ``(lat_deg, lon_deg)``, the longitude in
        [-180, 180) as the plots' are read (PROJ gave -180.00000000000028 near the
        antimeridian)."""
        lon, lat = _plane(self.lat_deg, self.lon_deg)[1].transform(z, x)
        return np.asarray(lat, float), np.asarray(wrap_lon(lon), float)

    def _factors(self, x: FloatArray, z: FloatArray) -> Any:
        """PROJ's factors of the plane at ``(x, z)`` (scale, meridian convergence)."""
        lat, lon = self.to_geodetic(x, z)
        return _plane_proj(self.lat_deg, self.lon_deg).get_factors(lon, lat)

    def scale(self, x: FloatArray, z: FloatArray) -> FloatArray:
        """The plane's scale factor at ``(x, z)`` (PROJ's; conformal: one in every direction):
        plane distances and speeds there are this many times the ground's (1 at the tangent
        point, about ``1 + (r / 2R)^2`` at a distance ``r``)."""
        return np.asarray(self._factors(x, z).meridional_scale, float)

    def on_earth(self, x: FloatArray, z: FloatArray, heading: FloatArray, speed: FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
        """A motion in the plane at ``(x, z)`` (heading in rad clockwise from the plane's ``x``
        axis, speed in m/s) on the earth: the heading from true north (PROJ's meridian
        convergence added: :meth:`north_azimuth` taken off) and the ground speed (the plane's
        speed over its :meth:`scale`), from one PROJ evaluation."""
        f = self._factors(x, z)
        return (np.asarray(heading, float) + np.deg2rad(np.asarray(f.meridian_convergence,
                                                                   float)),
                np.asarray(speed, float) / np.asarray(f.meridional_scale, float))

    def ground_distance(self, lat_deg: FloatArray, lon_deg: FloatArray) -> FloatArray:
        """Geodesic distance (m, WGS-84; PROJ's ``Geod``) from the reference to points."""
        lat, lon = np.broadcast_arrays(np.asarray(lat_deg, float), np.asarray(lon_deg, float))
        _, _, d = _GEOD.inv(np.full(lat.shape, self.lon_deg), np.full(lat.shape, self.lat_deg),
                            lon, lat)
        return np.asarray(d, float)

    def north_azimuth(self, x: FloatArray, z: FloatArray) -> FloatArray:
        """Angle (rad, clockwise) from the plane's ``x`` axis to true north at ``(x, z)``: the
        meridian convergence, which turns a radar's true-north azimuths into plane bearings."""
        lat, lon = self.to_geodetic(x, z)
        dlat = 1e-4  # degrees: about 11 m north
        xn, zn = self.to_plane(np.minimum(lat + dlat, 90.0), lon)
        return np.arctan2(zn - z, xn - x)


def geodetic_to_enu(site: tuple[float, float, float], lat_deg: FloatArray, lon_deg: FloatArray,
                    h_m: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Geodetic points -> east, north, up (m) in the topocentric frame of ``site``
    ``(lat_deg, lon_deg, height_m)``."""
    e, n, u = _topocentric(*site).transform(lon_deg, lat_deg, h_m)
    return np.asarray(e, float), np.asarray(n, float), np.asarray(u, float)


def enu_to_geodetic(site: tuple[float, float, float], e: FloatArray, n: FloatArray,
                    u: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of :func:`geodetic_to_enu`: ``(lat_deg, lon_deg, h_m)``."""
    lon, lat, h = _topocentric(*site).transform(e, n, u, direction="INVERSE")
    return np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float)


def slant_and_azimuth(site: tuple[float, float, float], lat_deg: FloatArray, lon_deg: FloatArray,
                      h_m: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """What a radar at ``site`` measures of points at ``(lat, lon, h)``: slant range (m),
    azimuth clockwise from the site's true north in [0, 2 pi) and elevation (rad)."""
    e, n, u = geodetic_to_enu(site, lat_deg, lon_deg, h_m)
    r = np.sqrt(e * e + n * n + u * u)
    return r, np.mod(np.arctan2(e, n), 2 * np.pi), np.arcsin(np.clip(u / np.maximum(r, 1e-9),
                                                                     -1, 1))


WGS84_MEAN_RADIUS = 6_371_008.8  # m, for the first guess of the elevation only


def radar_plot_position(site: tuple[float, float, float], range_m: FloatArray,
                        azimuth_rad: FloatArray, h_m: FloatArray, iterations: int = 4
                        ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Geodetic position ``(lat_deg, lon_deg, elevation_rad)`` of plots at slant range ``r`` and
    azimuth ``psi`` from ``site`` whose height above the ellipsoid is ``h``.

    The elevation ``eps`` solves ``height(site + r (sin psi cos eps, cos psi cos eps, sin eps)) =
    h``: first guess on a sphere, ``sin eps = ((R + h)^2 - (R + h0)^2 - r^2) / (2 r (R + h0))``,
    then Newton steps with ``d height / d eps ~ r cos eps`` on PROJ's exact heights (each step
    gains about 4 digits; 4 steps leave < 1 mm). Heights out of reach of the slant range are
    clipped to the nearest reachable elevation (+-90 degrees).
    """
    r = np.asarray(range_m, float)
    psi = np.asarray(azimuth_rad, float)
    h = np.broadcast_to(np.asarray(h_m, float), r.shape)
    R0 = WGS84_MEAN_RADIUS + site[2]
    s = ((WGS84_MEAN_RADIUS + h) ** 2 - R0**2 - r**2) / (2 * r * R0)
    eps = np.arcsin(np.clip(s, -1.0, 1.0))
    for _ in range(iterations):
        ce = np.cos(eps)
        _, _, hh = enu_to_geodetic(site, r * np.sin(psi) * ce, r * np.cos(psi) * ce,
                                   r * np.sin(eps))
        eps = np.clip(eps - (hh - h) / np.maximum(r * ce, 1e-3), -np.pi / 2, np.pi / 2)
    ce = np.cos(eps)
    lat, lon, _ = enu_to_geodetic(site, r * np.sin(psi) * ce, r * np.cos(psi) * ce,
                                  r * np.sin(eps))
    return lat, lon, eps
