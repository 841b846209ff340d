"""Inputs shared by the reconstruction and the filters: radar accuracies, plots, bounds.

SI units and radians inside the package; degrees appear only at the HTTP edge.
Frame (see spec/reconstruction.md section 1): ``x`` north, ``z`` east, azimuth and heading
clockwise from north, so a plot at ``(r, psi)`` lies at ``(r cos psi, r sin psi)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
MAX_RANGE_M = 1e7  # 10 000 km: beyond any radar's horizon
# Accuracies and bounds no sensor or aircraft has; far beyond them the solvers' weights and
# scaling break down (a range sigma of 1e200 m, a speed bound of 1e9 m/s made them fail).
MAX_RANGE_ERROR_M = 1e5  # a radar's range error or sigma, and a position sensor's sigma
MAX_AZIMUTH_ERROR_RAD = float(np.deg2rad(30.0))
MAX_ALTITUDE_M = 1e5  # a radar's max_altitude_m
MAX_ALTITUDE_SIGMA_M = 1e4  # a radar's altitude_sigma_m
MIN_ALTITUDE_SIGMA_M = 1e-3  # a radar's altitude_sigma_m when not 0 (as a position sensor's)
MAX_ACCELERATION = 100.0  # m/s^2 (10 g): the bounds on u and w
MAX_SPEED = 2000.0  # m/s: the bound on v
MAX_AZIMUTH_DEG = 1e6  # a plot's azimuth: normalised to [0, 360) to 1e-10 degrees
MAX_LON_DEG = 360.0
"""A longitude (degrees) is accepted in [-MAX_LON_DEG, MAX_LON_DEG] (east and west of either
convention, [-180, 180] or [0, 360)) and a plot's wrapped to [-180, 180) (:func:`wrap_lon`).
It was [-180, 360]: a fix at -180.0006 (a hair west of the antimeridian, as a conversion with
noise writes it) was a bad value, 180.0006 and 359.9 accepted (a tester's)."""


class InputError(ValueError):
    """Bad input, located by a field path such as ``("plots", 17, "t")``.

    The service turns it into a 422 whose message names the field and index.
    """

    def __init__(self, loc: tuple[str | int, ...], message: str):
        self.loc = loc
        self.message = message
        super().__init__(f"{format_loc(loc)} {message}")

    def __reduce__(self) -> tuple[type[InputError], tuple[tuple[str | int, ...], str]]:
        """Pickle by ``(loc, message)``: the default rebuilds from ``args`` (the formatted text
        alone) and fails, so the error could not cross a process boundary."""
        return (type(self), (self.loc, self.message))


def format_loc(loc: tuple[str | int, ...]) -> str:
    """``("plots", 17, "t")`` -> ``plots[17].t``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else part
    return out


@dataclass(frozen=True)
class Radar:
    """A priori accuracies of one radar.

    ``range_error_m`` and ``azimuth_error_rad`` are the maximum errors (``eps_r``, ``eps_psi``)
    that size the uncertainty ellipses; the sigmas are standard deviations for statistical
    weighting (default one third of the maximum errors). ``max_altitude_m`` and
    ``max_elevation_rad`` (``h_max``, ``alpha_max``) drive the unknown-altitude correction.
    ``altitude_sigma_m``: the standard deviation of the plots' altitude as a height above the
    radar (0: exact, the default); a Mode C flight level is a pressure altitude, some 100-300
    m from the geometric height (temperature, QNH), which moves a plot's ground range by that
    times ``h / d``: the plot's along-ray sigma grows by it (:func:`geometry.height_error`;
    three times it in the maximum errors).
    """

    range_error_m: float
    azimuth_error_rad: float
    # keyword-only: positionally a sigma and an altitude are too easy to swap
    range_sigma_m: float | None = field(default=None, kw_only=True)
    azimuth_sigma_rad: float | None = field(default=None, kw_only=True)
    max_altitude_m: float = field(default=0.0, kw_only=True)
    max_elevation_rad: float = field(default=0.0, kw_only=True)
    altitude_sigma_m: float = field(default=0.0, kw_only=True)

    @property
    def sigma_r(self) -> float:
        """Range standard deviation (m)."""
        return self.range_sigma_m if self.range_sigma_m is not None else self.range_error_m / 3

    @property
    def sigma_psi(self) -> float:
        """Azimuth standard deviation (rad)."""
        if self.azimuth_sigma_rad is not None:
            return self.azimuth_sigma_rad
        return self.azimuth_error_rad / 3

    def validate(self) -> None:
        """Raise :class:`InputError` for non-finite, negative or zero accuracies, and for
        accuracies no radar has (beyond :data:`MAX_RANGE_ERROR_M`, :data:`MAX_AZIMUTH_ERROR_RAD`:
        the weights they give are below the solvers' precision)."""
        # smallest accuracy a radar can claim: 1 mm in range, 1 nrad in azimuth
        checks: list[tuple[str, float | None, float, float]] = [
            ("range_error_m", self.range_error_m, 1e-3, MAX_RANGE_ERROR_M),
            ("azimuth_error_rad", self.azimuth_error_rad, 1e-9, MAX_AZIMUTH_ERROR_RAD),
            ("range_sigma_m", self.range_sigma_m, 1e-3, MAX_RANGE_ERROR_M),
            ("azimuth_sigma_rad", self.azimuth_sigma_rad, 1e-9, MAX_AZIMUTH_ERROR_RAD),
            ("max_altitude_m", self.max_altitude_m, 0.0, MAX_ALTITUDE_M),
            ("max_elevation_rad", self.max_elevation_rad, 0.0, np.inf),
            ("altitude_sigma_m", self.altitude_sigma_m, 0.0, MAX_ALTITUDE_SIGMA_M),
        ]
        for name, value, least, most in checks:
            if value is None:
                continue
            if not np.isfinite(value):
                raise InputError(("radar", name), "must be a finite number")
            if value < least or (least == 0 and value < 0):
                raise InputError(("radar", name), f"must be positive (at least {least:g})"
                                 if least > 0 else "must not be negative")
            if value > most:
                limit = (f"{np.rad2deg(most):g} degrees" if name.endswith("_rad")
                         else f"{most:g} m")
                raise InputError(("radar", name), f"must be at most {limit}")
        if self.max_elevation_rad >= np.pi / 2:
            raise InputError(("radar", "max_elevation_rad"), "must be below 90 degrees")
        if 0 < self.altitude_sigma_m < MIN_ALTITUDE_SIGMA_M:  # 1e-155 m made a singular smoother
            raise InputError(("radar", "altitude_sigma_m"), "must be 0 (the altitudes exact) or "
                             f"at least {MIN_ALTITUDE_SIGMA_M:g} m")


def wrap_azimuth(azimuth_rad: ArrayLike, loc: tuple[str | int, ...] = ("plots",)
                 ) -> FloatArray:
    """Azimuths (any real value, spec api.md) normalised to [0, 2 pi); :class:`InputError` at
    the first one beyond :data:`MAX_AZIMUTH_DEG` degrees, where the normalisation loses
    precision (at 1e300 degrees nothing of the angle is left)."""
    a = np.asarray(azimuth_rad, dtype=float)
    bad = np.flatnonzero(np.abs(a) > np.deg2rad(MAX_AZIMUTH_DEG))
    if bad.size:
        raise InputError((*loc, int(bad[0]), "azimuth_rad"), "must be within "
                         f"+-{MAX_AZIMUTH_DEG:g} degrees ({np.rad2deg(a[bad[0]]):g}); it is "
                         "normalised to [0, 360)")
    return np.mod(a, 2 * np.pi)


def wrap_lon(lon_deg: FloatArray) -> FloatArray:
    """Longitudes wrapped to [-180, 180) (NaN stays NaN): ``(lon + 180) mod 360 - 180`` for
    those outside, those inside as they are (the modulo moved 179.9994 by 4e-14)."""
    lon = np.asarray(lon_deg, dtype=float)
    inside = (lon >= -180.0) & (lon < 180.0)
    return np.where(inside | np.isnan(lon), lon, np.mod(lon + 180.0, 360.0) - 180.0)


@dataclass(frozen=True)
class Bounds:
    """Box bounds of the aircraft model: lateral ``u`` and longitudinal ``w`` accelerations
    (m/s^2) and speed ``v`` (m/s). Defaults are the seed's real-data values."""

    u: tuple[float, float] = (-7.0, 7.0)
    w: tuple[float, float] = (-2.0, 3.0)
    v: tuple[float, float] = (30.0, 330.0)

    def validate(self) -> None:
        """Raise :class:`InputError` unless ``lo < hi``, ``w_lo <= 0 <= w_hi``, ``v_lo > 0``,
        and the bounds lie within :data:`MAX_ACCELERATION` and :data:`MAX_SPEED` (no aircraft
        goes beyond; far beyond, the NLPs' scaling fails)."""
        for name in ("u", "w", "v"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi)):
                raise InputError(("bounds", name), "must be finite numbers")
            if not lo < hi:
                raise InputError(("bounds", name), f"is inverted or empty: [{lo}, {hi}]")
            most, unit = (MAX_SPEED, "m/s") if name == "v" else (MAX_ACCELERATION, "m/s^2")
            if max(abs(lo), abs(hi)) > most:
                raise InputError(("bounds", name), f"must lie within [-{most:g}, {most:g}] "
                                 f"{unit}: [{lo:g}, {hi:g}]")
        if not self.u[0] <= 0 <= self.u[1]:
            raise InputError(("bounds", "u"), "must contain 0 (straight flight)")
        if not self.w[0] <= 0 <= self.w[1]:
            raise InputError(("bounds", "w"), "must contain 0 (constant speed)")
        if self.v[0] < 1.0:
            raise InputError(("bounds", "v"), "lower speed bound must be at least 1 m/s "
                             "(the model turns by u / v)")
        for name in ("u", "w"):
            lo, hi = getattr(self, name)
            if hi - lo < 1e-6:
                raise InputError(("bounds", name), "must span at least 1e-6 m/s^2")


