"""Polar measurement model: plots ``(d, psi)`` with ``d`` the ground range where the altitude is
known (``sqrt(r^2 - h^2)``, sigma :func:`~solver.geometry.ground_range_sigma`: ``sigma_r r / d``
and the radar's ``altitude_sigma_m``), else the slant range (sigma ``sigma_r``).

Two ways to use them in a Cartesian filter:

- ``"converted"``: the plot point ``(d cos psi, d sin psi)`` as a linear position measurement with
  the converted covariance ``R = J diag(sigma_d^2, sigma_psi^2) J^T``, ``J`` the polar-to-Cartesian
  Jacobian at the predicted position (evaluating it at the measured point correlates ``R`` with
  the error and biases the update; at the prediction it does not).
- ``"ekf"``: the extended Kalman update with ``h(x) = (hypot(x, z), atan2(z, x))`` linearised at
  the prediction, azimuth innovation wrapped to ``(-pi, pi]``; iterated (relinearised at the
  updated position) while the linearisation error there exceeds :data:`LINEARISATION_TOLERANCE`
  of the plot's sigmas (after a long gap; see there).

The Cartesian filters default to ``"ekf"``: on the benchmark radars (``r sigma_psi^2 / sigma_r``
below 0.05) both give the same RMS to 1 m; on a stress radar (50 m, 0.03 rad, nonlinearity up to
3.6) the EKF update is 6-12 % more accurate and its covariance more honest, because the
converted ellipse cannot follow the curved (banana-shaped) polar uncertainty whose curvature
offset ``r sigma_psi^2 / 2`` is then comparable to the range sigma (benchmarks/filters_seed001.py
section 3). Same cost.

and, for the per-coordinate filters, conversion of a polar state ``(d, d', psi, psi')`` to
``(x, z, vx, vz)`` with its covariance (:func:`polar_state_to_cartesian`).

Several sensors (:class:`SensorPlots`, built from a :class:`~solver.plots.PlotTable`): the plots
of every sensor in time order, each with its own measurement model, as Stone Soup's detections.
A plot is either *polar* about the plane's origin (radars at the origin of the flat plane: the
model above, unchanged) or a *linear position fix* ``z = p + v``, ``v ~ N(0, R)``: the plot's
plane position from ``table.fixes()`` (a radar plot placed through the curved earth, an ADS-B
position projected) with ``R = B^2 e_r e_r^T + A^2 e_c e_c^T``, ``e_r = (cos psi, sin psi)``,
``e_c = (-sin psi, cos psi)`` from its one-sigma ellipse (``B`` along the sensor's ray, ``A``
across). A radar plot without altitude is placed at the altitude of the table's other plots
(Mode C of another radar, ADS-B), interpolated in time, when some carry one
(:func:`borrowed_altitude`), else at its site's height (the slant range taken for the ground
range, as for the single radar, with its ``h^2 / 2r`` bias): the filters' 2-D states cannot
estimate altitude.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..geometry import ground_range, ground_range_sigma
from ..inputs import FloatArray, Plots, Radar

if TYPE_CHECKING:
    from ..plots import PlotTable

MEASUREMENT_MODES = ("converted", "ekf")

LINEARISATION_TOLERANCE = 0.1
"""The EKF update is iterated (the iterated EKF: Gauss-Newton on the posterior mode) while
``h(x_new) - h(x_lin) - J (x_new - x_lin)``, the polar model's linearisation error between the
point it was linearised at and the updated position, exceeds this fraction of the plot's sigma in
range or azimuth. Tracking, the first update stays far below it (at 100 km the second-order range
term of a 500-m cross-range step is 1.3 m; the first plots of a track, whose velocity is unknown,
iterate once or twice); after a gap in which the aircraft held, the prediction can be tens of km
from the plot: the single update left the state 32 km from the plot after 300 s and 225 km
after 900 s (seed track), with a reported sigma of 0.4-1 km."""

MAX_LINEARISATIONS = 20
"""At most this many linearisations (updates) per plot and model."""


@dataclass(frozen=True)
class PolarPlots:
    """Measurements in the horizontal plane: times, ground ranges ``d`` with their sigmas, azimuths
    (unwrapped, so consecutive values never jump by 2 pi) and the azimuth sigma."""

    t: FloatArray
    d: FloatArray
    sigma_d: FloatArray
    psi: FloatArray
    sigma_psi: float

    @classmethod
    def from_plots(cls, plots: Plots, radar: Radar) -> PolarPlots:
        d = ground_range(plots)
        h = 0.0 if plots.altitude_m is None else np.nan_to_num(plots.altitude_m, nan=0.0)
        sigma_d = ground_range_sigma(radar.sigma_r, plots.range_m, d, radar.altitude_sigma_m, h)
        return cls(t=np.asarray(plots.t, dtype=float), d=d, sigma_d=sigma_d,
                   psi=np.unwrap(plots.azimuth_rad), sigma_psi=float(radar.sigma_psi))

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def points(self) -> FloatArray:
        """``(n, 2)`` plot points ``(d cos psi, d sin psi)``."""
        return np.column_stack([self.d * np.cos(self.psi), self.d * np.sin(self.psi)])

    def converted_cov(self, at: FloatArray | None = None) -> FloatArray:
        """``(n, 2, 2)`` converted covariances, Jacobian at positions ``at`` (default: plots)."""
        if at is None:
            d, psi = self.d, self.psi
        else:
            d, psi = np.hypot(at[..., 0], at[..., 1]), np.arctan2(at[..., 1], at[..., 0])
        return converted_cov(d, psi, self.sigma_d, self.sigma_psi)


def converted_cov(d: FloatArray, psi: FloatArray, sigma_d: FloatArray,
                  sigma_psi: float) -> FloatArray:
    """``J diag(sigma_d^2, sigma_psi^2) J^T`` with ``J = [[cos, -d sin], [sin, d cos]]``."""
    c, s = np.cos(psi), np.sin(psi)
    vr, vc = sigma_d**2, (d * sigma_psi) ** 2
    R = np.empty((*np.shape(d), 2, 2))
    R[..., 0, 0] = c * c * vr + s * s * vc
    R[..., 1, 1] = s * s * vr + c * c * vc
    R[..., 0, 1] = R[..., 1, 0] = s * c * (vr - vc)
    return R


def polar_innovation(pos: FloatArray, d: float, psi: float) -> tuple[FloatArray, FloatArray]:
    """EKF pieces at predicted position ``pos``: innovation ``(d - |pos|, wrap(psi - atan2))`` and
    the ``2 x 2`` Jacobian of ``(d, psi)`` with respect to ``(x, z)``."""
    x, z = pos
    rho2 = x * x + z * z
    rho = np.sqrt(rho2)
    dpsi = np.mod(psi - np.arctan2(z, x) + np.pi, 2 * np.pi) - np.pi
    nu = np.array([d - rho, dpsi])
    J = np.array([[x / rho, z / rho], [-z / rho2, x / rho2]])
    return nu, J


def polar_state_to_cartesian(m: FloatArray, P: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(n, 4)`` polar states ``(d, d', psi, psi')`` and ``(n, 4, 4)`` covariances to
    ``(x, z, vx, vz)`` and first-order covariances ``J P J^T``."""
    d, dd, psi, dpsi = m.T
    c, s = np.cos(psi), np.sin(psi)
    out = np.column_stack([d * c, d * s, dd * c - d * dpsi * s, dd * s + d * dpsi * c])
    J = np.zeros((m.shape[0], 4, 4))
    J[:, 0, 0], J[:, 0, 2] = c, -d * s
    J[:, 1, 0], J[:, 1, 2] = s, d * c
    J[:, 2, 0], J[:, 2, 1], J[:, 2, 2], J[:, 2, 3] = -dpsi * s, c, -dd * s - d * dpsi * c, -d * s
    J[:, 3, 0], J[:, 3, 1], J[:, 3, 2], J[:, 3, 3] = dpsi * c, s, dd * c - d * dpsi * s, d * c
    return out, J @ P @ np.transpose(J, (0, 2, 1))


