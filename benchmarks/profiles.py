"""Radar profiles of ../shared/bench/profiles.md: scan period, noise sigmas, detection probability
and the a priori maximum errors the product's ellipses use.

The table gives ``h_max``/``alpha_max`` only for ``seed000`` (the seed's real-data test); the other
two profiles leave them at 0, i.e. the ellipse is centred on the plot point, the same information
the baselines get. (``simulate(..., with_altitude=True)`` gives the true altitude instead.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.inputs import Radar


@dataclass(frozen=True)
class RadarProfile:
    """Simulation parameters (``scan_s`` s, ``sigma_r`` m, ``sigma_psi`` rad, ``pd``) and the
    a priori values handed to the estimators (``eps_r`` m, ``eps_psi`` rad, ``h_max`` m,
    ``alpha_max`` rad)."""

    name: str
    scan_s: float
    sigma_r: float
    sigma_psi: float
    pd: float
    eps_r: float
    eps_psi: float
    h_max: float = 0.0
    alpha_max: float = 0.0

    def radar(self) -> Radar:
        """The :class:`solver.Radar` an operator of this radar would configure."""
        return Radar(range_error_m=self.eps_r, azimuth_error_rad=self.eps_psi,
                     range_sigma_m=self.sigma_r, azimuth_sigma_rad=self.sigma_psi,
                     max_altitude_m=self.h_max, max_elevation_rad=self.alpha_max)


PROFILES: dict[str, RadarProfile] = {
    "seed000": RadarProfile("seed000", scan_s=19.0, sigma_r=500.0 / 3, sigma_psi=np.deg2rad(0.5),
                            pd=0.9, eps_r=500.0, eps_psi=np.deg2rad(1.5), h_max=15000.0,
                            alpha_max=np.deg2rad(60.0)),
    "seed001": RadarProfile("seed001", scan_s=10.0, sigma_r=400.0, sigma_psi=0.01, pd=1.0,
                            eps_r=1200.0, eps_psi=0.03),
    "ssr": RadarProfile("ssr", scan_s=4.8, sigma_r=50.0, sigma_psi=np.deg2rad(0.08), pd=0.97,
                        eps_r=150.0, eps_psi=np.deg2rad(0.24)),
}
