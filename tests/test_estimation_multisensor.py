"""Every filter on several sensors (issue 15): the legacy single flat radar unchanged, the
measurement set, the asynchronous Kalman update in closed form, two radars + ADS-B."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from solver import Plots, Radar

REFERENCE = Path(__file__).with_name("test_estimation_multisensor_reference.npz")
LEGACY_RADAR = Radar(1200.0, 0.03, range_sigma_m=400.0, azimuth_sigma_rad=0.01)
# name, params: the defaults and the non-default measurement / frame / order paths
LEGACY_RUNS: list[tuple[str, dict]] = [
    ("singer", {}), ("singer", {"measurement": "converted"}), ("singer", {"frame": "polar"}),
    ("quasi_optimal", {}), ("quasi_optimal", {"lam": "auto"}),
    ("quasi_optimal", {"discretisation": "taylor"}), ("fuzzy", {}),
    ("fuzzy", {"n_terms": 5, "shape": "gaussian"}), ("alpha_beta", {}),
    ("alpha_beta", {"order": 3, "k_max": 6}), ("cv_rts", {}),
    ("cv_rts", {"measurement": "converted", "smooth": False}), ("imm", {}),
    ("imm", {"measurement": "converted"}),
]


def legacy_cases() -> dict[str, Plots]:
    """Two seeded single-radar tracks: a turn with irregular steps and Mode C on some plots,
    and a straight pass across azimuth 0 / 2 pi."""
    rng = np.random.default_rng(15)
    n = 30
    t = np.cumsum(rng.choice([4.0, 4.0, 8.0, 12.0], n))
    heading = np.deg2rad(60.0) + np.where(t > 60, np.minimum(t - 60, 60) * np.deg2rad(1.5), 0)
    dt = np.diff(t, prepend=t[0])
    x = -70_000 + np.cumsum(180 * np.cos(heading) * dt)
    z = 20_000 + np.cumsum(180 * np.sin(heading) * dt)
    h = np.where(rng.random(n) < 0.5, 7000.0, np.nan)
    r = np.sqrt(x**2 + z**2 + np.nan_to_num(h) ** 2) + rng.normal(0, 400, n)
    psi = np.arctan2(z, x) + rng.normal(0, 0.01, n)
    turn = Plots.from_arrays(t, r, psi, h)
    t2 = 10.0 * np.arange(20)
    x2, z2 = np.full(20, 60_000.0), -5000 + 180 * t2
    north = Plots.from_arrays(t2, np.hypot(x2, z2) + rng.normal(0, 400, 20),
                              np.arctan2(z2, x2) + rng.normal(0, 0.01, 20))
    return {"turn": turn, "north": north}


def _key(case: str, name: str, params: dict) -> str:
    return "|".join([case, name, *(f"{k}={v}" for k, v in sorted(params.items()))])