@dataclass(frozen=True)
class SensorPlots:
    """The plots of one or several sensors in time order (ties: table order), each polar about
    the plane's origin (``polar[k]``: ``d``, ``sigma_d``, ``psi``, ``sigma_psi`` per plot) or a
    linear position fix (``centre[k]`` with covariance ``cov[k]``). ``rows[k]`` is the table row
    of measurement ``k``, ``sensor[k]`` its sensor's index (``n_sensors`` sensors). For polar
    plots ``centre`` is the plot point and ``cov`` its converted covariance at the plot.

    Same interface as :class:`PolarPlots` for the Cartesian filters (``t``, ``points()``,
    ``converted_cov()``, :func:`~.kalman.position_update`)."""

    t: FloatArray
    rows: np.ndarray
    sensor: np.ndarray
    n_sensors: int
    polar: np.ndarray
    d: FloatArray
    sigma_d: FloatArray
    psi: FloatArray
    sigma_psi: FloatArray
    centre: FloatArray
    cov: FloatArray

    @classmethod
    def from_table(cls, table: PlotTable) -> SensorPlots:
        """Measurements of every row of ``table`` in ``table.time_order()``; radar rows of a flat
        table (no frame: radars at the origin) are polar, all others fixes (``table.fixes()``)."""
        from ..sensors import RadarSensor

        order = np.asarray(table.time_order())
        n = len(table)
        is_radar = np.asarray(table.radar_rows(), dtype=bool)
        polar = is_radar & (table.frame is None)
        r, h = table.range_m, table.altitude_m
        d = np.where(np.isfinite(h), np.sqrt(np.maximum(r**2 - np.nan_to_num(h) ** 2, 0.0)), r)
        sig_r = np.array([s.sigma_r if isinstance(s, RadarSensor) else np.nan
                          for s in table.sensors])[table.sensor]
        sig_h = np.array([s.altitude_sigma_m if isinstance(s, RadarSensor) else 0.0
                          for s in table.sensors])[table.sensor]
        sig_psi = np.array([s.sigma_psi if isinstance(s, RadarSensor) else np.nan
                            for s in table.sensors])[table.sensor]
        d_safe = np.where(polar, d, 1.0)
        sigma_d = np.where(polar, ground_range_sigma(sig_r, r, d_safe, sig_h, np.nan_to_num(h)),
                           np.nan)
        d, psi = np.where(polar, d, np.nan), np.where(polar, table.azimuth_rad, np.nan)
        sig_psi = np.where(polar, sig_psi, np.nan)
        centre, cov = np.empty((n, 2)), np.empty((n, 2, 2))
        if polar.any():
            dp, pp = d[polar], psi[polar]
            centre[polar] = np.column_stack([dp * np.cos(pp), dp * np.sin(pp)])
            cov[polar] = converted_cov(dp, pp, sigma_d[polar], sig_psi[polar])
        if not polar.all():
            fixes = table.fixes()
            ell = fixes.ellipses
            fix = ~polar
            centre[fix] = np.column_stack([ell.cx, ell.cz])[fix]
            h = borrowed_altitude(table)
            moved = fixes.altitude_free & np.isfinite(h)
            if moved.any():  # within the heights the fix's altitude model covers
                h = np.clip(np.nan_to_num(h), fixes.h_mid - fixes.h_half,
                            fixes.h_mid + fixes.h_half)
                centre[moved] = fixes.centre_at(h)[moved]
            cov[fix] = ellipse_cov(ell.psi[fix], ell.A[fix], ell.B[fix])
        return cls(t=np.asarray(table.t, float)[order], rows=order,
                   sensor=np.asarray(table.sensor)[order], n_sensors=len(table.sensors),
                   polar=polar[order], d=d[order], sigma_d=sigma_d[order], psi=psi[order],
                   sigma_psi=sig_psi[order], centre=centre[order], cov=cov[order])

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def points(self) -> FloatArray:
        """``(n, 2)`` plot positions in the plane (fix centres, polar plot points)."""
        return self.centre

    def converted_cov(self, at: FloatArray | None = None) -> FloatArray:
        """``(n, 2, 2)`` covariances of :meth:`points`; with positions ``at`` the polar plots'
        Jacobian is taken there (fixes keep their own)."""
        if at is None or not self.polar.any():
            return self.cov
        out = self.cov.copy()
        p = self.polar
        a = np.asarray(at)[p]
        out[p] = converted_cov(np.hypot(a[:, 0], a[:, 1]), np.arctan2(a[:, 1], a[:, 0]),
                               self.sigma_d[p], self.sigma_psi[p])
        return out

    def same_instant(self) -> np.ndarray:
        """``(n,)`` index of the last measurement at the same time as each (ties grouped)."""
        n = len(self)
        last = np.flatnonzero(np.append(np.diff(self.t) > 0, True))
        return last[np.searchsorted(last, np.arange(n))]


