"""Uncertainty ellipses (spec section 3) and the R2 weights' orientation (section 4)."""

from __future__ import annotations

import numpy as np
import pytest

from solver.geometry import plot_points, uncertainty_ellipses, weight_entries
from solver.inputs import Plots, Radar

EPS_R, EPS_PSI = 500.0, np.deg2rad(1.5)


def _edges(ell, k: int = 0) -> tuple[float, float]:
    """Near and far ground ranges of ellipse ``k`` along its ray (centre -/+ B)."""
    centre = np.hypot(ell.cx[k], ell.cz[k])
    return centre - ell.B[k], centre + ell.B[k]


def test_near_edge_limited_by_elevation():
    """Close plot: ``(r - eps) sin(alpha) <= h_max``, so the nearest ground range is the
    projection at the elevation limit, ``(r - eps) cos(alpha)``."""
    r, alpha, h_max = 12_000.0, np.deg2rad(60.0), 15_000.0
    assert (r - EPS_R) * np.sin(alpha) <= h_max
    plots = Plots.from_arrays([0.0], [r], [0.3])
    ell = uncertainty_ellipses(plots, Radar(EPS_R, EPS_PSI, max_altitude_m=h_max,
                                            max_elevation_rad=alpha))
    near, far = _edges(ell)
    assert near == pytest.approx((r - EPS_R) * np.cos(alpha), rel=1e-12)
    assert far == pytest.approx(r + EPS_R, rel=1e-12)


def test_near_edge_limited_by_altitude():
    """Far plot: the aircraft at most ``h_max`` high, nearest ground range
    ``sqrt((r - eps)^2 - h_max^2)``."""
    r, alpha, h_max = 150_000.0, np.deg2rad(60.0), 15_000.0
    assert (r - EPS_R) * np.sin(alpha) > h_max
    plots = Plots.from_arrays([0.0], [r], [4.0])
    ell = uncertainty_ellipses(plots, Radar(EPS_R, EPS_PSI, max_altitude_m=h_max,
                                            max_elevation_rad=alpha))
    near, far = _edges(ell)
    assert near == pytest.approx(np.sqrt((r - EPS_R) ** 2 - h_max**2), rel=1e-12)
    assert far == pytest.approx(r + EPS_R, rel=1e-12)
    centre = (near + far) / 2
    assert ell.A[0] == pytest.approx(EPS_PSI * centre, rel=1e-12)


def test_centre_lies_on_the_ray():
    psi = np.deg2rad([0.0, 37.0, 135.0, 260.0, 359.0])
    plots = Plots.from_arrays(np.arange(5.0), np.full(5, 80_000.0), psi)
    ell = uncertainty_ellipses(plots, Radar(EPS_R, EPS_PSI, max_altitude_m=15_000.0,
                                            max_elevation_rad=np.deg2rad(60.0)))
    assert np.allclose(np.mod(np.arctan2(ell.cz, ell.cx), 2 * np.pi), psi, atol=1e-12)


def test_no_altitude_correction_gives_plot_point():
    plots = Plots.from_arrays([0.0, 1.0], [50_000.0, 90_000.0], [0.5, 2.0])
    ell = uncertainty_ellipses(plots, Radar(EPS_R, EPS_PSI))
    px, pz = plot_points(plots)
    assert np.allclose(ell.cx, px) and np.allclose(ell.cz, pz)
    assert np.allclose(ell.B, EPS_R) and np.allclose(ell.A, EPS_PSI * plots.range_m)


def test_known_altitude_uses_exact_ground_range():
    r, h = 60_000.0, 9_000.0
    plots = Plots.from_arrays([0.0, 1.0], [r, r], [1.0, 1.0], altitude_m=[h, np.nan])
    ell = uncertainty_ellipses(plots, Radar(EPS_R, EPS_PSI, max_altitude_m=15_000.0,
                                            max_elevation_rad=np.deg2rad(60.0)))
    d = np.sqrt(r * r - h * h)
    assert np.hypot(ell.cx[0], ell.cz[0]) == pytest.approx(d, rel=1e-12)
    assert ell.B[0] == pytest.approx(EPS_R * r / d, rel=1e-12)
    # the plot without altitude still gets the unknown-altitude ellipse
    near, far = _edges(ell, 1)
    assert far == pytest.approx(r + EPS_R) and near < r - EPS_R


@pytest.mark.parametrize("psi", np.deg2rad([0.0, 20.0, 45.0, 100.0, 200.0, 315.0]))
def test_r2_orientation(psi):
    """A residual of length A across the ray and one of length B along it both score 1; the
    seed's printed sign of ``b`` (the transposed orientation) would fail this."""
    A, B = 3000.0, 700.0
    a, b, c = weight_entries(np.array([psi]), np.array([A]), np.array([B]))[0]
    e_r = np.array([np.cos(psi), np.sin(psi)])
    e_c = np.array([-np.sin(psi), np.cos(psi)])
    m = np.array([[a, b], [b, c]])
    assert (A * e_c) @ m @ (A * e_c) == pytest.approx(1.0, rel=1e-12)
    assert (B * e_r) @ m @ (B * e_r) == pytest.approx(1.0, rel=1e-12)
    assert (A * e_c) @ m @ (B * e_r) == pytest.approx(0.0, abs=1e-12)
    if np.sin(2 * psi) != pytest.approx(0.0, abs=1e-9):
        m_seed = np.array([[a, -b], [-b, c]])
        assert (A * e_c) @ m_seed @ (A * e_c) != pytest.approx(1.0, rel=1e-3)


def test_score_matches_weights():
    plots = Plots.from_arrays([0.0, 1.0], [70_000.0, 71_000.0], [0.2, 0.21])
    ell = uncertainty_ellipses(plots, Radar(EPS_R, EPS_PSI))
    e_c = np.array([-np.sin(ell.psi), np.cos(ell.psi)])
    px, pz = ell.cx + ell.A * e_c[0], ell.cz + ell.A * e_c[1]
    assert np.allclose(ell.score(px, pz), 1.0)