@dataclass(frozen=True)
class Plots:
    """Radar plots of one aircraft: times (s, strictly increasing), slant ranges (m, > 0),
    azimuths (rad, clockwise from north, normalised to [0, 2 pi)), and optional altitudes
    (m; NaN where unknown)."""

    t: FloatArray
    range_m: FloatArray
    azimuth_rad: FloatArray
    altitude_m: FloatArray | None = field(default=None)

    @classmethod
    def from_arrays(
        cls,
        t: ArrayLike,
        range_m: ArrayLike,
        azimuth_rad: ArrayLike,
        altitude_m: ArrayLike | None = None,
    ) -> Plots:
        """Build validated plots from array-likes (see :meth:`validate`)."""
        alt = None if altitude_m is None else np.asarray(altitude_m, dtype=float).copy()
        if alt is not None and np.all(np.isnan(alt)):
            alt = None
        plots = cls(
            t=np.asarray(t, dtype=float).copy(),
            range_m=np.asarray(range_m, dtype=float).copy(),
            azimuth_rad=wrap_azimuth(azimuth_rad),
            altitude_m=alt,
        )
        plots.validate()
        return plots

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def validate(self) -> None:
        """Raise :class:`InputError` naming the first offending plot and field."""
        n = self.t.shape[0]
        arrays = {"t": self.t, "range_m": self.range_m, "azimuth_rad": self.azimuth_rad}
        if self.altitude_m is not None:
            arrays["altitude_m"] = self.altitude_m
        for name, arr in arrays.items():
            if arr.ndim != 1 or arr.shape[0] != n:
                raise InputError(("plots",), f"field {name} has {arr.shape} values, expected {n}")
        if n == 0:
            raise InputError(("plots",), "must contain at least one plot")
        for name in ("t", "range_m", "azimuth_rad"):
            bad = np.flatnonzero(~np.isfinite(arrays[name]))
            if bad.size:
                raise InputError(("plots", int(bad[0]), name), "must be a finite number")
        bad = np.flatnonzero(self.range_m <= 0)
        if bad.size:
            raise InputError(("plots", int(bad[0]), "range_m"), "must be positive")
        bad = np.flatnonzero(self.range_m > MAX_RANGE_M)
        if bad.size:
            raise InputError(("plots", int(bad[0]), "range_m"),
                             f"must be below {MAX_RANGE_M:g} m (no radar sees further)")
        if self.altitude_m is not None:
            alt = self.altitude_m
            bad = np.flatnonzero(np.isinf(alt) | (alt < 0) | (alt >= self.range_m))
            if bad.size:
                i = int(bad[0])
                raise InputError(("plots", i, "altitude_m"),
                                 f"must be finite, >= 0 and below the slant range ({alt[i]})")
        bad = np.flatnonzero(np.diff(self.t) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise InputError(("plots", i, "t"), f"is not after plots[{i - 1}].t "
                             f"({float(self.t[i]):g} <= {float(self.t[i - 1]):g})")


ArrayLike = FloatArray | list[float] | tuple[float, ...]
