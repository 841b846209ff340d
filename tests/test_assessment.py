"""The run's sensor figure (``sensors.png``, :mod:`solver.assessment`): the residuals read from
``tracks.parquet`` part by part give the same bias, sigma and binned means as numpy over all
rows at once (gated plots counted, not used), for radars and for position sensors (along and
across the track by speed); the scatter sample stays bounded, parts without residual columns
(an earlier version's) are skipped, and the figure is drawn."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from solver import assessment
from solver.assessment import sensor_residuals, write_sensors_figure


def _part(path, sensor, rng_m, az, dr, da, gated, position=None):
    n = rng_m.size
    cols = {"aircraft": ["A"] * n, "sensor": sensor, "plot_range_m": rng_m,
            "plot_azimuth_deg": az, "range_residual_m": dr, "azimuth_residual_deg": da,
            "gated": gated}
    if position is not None:
        cols.update(zip(("speed", "along_track_residual_m", "cross_track_residual_m"), position,
                        strict=True))
    pq.write_table(pa.table(cols), path)


def test_streamed_statistics_equal_the_whole_and_the_sample_is_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(assessment, "SCATTER_POINTS", 500)
    parts = tmp_path / "tracks.parquet"
    parts.mkdir()
    rng = np.random.default_rng(3)
    rows = []
    for k in range(4):
        n = 1_000
        sensor = rng.choice(["R1", "R2", "ADSB"], n)
        r = rng.uniform(1e3, 250e3, n)
        az = rng.uniform(0, 360, n)
        dr = 20.0 + 1e-4 * r + rng.normal(0, 50, n)  # a range-dependent bias
        da = 0.05 * np.sin(np.deg2rad(az)) + rng.normal(0, 0.08, n)  # an eccentricity
        gated = rng.random(n) < 0.02
        dr[gated] += 5_000.0
        adsb = sensor == "ADSB"
        r[adsb] = az[adsb] = dr[adsb] = da[adsb] = np.nan
        speed = rng.uniform(60, 300, n)
        along = np.where(adsb, -0.5 * speed + rng.normal(0, 30, n), np.nan)  # 0.5 s late
        cross = np.where(adsb, rng.normal(5, 30, n), np.nan)
        _part(parts / f"part-{k:06d}.parquet", sensor, r, az, dr, da, gated,
              None if k == 0 else (speed, along, cross))  # part 0: before the columns
        rows.append((sensor, r, az, dr, da, gated, speed, along, cross, np.full(n, k > 0)))
    pq.write_table(pa.table({"aircraft": ["old"], "x": [0.0]}), parts / "part-000009.parquet")
    sensor, r, az, dr, da, gated, speed, along, cross, newer = (
        np.concatenate(c) for c in zip(*rows, strict=True))
    found = sensor_residuals(tmp_path, order=["R2", "ADSB", "R1"])
    assert [(x.kind, x.sensor) for x in found] == [("radar", "R2"), ("radar", "R1"),
                                                   ("position", "ADSB")]
    pos = found[-1]
    sel = (sensor == "ADSB") & newer
    ok = sel & ~gated
    assert pos.plots == sel.sum() and pos.wild == (sel & gated).sum()
    np.testing.assert_allclose(pos.bias_sigma(), (along[ok].mean(), along[ok].std(),
                                                  cross[ok].mean(), cross[ok].std()), rtol=1e-9)
    (mean, _), (mean2, sigma2) = pos.first.mean_sigma(), pos.second.mean_sigma()
    b = (speed[ok] // assessment.SPEED_BIN_MS).astype(int)
    checked = 0
    for k in np.unique(b):
        if (b == k).sum() >= assessment.MIN_BIN_PLOTS:
            assert mean[k] == pytest.approx(along[ok][b == k].mean(), rel=1e-9)
            assert mean2[k] == pytest.approx(cross[ok][b == k].mean(), rel=1e-9)
            assert sigma2[k] == pytest.approx(cross[ok][b == k].std(), rel=1e-7)
            checked += 1
    assert checked >= 10
    got = {x.sensor: x for x in found if x.kind == "radar"}
    assert set(got) == {"R1", "R2"}
    for sid, res in got.items():
        sel = sensor == sid
        ok = sel & ~gated
        assert res.plots == sel.sum() and res.wild == (sel & gated).sum()
        np.testing.assert_allclose(res.bias_sigma(), (dr[ok].mean(), dr[ok].std(),
                                                      da[ok].mean(), da[ok].std()), rtol=1e-9)
        mean, sigma = res.first.mean_sigma()
        b = (r[ok] // assessment.RANGE_BIN_M).astype(int)
        for k in np.unique(b):
            if (b == k).sum() >= assessment.MIN_BIN_PLOTS:
                assert mean[k] == pytest.approx(dr[ok][b == k].mean(), rel=1e-9)
                assert sigma[k] == pytest.approx(dr[ok][b == k].std(), rel=1e-7)
        # the second panel: the azimuth residuals in azimuth bins (the eccentricity's sine)
        mean, sigma = res.second.mean_sigma()
        b = (az[ok] // assessment.AZIMUTH_BIN_DEG).astype(int)
        assert np.unique(b).size == 36
        checked = 0
        for k in np.unique(b):
            if (b == k).sum() >= assessment.MIN_BIN_PLOTS:
                assert mean[k] == pytest.approx(da[ok][b == k].mean(), rel=1e-9)
                assert sigma[k] == pytest.approx(da[ok][b == k].std(), rel=1e-7)
                checked += 1
        assert checked >= 30
        assert res.sample.shape == (500, 5)  # bounded, drawn from every part
        assert set(np.round(res.sample[:, 0], 6)) <= set(np.round(r[sel], 6))
    assert write_sensors_figure(tmp_path).read_bytes()[:4] == b"\x89PNG"


def test_no_residual_no_figure(tmp_path):
    parts = tmp_path / "tracks.parquet"
    parts.mkdir()
    nan = np.full(3, np.nan)
    _part(parts / "part-000001.parquet", ["ADSB"] * 3, nan, nan, nan, nan, np.zeros(3, bool))
    assert sensor_residuals(tmp_path) == [] and write_sensors_figure(tmp_path) is None


def test_the_figure_takes_the_estimated_sigmas_from_the_runs_sensors_json(tmp_path):
    """sensors.png's radar titles give the sigmas sensors.json estimated (read by sensor id);
    a missing or unreadable sensors.json leaves the figure the residuals alone."""
    from solver.assessment import _estimated

    path = tmp_path / "sensors.json"
    assert _estimated(path) == {}
    path.write_text('[{"sensor": "R1", "range_sigma_estimate_m": 60.4}, {"x": 1}]')
    assert _estimated(path) == {"R1": {"sensor": "R1", "range_sigma_estimate_m": 60.4}}
    path.write_text("{not json")
    assert _estimated(path) == {}
