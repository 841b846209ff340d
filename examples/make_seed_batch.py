"""Write ``examples/seed_track.json``: a request body for ``POST /v1/reconstructions``.

The track is the benchmarks' synthetic seed-like aircraft (``benchmarks.truth``: 5000 s,
straight legs, a ~220 deg right turn and a ~180 deg left turn, speed changes) seen by the
``seed000`` radar profile (19-s scan, sigma 167 m / 0.5 deg, Pd 0.9, plots thinned in the
turns), random seed 0: deterministic. The aircraft flies at 8,000 m here (the benchmarks' copy
of the track flies at 3,000 m since ee613f3; this file was made before and its numbers are
quoted in the README). Run from the repository root:

    .venv/bin/python -m examples.make_seed_batch
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.profiles import PROFILES
from benchmarks.simulate import simulate
from benchmarks.truth import SYNTHETIC, load_truth

OUT = Path(__file__).with_name("seed_track.json")
ALTITUDE_M = 8000.0


def seed_batch(t_max: float | None = None) -> dict:
    """The request body (JSON-ready dict); ``t_max`` cuts the track (s)."""
    profile = PROFILES["seed000"]
    truth = load_truth(SYNTHETIC)
    truth = replace(truth, h=np.full(truth.t.size, ALTITUDE_M))
    track = simulate(truth, profile, seed=0, drop_in_turns=True, t_max=t_max)
    p = track.plots
    t0 = float(p.t[0])
    return {
        "radar": {
            "range_error_m": profile.eps_r,
            "azimuth_error_deg": round(float(np.rad2deg(profile.eps_psi)), 6),
            "range_sigma_m": round(profile.sigma_r, 3),
            "azimuth_sigma_deg": round(float(np.rad2deg(profile.sigma_psi)), 6),
            "max_altitude_m": profile.h_max,
            "max_elevation_deg": round(float(np.rad2deg(profile.alpha_max)), 6),
        },
        "plots": [
            {"t": round(float(t) - t0, 3), "range_m": round(float(r), 1),
             "azimuth_deg": round(float(np.rad2deg(a)), 4)}
            for t, r, a in zip(p.t, p.range_m, p.azimuth_rad, strict=True)
        ],
    }


def text(body: dict) -> str:
    """The file's text: one plot per line."""
    plots = ",\n  ".join(json.dumps(p) for p in body["plots"])
    return f'{{\n "radar": {json.dumps(body["radar"])},\n "plots": [\n  {plots}\n ]\n}}\n'


def main() -> None:
    body = seed_batch()
    OUT.write_text(text(body))
    print(f"wrote {OUT} ({len(body['plots'])} plots over {body['plots'][-1]['t']:.0f} s)")


if __name__ == "__main__":
    main()
