"""Write ``examples/two_radars_adsb.json``: a request body for ``POST /v1/reconstructions``
with several sensors on the earth (spec sensors.md).

The aircraft is the benchmarks' ADS-B truth ``calibration__vienna`` placed where it flew
(``benchmarks.earth``), first 1200 s, seen by a primary radar at its original site (seed 000's
accuracy, 4.8-s scans, no altitude), a secondary radar 113 km away (SSR accuracy, no Mode C)
whose range is 120 m long (asked to be estimated), and ADS-B every 2 s with outages; random seed
0: deterministic. Run from the repository root:

    .venv/bin/python -m examples.make_sensors_batch
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.earth import BiasDraw, SensorSpec, place, simulate_multi
from solver.sensors import PositionSensor, RadarSensor

OUT = Path(__file__).with_name("two_radars_adsb.json")
SPECS = (
    SensorSpec("PSR", "radar", 4.8, pd=0.9, slot=0, sigma_r=500 / 3, sigma_psi=np.deg2rad(0.5),
               eps_r=500.0, eps_psi=np.deg2rad(1.5)),
    SensorSpec("SSR", "radar", 4.8, pd=0.97, slot=1, sigma_r=50.0, sigma_psi=np.deg2rad(0.08),
               eps_r=150.0, eps_psi=np.deg2rad(0.24), bias=BiasDraw(range_m=(120.0, 120.0)),
               estimate_bias=True),
    SensorSpec("ADSB", "position", 2.0, pd=0.95, sigma_pos=30.0, gaps_per_hour=6.0,
               gap_s=(60.0, 240.0)),
)


def _sensor(s: RadarSensor | PositionSensor) -> dict:
    if isinstance(s, PositionSensor):
        return {"id": s.id, "kind": "position", "position_sigma_m": s.position_sigma_m}
    assert s.site is not None
    return {"id": s.id, "kind": "radar", "lat_deg": s.site.lat_deg, "lon_deg": s.site.lon_deg,
            "height_m": s.site.height_m, "range_error_m": s.range_error_m,
            "azimuth_error_deg": round(float(np.rad2deg(s.azimuth_error_rad)), 6),
            "range_sigma_m": round(s.sigma_r, 3),
            "azimuth_sigma_deg": round(float(np.rad2deg(s.sigma_psi)), 6),
            "estimate_bias": s.estimate_bias}


def sensors_batch(t_max: float = 1200.0) -> dict:
    """The request body (JSON-ready dict)."""
    et = place("calibration__vienna")
    run = simulate_multi(et, SPECS, "example", seed=0, t_max=t_max)
    tab = run.table
    t0 = float(tab.t.min())
    plots = []
    for i in range(len(tab)):
        s = tab.sensors[tab.sensor[i]]
        p: dict = {"t": round(float(tab.t[i]) - t0, 3), "sensor": s.id}
        if isinstance(s, RadarSensor):
            p["range_m"] = round(float(tab.range_m[i]), 1)
            p["azimuth_deg"] = round(float(np.rad2deg(tab.azimuth_rad[i])), 4)
        else:
            p["lat_deg"] = round(float(tab.lat_deg[i]), 7)
            p["lon_deg"] = round(float(tab.lon_deg[i]), 7)
        plots.append(p)
    return {"sensors": [_sensor(s) for s in tab.sensors],  # type: ignore[arg-type]
            "reference": {"lat_deg": et.frame.lat_deg, "lon_deg": et.frame.lon_deg},
            "plots": plots}


def text(body: dict) -> str:
    """The file's text: one sensor, one plot per line."""
    plots = ",\n  ".join(json.dumps(p) for p in body["plots"])
    sensors = ",\n  ".join(json.dumps(s) for s in body["sensors"])
    return (f'{{\n "sensors": [\n  {sensors}\n ],\n "reference": '
            f'{json.dumps(body["reference"])},\n "plots": [\n  {plots}\n ]\n}}\n')


def main() -> None:
    body = sensors_batch()
    OUT.write_text(text(body))
    print(f"wrote {OUT} ({len(body['plots'])} plots over {body['plots'][-1]['t']:.0f} s)")


if __name__ == "__main__":
    main()
