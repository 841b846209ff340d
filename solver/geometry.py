"""Where a plot puts the aircraft on the plane: uncertainty ellipses and criterion weights.

Spec/reconstruction.md sections 3-4. An ellipse has its centre on the ray ``psi``, a radial
semi-axis ``B`` and a cross-range semi-axis ``A``. The criterion weight of a residual ``d`` is
``d^T M d`` with ``M = e_r e_r^T / B^2 + e_c e_c^T / A^2``, ``e_r = (cos psi, sin psi)``,
``e_c = (-sin psi, cos psi)``, stored as the three entries ``(a, b, c)`` of the symmetric ``M``:
``a = cos^2/B^2 + sin^2/A^2``, ``b = sin cos (1/B^2 - 1/A^2)``, ``c = sin^2/B^2 + cos^2/A^2``.
(The seed prints ``b`` with the opposite sign, which turns the ellipse by 90 degrees about the
ray's mirror axis; this sign is the right one: a residual of length ``A`` across the ray and one
of length ``B`` along it both score 1.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .inputs import FloatArray, Plots, Radar


@dataclass(frozen=True)
class Ellipses:
    """Per-plot ellipses: centres ``(cx, cz)``, ray azimuth ``psi``, semi-axes ``A`` (across the
    ray) and ``B`` (along it), all ``(n,)`` arrays in metres and radians."""

    cx: FloatArray
    cz: FloatArray
    psi: FloatArray
    A: FloatArray
    B: FloatArray

    def weights(self) -> FloatArray:
        """``(n, 3)`` entries ``(a, b, c)`` of the R2 weight matrices ``M_i``."""
        return weight_entries(self.psi, self.A, self.B)

    def score(self, px: FloatArray, pz: FloatArray) -> FloatArray:
        """R2 terms ``d^T M d`` of positions ``(px, pz)`` against each ellipse."""
        abc = self.weights()
        dx, dz = px - self.cx, pz - self.cz
        return abc[:, 0] * dx * dx + 2 * abc[:, 1] * dx * dz + abc[:, 2] * dz * dz


def weight_entries(psi: FloatArray, A: FloatArray, B: FloatArray) -> FloatArray:
    """``(n, 3)`` entries ``(a, b, c)`` of ``M = e_r e_r^T / B^2 + e_c e_c^T / A^2``."""
    c, s = np.cos(psi), np.sin(psi)
    ib, ia = 1.0 / (B * B), 1.0 / (A * A)
    return np.column_stack([c * c * ib + s * s * ia, s * c * (ib - ia), s * s * ib + c * c * ia])


def ground_range(plots: Plots) -> FloatArray:
    """Horizontal distance ``sqrt(r^2 - h^2)`` where the altitude is known, else the slant range."""
    if plots.altitude_m is None:
        return plots.range_m.copy()
    h = np.nan_to_num(plots.altitude_m, nan=0.0)
    return np.sqrt(plots.range_m**2 - h**2)


def plot_points(plots: Plots) -> tuple[FloatArray, FloatArray]:
    """Plot points ``(d cos psi, d sin psi)`` with ``d`` the ground range (slant if unknown)."""
    d = ground_range(plots)
    return d * np.cos(plots.azimuth_rad), d * np.sin(plots.azimuth_rad)


def uncertainty_ellipses(plots: Plots, radar: Radar) -> Ellipses:
    """A priori uncertainty ellipses from the maximum errors ``eps_r``, ``eps_psi``.

    Unknown altitude (spec section 3): ``d_far = r + eps_r``; ``d_near = (r - eps_r) - delta_h``
    with ``delta_h = (r - eps_r)(1 - cos alpha_max)`` when ``(r - eps_r) sin alpha_max <= h_max``,
    else ``(r - eps_r) - sqrt((r - eps_r)^2 - h_max^2)``. Known altitude ``h``: the ground range
    ``d = sqrt(r^2 - h^2)`` is exact up to the range error, whose ground projection is
    ``eps_r r / d``, and the altitude's (:func:`height_error` of ``3 altitude_sigma_m``).
    """
    r, psi = plots.range_m, plots.azimuth_rad
    eps_r, eps_psi = radar.range_error_m, radar.azimuth_error_rad
    near0 = np.maximum(r - eps_r, 0.0)
    h_max, alpha = radar.max_altitude_m, radar.max_elevation_rad
    by_angle = near0 * (1 - np.cos(alpha))
    by_height = near0 - np.sqrt(np.maximum(near0**2 - h_max**2, 0.0))
    delta_h = np.where(near0 * np.sin(alpha) <= h_max, by_angle, by_height)
    d_far, d_near = r + eps_r, near0 - delta_h
    centre = (d_far + d_near) / 2
    B = (d_far - d_near) / 2
    if plots.altitude_m is not None:
        known = ~np.isnan(plots.altitude_m)
        d = ground_range(plots)
        centre = np.where(known, d, centre)
        h = np.nan_to_num(plots.altitude_m, nan=0.0)
        B = np.where(known, np.hypot(ground_range_error(eps_r, r, d),
                                     height_error(3 * radar.altitude_sigma_m, h, d)), B)
    A = np.maximum(eps_psi * centre, 1e-3)
    return Ellipses(centre * np.cos(psi), centre * np.sin(psi), psi, A, np.maximum(B, 1e-3))


def statistical_ellipses(plots: Plots, radar: Radar) -> Ellipses:
    """One-sigma ellipses for statistical weighting: centre at the plot point (ground range if the
    altitude is known), ``B = sigma_r r / d`` along the ray (see :func:`ground_range_error`; with
    the altitude's own sigma, ``hypot`` of that and :func:`height_error`), ``A = sigma_psi d``
    across it (at least 1 m)."""
    d = ground_range(plots)
    psi = plots.azimuth_rad
    B = ground_range_error(radar.sigma_r, plots.range_m, d)
    if plots.altitude_m is not None:
        h = np.nan_to_num(plots.altitude_m, nan=0.0)
        B = np.hypot(B, height_error(radar.altitude_sigma_m, h, d))
    A = np.maximum(radar.sigma_psi * d, 1.0)
    return Ellipses(d * np.cos(psi), d * np.sin(psi), psi, A, B)


def ground_range_sigma(sigma_r: float | FloatArray, r: FloatArray, d: FloatArray,
                       sigma_h: float | FloatArray = 0.0, h: FloatArray | float = 0.0
                       ) -> FloatArray:
    """The filters' ground-range sigma of a plot at slant range ``r``, ground range ``d``:
    ``sigma_r r / d``, with the ``hypot`` of :func:`height_error` for an altitude ``h`` of
    sigma ``sigma_h`` (0: exact)."""
    return np.hypot(sigma_r * r / d, height_error(sigma_h, h, d))


def height_error(e_h: float | FloatArray, h: FloatArray, d: FloatArray) -> FloatArray:
    """Ground-range error of a height error ``e_h`` at height ``h`` above the radar, ground
    range ``d``: ``e_h |h| / d`` to first order (``d^2 = r^2 - h^2`` at a fixed slant range),
    which diverges overhead: ``d`` is floored at ``sqrt(2 |h| e_h)``, the ground range a height
    error ``e_h`` reaches from overhead (as :func:`ground_range_error`); 0 where ``e_h h = 0``."""
    h = np.abs(h)
    den = np.maximum(d, np.sqrt(2 * h * e_h))
    return np.where(e_h * h > 0, e_h * h / np.where(den > 0, den, 1.0), 0.0)


def ground_range_error(e_r: float | FloatArray, r: FloatArray, d: FloatArray) -> FloatArray:
    """Ground-range error of a slant-range error ``e_r`` at slant range ``r``, ground range
    ``d``: ``e_r r / d`` to first order, which diverges overhead (``d -> 0``); there the
    second-order value ``sqrt(2 r e_r)`` (from ``d^2 = r^2 - h^2``) bounds it."""
    return e_r * r / np.maximum(d, np.sqrt(2 * r * e_r))
