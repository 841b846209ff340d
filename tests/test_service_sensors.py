"""POST /v1/reconstructions with several sensors on the earth (spec sensors.md), in process."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from solver.frames import LocalFrame
from solver.results import Segment
from solver.sensors import RadarSensor, Site
from solver.trajectory import evaluate

FRAME = LocalFrame(46.0, 14.8)
ROOT = Path(__file__).resolve().parents[1]
SITES = {"LJLJ": Site(46.2237, 14.4576, 380.0), "SSR2": Site(45.5, 15.2, 900.0)}


def _body(mode_c: bool = False, estimate_bias: bool = False, height_m: float = 10_000.0
          ) -> dict:
    """Two radars (a PSR without altitude and an SSR) and ADS-B on one turning track at
    ``height_m``."""
    segs = [Segment(0.0, 300.0, -40e3, -30e3, 0.6, 220.0, 1.0, 0.0)]
    rng = np.random.default_rng(2)
    sensors = [
        {"id": "LJLJ", "kind": "radar", "lat_deg": 46.2237, "lon_deg": 14.4576,
         "height_m": 380.0, "range_error_m": 150.0, "azimuth_error_deg": 0.24,
         "estimate_bias": estimate_bias},
        {"id": "SSR2", "kind": "radar", "lat_deg": 45.5, "lon_deg": 15.2, "height_m": 900.0,
         "range_error_m": 150.0, "azimuth_error_deg": 0.24},
        {"id": "ADSB", "kind": "position", "position_sigma_m": 30.0},
    ]
    plots = []
    for sid, period, offset in (("LJLJ", 4.8, 0.0), ("SSR2", 4.0, 0.0), ("ADSB", 2.0, 1.0)):
        t = np.arange(offset, 300.0, period)
        st = evaluate(segs, t)
        h = np.full(t.size, height_m)
        if sid == "ADSB":
            lat, lon = FRAME.to_geodetic(st.x + rng.normal(0, 30, t.size),
                                         st.z + rng.normal(0, 30, t.size))
            plots += [{"t": float(a), "sensor": sid, "lat_deg": float(b), "lon_deg": float(c),
                       "altitude_m": height_m} for a, b, c in zip(t, lat, lon, strict=True)]
            continue
        radar = RadarSensor(150.0, np.deg2rad(0.24), id=sid, site=SITES[sid])
        r, az = radar.measure(FRAME, st.x, st.z, h)
        r = r + rng.normal(0, 50, t.size)
        az = np.rad2deg(az) + rng.normal(0, 0.08, t.size)
        for a, b, c in zip(t, r, az, strict=True):
            plot = {"t": float(a), "sensor": sid, "range_m": float(b), "azimuth_deg": float(c)}
            if mode_c and sid == "SSR2":
                plot["altitude_m"] = height_m
            plots.append(plot)
    return {"sensors": sensors, "reference": {"lat_deg": 46.0, "lon_deg": 14.8},
            "plots": plots, "filters": []}


@pytest.fixture(scope="module")
def client():
    app = create_app(Settings(workers=1, max_plots=2000, max_samples=20_000,
                              max_body_bytes=1_000_000, warmup=False))
    with TestClient(app) as c:
        for _ in range(600):
            if c.get("/readyz").status_code == 200:
                break
            import time

            time.sleep(0.1)
        yield c


def test_two_radars_and_adsb_answer_on_the_earth(client):
    body = _body()
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 200, res.text
    out = res.json()
    at = out["trajectory"]["at_plots"]
    assert len(at) == len(body["plots"])
    for state in (at[0], out["trajectory"]["samples"][-1]):
        assert {"lat_deg", "lon_deg", "altitude_m", "altitude_sigma_m"} <= set(state)
    # positions on the earth agree with the plane positions through the reference's frame
    lat, lon = FRAME.to_geodetic(np.array([at[5]["x"]]), np.array([at[5]["z"]]))
    assert at[5]["lat_deg"] == pytest.approx(lat[0], abs=1e-9)
    assert at[5]["lon_deg"] == pytest.approx(lon[0], abs=1e-9)
    assert [s["id"] for s in out["sensors"]] == ["LJLJ", "SSR2", "ADSB"]
    ljlj = out["sensors"][0]
    assert ljlj["plots"] == sum(p["sensor"] == "LJLJ" for p in body["plots"])
    assert ljlj["range_bias_m"] is None
    assert 20 < ljlj["range_residual_rms_m"] < 100
    assert 0.03 < ljlj["azimuth_residual_rms_deg"] < 0.2
    # each sensor's sigma estimated from its residuals' degrees of freedom, beside them
    assert ljlj["range_sigma_estimate_m"] > ljlj["range_residual_sigma_m"]
    assert ljlj["azimuth_sigma_estimate_deg"] > ljlj["azimuth_residual_sigma_deg"]
    assert out["sensors"][2]["position_sigma_estimate_m"] > 0
    assert out["trajectory"]["altitude_m"] == pytest.approx(10_000, abs=200)
    # each plot against its state: the statistics are these residuals' over the kept plots
    for sensor, stats in zip(("LJLJ", "SSR2", "ADSB"), out["sensors"], strict=True):
        mine = [s for s, p in zip(at, body["plots"], strict=True) if p["sensor"] == sensor]
        kept = [s for s in mine if not s["gated"]]
        assert len(mine) - len(kept) == stats["plots_gated"]
        if sensor == "ADSB":
            assert all("range_residual_m" not in s for s in mine)
            rms = np.sqrt(np.mean([s["position_residual_m"] ** 2 for s in kept]))
            assert rms == pytest.approx(stats["position_residual_rms_m"], rel=1e-9)
            # split along and across the track (the statistics; per plot in a job's tracks)
            assert abs(stats["along_track_residual_mean_m"]) < 20
            assert 0 < stats["cross_track_residual_sigma_m"] < stats["position_residual_rms_m"]
            assert all("along_track_residual_m" not in s for s in mine)
            continue
        assert all("position_residual_m" not in s for s in mine)
        for name in ("range_residual_m", "azimuth_residual_deg"):
            rms = np.sqrt(np.mean([s[name] ** 2 for s in kept]))
            assert rms == pytest.approx(stats[name.replace("_m", "_rms_m").replace(
                "_deg", "_rms_deg")], rel=1e-9)


def test_sliding_windows_take_the_sensors_too(client):
    """`method: sliding` over two radars and ADS-B on the earth: the seed's windows over every
    sensor's plots, answered on the earth with each plot's residuals and the sensors'
    statistics (no covariance), within reach of the refined answer."""
    body = _body()
    answers = {m: client.post("/v1/reconstructions", json={**body, "method": m})
               for m in ("sliding", "refined")}
    assert all(r.status_code == 200 for r in answers.values()), answers["sliding"].text
    out = answers["sliding"].json()
    assert out["diagnostics"]["method"] == "sliding"
    assert out["diagnostics"]["windows_solved"] > 0
    at, ref = out["trajectory"]["at_plots"], answers["refined"].json()["trajectory"]["at_plots"]
    assert len(at) == len(body["plots"]) and all(s["cov"] is None for s in at)
    assert {"lat_deg", "lon_deg"} <= set(at[0])
    apart = np.hypot([s["x"] - r["x"] for s, r in zip(at, ref, strict=True)],
                     [s["z"] - r["z"] for s, r in zip(at, ref, strict=True)])
    assert np.sqrt(np.mean(apart**2)) < 60.0, np.sqrt(np.mean(apart**2))  # 42 m measured
    assert [s["id"] for s in out["sensors"]] == ["LJLJ", "SSR2", "ADSB"]
    assert 30.0 < out["sensors"][2]["position_residual_rms_m"] < 80.0  # sigma 30 m; 58 m
    assert any("without an altitude placed at" in w for w in out["diagnostics"]["warnings"])


def test_filters_take_every_sensor_and_answer_on_the_earth(client):
    body = _body()
    body["filters"] = ["cv_rts", "imm"]
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 200, res.text
    out = res.json()
    for name in ("cv_rts", "imm"):
        states = out["filters"][name]["states"]
        assert len(states) == len(body["plots"])
        assert {"lat_deg", "lon_deg"} <= set(states[0])
        x = np.array([s["x"] for s in states])
        ref = np.array([s["x"] for s in out["trajectory"]["at_plots"]])
        assert np.sqrt(np.mean((x - ref) ** 2)) < 150.0


def test_fusion_filters_need_exactly_two_sensors(client):
    body = _body()
    body["filters"] = ["cv_rts", "fusion_c"]
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 422
    assert res.json()["detail"][0]["loc"] == ["filters", 1]
    two = _body()
    two["sensors"] = two["sensors"][1:]
    two["plots"] = [p for p in two["plots"] if p["sensor"] != "LJLJ"]
    two["filters"] = ["fusion_a", "fusion_b", "fusion_c"]
    res = client.post("/v1/reconstructions", json=two)
    assert res.status_code == 200, res.text
    assert set(res.json()["filters"]) == {"fusion_a", "fusion_b", "fusion_c"}


def test_bias_estimates_are_reported_in_degrees(client):
    res = client.post("/v1/reconstructions", json=_body(mode_c=True, estimate_bias=True))
    assert res.status_code == 200, res.text
    s = res.json()["sensors"][0]
    assert s["range_bias_sigma_m"] > 0 and s["azimuth_bias_sigma_deg"] > 0
    assert abs(s["azimuth_bias_deg"]) < 3 * s["azimuth_bias_sigma_deg"] + 1e-3
    # a radar 0.2 deg off in azimuth: the offset found, in degrees (0.0035 in radians)
    body = _body(mode_c=True, estimate_bias=True)
    for p in body["plots"]:
        if p["sensor"] == "LJLJ":
            p["azimuth_deg"] += 0.2
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 200, res.text
    s = res.json()["sensors"][0]
    assert 0 < s["azimuth_bias_sigma_deg"] < 0.05, s
    assert abs(s["azimuth_bias_deg"] - 0.2) < 3 * s["azimuth_bias_sigma_deg"] + 0.01, s
    # a position sensor's estimate_bias: its time offset alone (the plots are on time here)
    body = _body(mode_c=True)
    body["sensors"][2]["estimate_bias"] = True
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 200, res.text
    adsb = res.json()["sensors"][2]
    assert adsb["id"] == "ADSB" and adsb["range_bias_m"] is None
    assert 0 < adsb["time_bias_sigma_s"] < 0.1
    assert abs(adsb["time_bias_s"]) < 3 * adsb["time_bias_sigma_s"]


def test_single_radar_answer_has_no_earth_fields(client):
    body = {"radar": {"range_error_m": 150.0, "azimuth_error_deg": 0.24},
            "plots": [{"t": 5.0 * k, "range_m": 50e3 + 1000.0 * k, "azimuth_deg": 30.0}
                      for k in range(10)]}
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 200, res.text
    out = res.json()
    assert "lat_deg" not in out["trajectory"]["at_plots"][0]
    assert not {"gated", "range_residual_m"} & set(out["trajectory"]["at_plots"][0])
    assert out["sensors"] == []


LAST = len(_body()["plots"]) - 1  # an ADS-B plot


@pytest.mark.parametrize("change, loc", [
    (lambda b: b["plots"][3].update(sensor="NOPE"), ["plots", 3, "sensor"]),
    (lambda b: b["sensors"][0].update(lat_deg=95.0), ["sensors", 0, "lat_deg"]),
    (lambda b: b["plots"][3].update(t=b["plots"][1]["t"]), ["plots", 3, "t"]),
    (lambda b: b["plots"][-1].update(range_m=1000.0), ["plots", LAST, "range_m"]),
    (lambda b: b["plots"][0].pop("azimuth_deg"), ["plots", 0, "azimuth_deg"]),
    (lambda b: b["plots"][0].pop("sensor"), ["plots", 0, "sensor"]),
    (lambda b: b.update(radar={"range_error_m": 1.0, "azimuth_error_deg": 1.0}), ["sensors"]),
    # a sensor without plots is left out (below), but checked at its own index
    (lambda b: b["sensors"].append({"id": "SPARE", "kind": "position",
                                    "position_sigma_m": 0.0}), ["sensors", 3, "position_sigma_m"]),
    (lambda b: b["sensors"][1].update(id="LJLJ"), ["sensors", 1, "id"]),
    (lambda b: b["sensors"][0].update(azimuth_error_deg=-1.0),
     ["sensors", 0, "azimuth_error_deg"]),
    (lambda b: b["sensors"][0].update(altitude_sigma_m=-1.0), ["sensors", 0, "altitude_sigma_m"]),
    (lambda b: b["reference"].update(lat_deg=-91.0), ["reference", "lat_deg"]),
])
def test_bad_sensor_input_gets_a_422_naming_the_field(client, change, loc):
    body = copy.deepcopy(_body())
    change(body)
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 422, res.text
    err = res.json()
    assert err["detail"][0]["loc"] == loc, err


def test_a_default_reference_at_a_pole_names_the_field_sent(client):
    """Without `reference`, the plane is tangent at the first radar's site, else at the first
    position plot: at a pole, the 422 names that field (not the `reference` never sent) and
    the way out."""
    body = copy.deepcopy(_body())
    del body["reference"]
    body["sensors"][0]["lat_deg"] = 90.0
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 422, res.text
    assert res.json()["detail"][0]["loc"] == ["sensors", 0, "lat_deg"]
    assert res.json()["message"].startswith("sensors[0].lat_deg must be within 89.9 degrees")
    assert "defaults to the first radar's site; pass a `reference`" in res.json()["message"]

    adsb = copy.deepcopy(_body())
    del adsb["reference"]
    adsb["sensors"] = adsb["sensors"][2:]
    adsb["plots"] = [p for p in adsb["plots"] if p["sensor"] == "ADSB"]
    adsb["plots"][0]["lat_deg"] = -90.0
    res = client.post("/v1/reconstructions", json=adsb)
    assert res.status_code == 422, res.text
    assert res.json()["detail"][0]["loc"] == ["plots", 0, "lat_deg"]
    assert "defaults to the first position plot" in res.json()["message"]


def test_omit_samples_and_covariances(client):
    body = _body()
    body["filters"] = ["cv_rts"]
    full = client.post("/v1/reconstructions", json=body)
    body["omit"] = ["samples", "covariances"]
    slim = client.post("/v1/reconstructions", json=body)
    assert full.status_code == slim.status_code == 200, slim.text
    out = slim.json()
    assert out["trajectory"]["samples"] == []
    assert out["trajectory"]["at_plots"][0]["cov"] is None
    assert out["filters"]["cv_rts"]["states"][0]["cov"] is None
    assert out["trajectory"]["at_plots"][0]["x"] == full.json()["trajectory"]["at_plots"][0]["x"]
    assert len(slim.content) < len(full.content) / 3
    body["omit"] = ["everything"]
    assert client.post("/v1/reconstructions", json=body).status_code == 422


def test_a_long_gap_is_refused_before_solving(client):
    """Three plots over 10^7 s would be half a million refinement nodes from a tiny body."""
    body = {"radar": {"range_error_m": 150.0, "azimuth_error_deg": 0.24},
            "plots": [{"t": 0.0, "range_m": 50e3, "azimuth_deg": 1.0},
                      {"t": 10.0, "range_m": 51e3, "azimuth_deg": 1.0},
                      {"t": 1e7, "range_m": 52e3, "azimuth_deg": 1.0}],
            "sample_step_s": 1e4}
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 422, res.text
    assert res.json()["detail"][0]["loc"] == ["plots"]
    assert "max_nodes" in res.json()["message"]


def test_a_reference_far_from_the_track_warns_of_the_planes_scale():
    """ADS-B plots at 10 N 100 E, 0.003 deg of longitude every 2 s (164.5 m/s on the ground):
    with the reference at the track, that speed and no warning; 2000 km away the plane's
    stereographic scale makes it 2.4 % larger (2.5 % at the farthest plot), and the answer
    says so."""
    from service.convert import to_job
    from service.models import ReconstructionRequest
    from solver.reconstruct import reconstruct

    plots = [{"t": 2.0 * i, "sensor": "ADSB", "lat_deg": 10.0, "lon_deg": 100.0 + 0.003 * i}
             for i in range(20)]
    body = {"sensors": [{"id": "ADSB", "kind": "position", "position_sigma_m": 30.0}],
            "plots": plots, "omit": ["samples"]}
    for reference, speed, warned in (((10.0, 100.03), 164.5, False),
                                     ((10.0 + 2000 / 111.2, 100.03), 168.5, True)):
        req = ReconstructionRequest.model_validate(
            {**body, "reference": {"lat_deg": reference[0], "lon_deg": reference[1]}})
        job = to_job(req, "sqpmethod", 20_000, 50_000)
        rec = reconstruct(job.table, config=job.config)
        assert np.median(rec.at_plots.speed) == pytest.approx(speed, abs=0.3)
        far = [w for w in rec.diagnostics.warnings if "from the plane's reference" in w]
        assert bool(far) == warned, rec.diagnostics.warnings
    # at the farthest plot, 1991 km on the ground (pyproj Geod; 2007 km in the plane)
    assert "lies up to 1991 km" in far[0] and "up to 2.5 % larger there" in far[0], far


def test_covariances_far_from_the_reference_are_in_the_planes_metres():
    """`cov` is over `(x, z, vx, vz)` in the plane's metres: with the reference 4,300 km from
    the track (the plane's scale 1.12) every sigma is the near reference's times the plane's
    scale at the state (:meth:`LocalFrame.scale`), as `x`, `z`, `vx`, `vz` are. The ADS-B
    circles, the refinement's control prior and the filters' process noise were ground
    metres: the sigmas grew 1.013 (refined) and 1.006 (IMM smoother) times (a tester's)."""
    from service.convert import to_job
    from service.models import ReconstructionRequest
    from solver.estimation import run_filters
    from solver.reconstruct import reconstruct

    body = _body()
    sigmas, scales = {}, None
    for reference in ((46.0, 14.8), (7.3, 14.8)):
        req = ReconstructionRequest.model_validate(
            {**body, "reference": {"lat_deg": reference[0], "lon_deg": reference[1]},
             "omit": ["samples"]})
        job = to_job(req, "sqpmethod", 20_000, 50_000)
        rec = reconstruct(job.table, config=job.config)
        states = {"refined": rec.at_plots, **{k: e.states for k, e in run_filters(
            ["cv_rts", "imm_smoother"], job.table).items()}}
        sigmas[reference] = {k: np.sqrt(np.diagonal(s.cov, axis1=1, axis2=2))
                             for k, s in states.items()}
        scales = np.asarray(job.table.frame.scale(rec.at_plots.x, rec.at_plots.z))
    assert scales is not None and 1.11 < np.median(scales) < 1.13, np.median(scales)
    for name, near in sigmas[(46.0, 14.8)].items():
        ratio = sigmas[(7.3, 14.8)][name] / (near * scales[:, None])
        np.testing.assert_allclose(ratio, 1.0, atol=0.01, err_msg=name)


def test_known_heights_below_the_general_range_keep_the_radar_plots(client):
    """ADS-B at -800 m (accepted: altitude_m down to -1000 m) widens the heights the track may
    take; the radar plots without altitude must reach them too: their reach stopped at -500 m
    and every one of them (30-50 km from its radar) was given no weight as "above 74 deg
    elevation" (a tester's). Now none is, the height is estimated at the ADS-B's and the
    track is where it was flown."""
    body = _body(height_m=-800.0)
    res = client.post("/v1/reconstructions", json={**body, "omit": ["samples"]})
    assert res.status_code == 200, res.text
    got = res.json()
    assert not [w for w in got["diagnostics"]["warnings"] if "weight" in w], got["diagnostics"]
    assert not any(s.get("gated") for s in got["trajectory"]["at_plots"])
    assert got["trajectory"]["altitude_m"] == pytest.approx(-800.0, abs=30.0)
    at = got["trajectory"]["at_plots"]
    truth = evaluate([Segment(0.0, 300.0, -40e3, -30e3, 0.6, 220.0, 1.0, 0.0)],
                     np.array([s["t"] for s in at]))
    error = np.hypot(np.array([s["x"] for s in at]) - truth.x,
                     np.array([s["z"] for s in at]) - truth.z)
    assert np.sqrt(np.mean(error**2)) < 30.0, np.sqrt(np.mean(error**2))


def test_sensors_without_plots_are_left_out_with_a_note(client):
    """A site list shared by many requests: a radar (listed first, without `reference`: the
    plane's tangent point) and an ADS-B receiver that saw nothing of this track are left out,
    said in the warnings; the answer is the one without them, in the same plane, and its
    `sensors` lists them in their place with no plots."""
    body = _body()
    del body["reference"]
    spare = [{"id": "SPARE", "kind": "radar", "lat_deg": 46.5, "lon_deg": 14.0,
              "range_error_m": 150.0, "azimuth_error_deg": 0.24},
             {"id": "SPARE2", "kind": "position", "position_sigma_m": 10.0}]
    res = client.post("/v1/reconstructions", json={**body, "sensors": [spare[0], *body["sensors"],
                                                                       spare[1]]})
    assert res.status_code == 200, res.text
    got = res.json()
    assert "sensors 'SPARE', 'SPARE2' have no plots: left out" in got["diagnostics"]["warnings"]
    # sensors.md: one entry per sensor, in request order (the spares with no plots)
    assert [s["id"] for s in got["sensors"]] == ["SPARE", "LJLJ", "SSR2", "ADSB", "SPARE2"]
    assert [s["plots"] for s in got["sensors"]][::4] == [0, 0]
    assert got["sensors"][0]["range_residual_rms_m"] is None
    want = client.post("/v1/reconstructions", json={
        **body, "reference": {"lat_deg": 46.5, "lon_deg": 14.0}}).json()
    for a, b in zip(got["trajectory"]["at_plots"], want["trajectory"]["at_plots"], strict=True):
        assert (a["x"], a["z"], a["lat_deg"]) == pytest.approx((b["x"], b["z"], b["lat_deg"]),
                                                               abs=1e-6)


def test_a_pole_radar_after_an_unused_sensor_is_named_at_its_own_index(client):
    """The pole error names the request's index of the radar even when a sensor before it,
    without plots, is left out."""
    body = _body()
    del body["reference"]
    body["sensors"][0].update(lat_deg=90.0, lon_deg=0.0)
    spare = {"id": "SPARE", "kind": "position", "position_sigma_m": 10.0}
    res = client.post("/v1/reconstructions", json={**body, "sensors": [spare, *body["sensors"]]})
    assert res.status_code == 422, res.text
    assert res.json()["detail"][0]["loc"] == ["sensors", 1, "lat_deg"]


def test_a_missing_field_is_named_as_missing(client):
    """A position plot without `lon_deg` was "must be a finite number in [-180, 360] (nan)";
    a sensor without a required field was named with its kind in the path
    (`sensors[1].radar.range_error_m`)."""
    body = json.loads((ROOT / "examples" / "two_radars_adsb.json").read_text())
    kinds = {s["id"]: s["kind"] for s in body["sensors"]}
    adsb = next(i for i, p in enumerate(body["plots"]) if kinds[p["sensor"]] == "position")
    radar = next(i for i, p in enumerate(body["plots"]) if kinds[p["sensor"]] == "radar")
    pos = next(j for j, s in enumerate(body["sensors"]) if s["kind"] == "position")
    cases = ((("plots", adsb, "lon_deg"), f"plots[{adsb}].lon_deg is required for a plot of "),
             (("plots", radar, "range_m"), f"plots[{radar}].range_m is required for a plot of "),
             (("sensors", 0, "range_error_m"), "sensors[0].range_error_m: Field required"),
             (("sensors", pos, "position_sigma_m"),
              f"sensors[{pos}].position_sigma_m: Field required"))
    for (where, i, name), message in cases:
        sent = json.loads(json.dumps(body))
        del sent[where][i][name]
        r = client.post("/v1/reconstructions", json=sent)
        assert r.status_code == 422 and r.json()["message"].startswith(message), r.text
        assert r.json()["detail"][0]["loc"] == [where, i, name]


@pytest.mark.parametrize("reference, status", [((-46.0, -165.2), 422), ((20.0, -60.0), 200)])
def test_a_reference_near_the_datas_antipode_is_refused(client, reference, status):
    """The reference given at the track's antipode (19,950 km): the stereographic plane blows
    up there (a tester measured 59 km RMS, answered 200); refused, naming ``reference``, the
    distance and the plane's scale. 7200 km away (scale 1.4) the answer stays right."""
    body = _body()
    body["reference"] = {"lat_deg": reference[0], "lon_deg": reference[1]}
    body["omit"] = ["samples"]
    r = client.post("/v1/reconstructions", json=body)
    assert r.status_code == status, r.text[:500]
    if status == 422:
        err = r.json()["detail"][0]
        assert err["loc"] == ["reference"]
        assert "km from the data" in err["msg"] and "plane's scale would be" in err["msg"]


@pytest.mark.parametrize("wild", [False, True])
@pytest.mark.parametrize("gate", [6.0, None])
def test_filters_beside_gated_plots_say_which_they_used(client, wild, gate):
    """A plot at 1 m range (given no weight by the reconstruction, said) is left out by a gated
    filter (named) and used by an ungated one (`filter_gate_sigma` null; `alpha_beta`, which
    has no gate): the answer says which filter used it (a tester read 'given no weight' as true
    of the filters, whose states were 55-248 km off there)."""
    body = _body()
    body["filters"] = ["cv_rts", "alpha_beta"]
    body["filter_gate_sigma"] = gate
    body["omit"] = ["samples"]
    first = next(i for i, p in enumerate(body["plots"]) if p["sensor"] == "LJLJ")
    if wild:
        body["plots"][first + 5]["range_m"] = 1.0
    r = client.post("/v1/reconstructions", json=body)
    assert r.status_code == 200, r.text[:300]
    out = r.json()
    assert out["trajectory"]["at_plots"][first + 5]["gated"] is wild
    warnings = out["diagnostics"]["warnings"]
    used = sorted(w.split(":")[0] for w in warnings if "the reconstruction gave no weight" in w)
    left_out = [w for w in warnings if "left out, far from the filter's prediction" in w]
    if not wild:
        assert not used and not left_out, warnings
        return
    assert used == (["filters.alpha_beta"] if gate else ["filters.alpha_beta", "filters.cv_rts"])
    assert all(w.endswith(f"as wild: [{first + 5}]") for w in warnings if "as wild:" in w)
    assert out["filters"]["cv_rts"]["gated"] == ([first + 5] if gate else [])
    assert left_out == ([f"filters.cv_rts: 1 plot(s) left out, far from the filter's "
                         f"prediction (wild plots?): [{first + 5}]"] if gate else [])


def test_known_offsets_are_taken_off_the_plots(client):
    """A radar's known offsets in the request (an earlier registration's result, as in the
    sensor file): the SSR's plots 150 m long and 0.2 deg clockwise and ADS-B 1 s late; with
    their known offsets the answer is that of plots without offsets (the SSR's range residual
    RMS 71.8 m -> 48.1 m, as without any; ADS-B on the track again); out-of-bound offsets are
    a 422 naming the field."""
    def ssr_means(body: dict) -> tuple[float, float]:
        res = client.post("/v1/reconstructions", json=body)
        assert res.status_code == 200, res.text
        rep = {s["id"]: s for s in res.json()["sensors"]}
        return rep["SSR2"]["range_residual_rms_m"], rep["ADSB"]["along_track_residual_mean_m"]

    body = _body(mode_c=True)
    for p in body["plots"]:
        if p["sensor"] == "SSR2":
            p["range_m"] += 150.0
            p["azimuth_deg"] += 0.2
        elif p["sensor"] == "ADSB":
            p["t"] += 1.0
    off_rms, late = ssr_means(body)
    body["sensors"][1].update(range_offset_m=150.0, azimuth_offset_deg=0.2)
    body["sensors"][2]["time_offset_s"] = 1.0
    on_rms, on_time = ssr_means(body)
    clean_rms, _ = ssr_means(_body(mode_c=True))
    # measured: 71.8 m off, 48.1 m with them, as without any offset (to 1e-6 m)
    assert off_rms > 1.3 * clean_rms and abs(on_rms - clean_rms) < 0.1, (off_rms, on_rms)
    assert late < -15.0 and abs(on_time) < 5.0, (late, on_time)  # measured -20.0, +0.6 m
    for field, value in (("range_offset_m", 6000.0), ("azimuth_offset_deg", -11.0),
                         ("time_offset_s", 61.0)):
        bad = _body()
        bad["sensors"][1][field] = value
        res = client.post("/v1/reconstructions", json=bad)
        assert res.status_code == 422 and res.json()["detail"][0]["loc"][-1] == field, res.text


def test_flight_levels_are_made_geometric_by_the_aircrafts_adsb(client):
    """A request's Mode C (`flight_level`) is corrected as a recording's (a tester: the JSON
    routes had no flight level, so a job of tracks and a single request took pressure
    altitudes as heights and answered up to 5 m and 8 residual metres away from the command
    line on the same plots). Here the air mass puts every pressure altitude 200 m low: with
    the ADS-B reports' own flight levels the answer equals the one given the true heights;
    without ADS-B heights (no pairs) the pressure altitudes are taken as heights: it
    differs."""
    true = _body(mode_c=True)
    fl = (10_000.0 - 200.0) / 30.48
    corrected = copy.deepcopy(true)
    for p in corrected["plots"]:
        if p["sensor"] == "SSR2":
            del p["altitude_m"]
            p["flight_level"] = fl
        elif p["sensor"] == "ADSB":
            p["flight_level"] = fl
    lone = copy.deepcopy(corrected)  # ADS-B without heights: nothing to pair with
    for p in lone["plots"]:
        if p["sensor"] == "ADSB":
            del p["flight_level"], p["altitude_m"]
    answers = []
    for body in (true, corrected, lone):
        res = client.post("/v1/reconstructions", json=body)
        assert res.status_code == 200, res.text
        answers.append(res.json())
    xz = [np.array([[s["x"], s["z"]] for s in a["trajectory"]["at_plots"]]) for a in answers]
    assert np.abs(xz[1] - xz[0]).max() < 0.01
    assert np.abs(xz[2] - xz[0]).max() > 1.0
    said = [w for w in answers[1]["diagnostics"]["warnings"] if "made geometric" in w]
    assert said == [f"{sum(p['sensor'] == 'SSR2' for p in true['plots'])} pressure "
                    "altitude(s) made geometric by the aircraft's ADS-B: +200.0 m (median of "
                    f"{sum(p['sensor'] == 'ADSB' for p in true['plots'])} pairs; running "
                    "median over 120 s)"]
    assert not [w for w in answers[2]["diagnostics"]["warnings"] if "made geometric" in w]
    # a flight level needs a site on the earth: refused with the single radar
    legacy = json.loads((ROOT / "examples" / "seed_track.json").read_text())
    legacy["plots"][3]["flight_level"] = 330.0
    res = client.post("/v1/reconstructions", json=legacy)
    assert res.status_code == 422 and res.json()["detail"][0]["loc"] == ["plots", 3,
                                                                         "flight_level"]
    bad = copy.deepcopy(corrected)
    bad["plots"][0]["flight_level"] = 5000.0
    res = client.post("/v1/reconstructions", json=bad)
    assert res.status_code == 422 and res.json()["detail"][0]["loc"][:3] == ["plots", 0,
                                                                            "flight_level"]


@pytest.mark.parametrize("estimate_bias", [False, True])
def test_a_solve_past_its_time_limit_names_its_cost(estimate_bias):
    """A tester's 16 radars with estimate_bias held a worker for the whole limit and were
    told of long gaps between plots; the offsets were the cost. The answer names what the
    refinement solved: its node intervals, the offsets of the sensors with estimate_bias, and
    gaps only where they add nodes."""
    from service.convert import to_job
    from service.models import ReconstructionRequest
    from service.workers import solve

    body = _body(mode_c=True, estimate_bias=estimate_bias)
    body["sensors"][1]["estimate_bias"] = estimate_bias
    job = to_job(ReconstructionRequest.model_validate(body), "sqpmethod", 20_000, 100_000)
    out = solve(job, 0.0, time_limit_s=1e-6)
    assert out.body is None and out.error_loc == ("plots",)
    msg = out.error_message
    assert "solve time limit of 1e-06 s" in msg and "split the track" in msg
    assert f"{len(job.table) - 1} node intervals" in msg
    assert "gaps" not in msg
    assert ("6 offsets of 2 sensor(s) with estimate_bias (LJLJ, SSR2)" in msg) == estimate_bias
    # a gap of an hour: its nodes are named
    late = copy.deepcopy(body)
    for p in late["plots"]:
        p["t"] += 3600.0 if p["t"] > 150.0 else 0.0
    job = to_job(ReconstructionRequest.model_validate(late), "sqpmethod", 20_000, 100_000)
    msg = solve(job, 0.0, time_limit_s=1e-6).error_message
    assert "of the nodes fill long gaps between plots (one every 20 s)" in msg


def test_position_plots_west_of_the_antimeridian_are_taken(client):
    """ADS-B plots crossing the antimeridian written west of -180 (-180.0006: a conversion
    with noise) were a 422 at plots[k].lon_deg, where 180.0006 was taken: the single request
    takes [-360, 360] as the tables do (one limit), and answers on [-180, 180)."""
    lons = [-179.99 - 0.002 * i for i in range(10)]  # 92 m/s west at 65.5 N, past -180
    body = {"sensors": [{"id": "ADSB", "kind": "position", "position_sigma_m": 30.0}],
            "plots": [{"t": float(i), "sensor": "ADSB", "lat_deg": 65.5, "lon_deg": lon,
                       "altitude_m": 10_000.0} for i, lon in enumerate(lons)]}
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 200, res.text
    got = [s["lon_deg"] for s in res.json()["trajectory"]["at_plots"]]
    assert all(-180.0 <= g < 180.0 for g in got)
    apart = (np.array(got) - np.array(lons) + 180.0) % 360.0 - 180.0  # across +-180 too
    assert np.all(np.abs(apart) < 0.002)  # 30-m plots, 92 m apart
    body["plots"][0]["lon_deg"] = -360.5
    res = client.post("/v1/reconstructions", json=body)
    assert res.status_code == 422 and res.json()["detail"][0]["loc"] == ["plots", 0, "lon_deg"]
    assert "[-360, 360]" in res.json()["detail"][0]["msg"], res.text
