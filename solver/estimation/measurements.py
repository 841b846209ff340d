"""Polar measurement model: plots ``(d, psi)`` with ``d`` the ground range where the altitude is
known (``sqrt(r^2 - h^2)``, sigma ``sigma_r r / d``), else the slant range (sigma ``sigma_r``).

Two ways to use them in a Cartesian filter:

- ``"converted"``: the plot point ``(d cos psi, d sin psi)`` as a linear position measurement with
  the converted covariance ``R = J diag(sigma_d^2, sigma_psi^2) J^T``, ``J`` the polar-to-Cartesian
  Jacobian at the predicted position (evaluating it at the measured point correlates ``R`` with
  the error and biases the update; at the prediction it does not).
- ``"ekf"``: the extended Kalman update with ``h(x) = (hypot(x, z), atan2(z, x))`` linearised at
  the prediction, azimuth innovation wrapped to ``(-pi, pi]``.

The Cartesian filters default to ``"ekf"``: on the benchmark radars (``r sigma_psi^2 / sigma_r``
below 0.05) both give the same RMS to 1 m; on a stress radar (50 m, 0.03 rad, nonlinearity up to
3.6) the EKF update is 6-12 % more accurate and its covariance more honest, because the
converted ellipse cannot follow the curved (banana-shaped) polar uncertainty whose curvature
offset ``r sigma_psi^2 / 2`` is then comparable to the range sigma (benchmarks/filters_seed001.py
section 3). Same cost.

and, for the per-coordinate filters, conversion of a polar state ``(d, d', psi, psi')`` to
``(x, z, vx, vz)`` with its covariance (:func:`polar_state_to_cartesian`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import ground_range
from ..inputs import FloatArray, Plots, Radar

MEASUREMENT_MODES = ("converted", "ekf")


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
        return cls(t=np.asarray(plots.t, dtype=float), d=d,
                   sigma_d=radar.sigma_r * plots.range_m / d,
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