def at_estimated_heights(table: PlotTable, h: FloatArray | None) -> PlotTable:
    """``table`` with its radar plots' unknown altitudes set to ``h`` (per row: the
    reconstruction's estimated heights), kept within 0.95 of each plot's slant range of its
    radar's height. The recursive filters place a radar plot without altitude at the
    radar's height, and with no other sensor's altitude to borrow (radars without Mode C)
    that is ``h^2 / 2r`` off: 800 m in the median, 7 km near a radar, measured on a
    two-radar track at 10 km. Unchanged without ``h`` (no altitude estimated)."""
    from ..sensors import RadarSensor

    if h is None or table.frame is None:
        return table
    radar = np.array([isinstance(s, RadarSensor) for s in table.sensors])[table.sensor]
    missing = radar & ~np.isfinite(table.altitude_m) & np.isfinite(h)
    if not missing.any():
        return table
    site_h = np.array([s.site_in(table.frame)[2] if isinstance(s, RadarSensor) else 0.0
                       for s in table.sensors])[table.sensor]
    reach = 0.95 * table.range_m
    alt = table.altitude_m.copy()
    alt[missing] = np.clip(h, site_h - reach, site_h + reach)[missing]
    return replace(table, altitude_m=alt)


def borrowed_altitude(table: PlotTable) -> FloatArray:
    """``(n,)`` heights at which to place radar plots without altitude: interpolated in time
    (held beyond the ends) from the table's plots that carry one (another radar's Mode C, an
    ADS-B altitude); NaN when no plot does. Plots with their own altitude keep it."""
    h = table.altitude_m
    known = np.flatnonzero(np.isfinite(h))
    if known.size == 0:
        return np.full(len(table), np.nan)
    order = known[np.argsort(table.t[known], kind="stable")]
    return np.where(np.isfinite(h), h, np.interp(table.t, table.t[order], h[order]))


def ellipse_cov(psi: FloatArray, A: FloatArray, B: FloatArray) -> FloatArray:
    """``(n, 2, 2)`` covariance ``B^2 e_r e_r^T + A^2 e_c e_c^T`` of one-sigma ellipses (``B``
    along ``e_r = (cos psi, sin psi)``, ``A`` across), the inverse of
    :func:`solver.geometry.weight_entries`."""
    c, s = np.cos(psi), np.sin(psi)
    vr, vc = np.asarray(B, float) ** 2, np.asarray(A, float) ** 2
    R = np.empty((*np.shape(c), 2, 2))
    R[..., 0, 0] = c * c * vr + s * s * vc
    R[..., 1, 1] = s * s * vr + c * c * vc
    R[..., 0, 1] = R[..., 1, 0] = s * c * (vr - vc)
    return R
