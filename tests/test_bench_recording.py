"""The synthetic whole recording of benchmarks/recording.py: deterministic, the aircraft asked
for with distinct Mode S addresses, decoded back to every plot encoded, and its rotated,
time-shifted real trajectories still physically valid."""

from __future__ import annotations

import json
import time
from dataclasses import fields

import numpy as np
import pytest

from benchmarks.recording import (
    ADDRESS0,
    REFERENCE,
    SPEED_BOUNDS,
    RecordingSpec,
    aircraft_truths,
    build,
    deadline_epoch,
    in_task_rate,
    pooled_in_process,
    real_truths,
    sensor_set,
    simulate,
)
from benchmarks.truth import load_truth
from solver.frames import LocalFrame
from solver.io.asterix import read_recording
from solver.io.split import split_aircraft

SPEC = RecordingSpec(aircraft=8, window_s=120.0, in_air=4.0, seed=3)


def test_deterministic_with_distinct_mode_s():
    a, addr_a = simulate(SPEC)
    b, addr_b = simulate(SPEC)
    for f in fields(a):
        if f.name != "origin_unit":
            np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))
    assert addr_a == addr_b == [ADDRESS0 + i for i in range(SPEC.aircraft)]
    assert set(np.unique(a.mode_s).tolist()) == set(addr_a)
    assert len(set(addr_a)) == SPEC.aircraft
    other, _ = simulate(RecordingSpec(**{**SPEC.__dict__, "seed": 4}))
    assert len(other) != len(a) or not np.array_equal(other.t, a.t)
    # each sensor's times increase in recording order; across sensors less than 4 s apart
    for s in ("R1", "R2", "ADSB"):
        assert np.all(np.diff(a.t[a.sensor == s]) >= 0)
    assert (np.maximum.accumulate(a.t) - a.t).max() < 4.0


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    return build(SPEC, tmp_path_factory.mktemp("rec"), processes=1)


def test_decodes_to_the_same_plots_and_aircraft(built):
    sensors = sensor_set()
    rec = read_recording(built.recording, sensors)
    assert len(rec.rows) == built.plots > 10 * SPEC.aircraft
    assert not rec.problems.counts
    assert {s: int(np.sum(rec.rows.sensor == s)) for s in ("R1", "R2", "ADSB")} == \
        built.plots_per_sensor
    assert {k for k, st in rec.service.items() if st.rotation_period_s} == {"R1", "R2"}
    rows, _ = simulate(SPEC)
    # times of day from 06:00 (t counts from the midnight before), to I140's resolution
    np.testing.assert_allclose(rec.rows.t - SPEC.start_tod_s, rows.t, atol=1 / 128)
    tracks = list(split_aircraft(rec.rows, sensors, problems=rec.problems))
    assert sorted(t.key for t in tracks) == sorted(f"{a:06X}" for a in built.addresses)
    assert sum(len(t.table) for t in tracks) == built.plots


def test_shifted_rotated_truths_stay_physical():
    names = real_truths()
    starts = []
    for i, (truth, w0, w1) in enumerate(aircraft_truths(SPEC)):
        base = load_truth(names[i % len(names)])
        speed = np.hypot(truth.vx, truth.vz)
        assert SPEED_BOUNDS[0] <= speed.min() and speed.max() <= SPEED_BOUNDS[1]
        assert truth.t[0] <= w0 < w1 <= truth.t[-1]
        assert 0.0 <= w0 <= SPEC.duration_s
        starts.append(w0)
        # a rotation about the reference (R1's site): ranges and speeds are the truth's
        n = truth.t.size
        r, rb = np.hypot(truth.x, truth.z), np.hypot(base.x, base.z)
        j = int(np.argmin([np.abs(rb[k:k + n] - r).max() for k in range(base.t.size - n + 1)]))
        np.testing.assert_allclose(r, rb[j:j + n], rtol=1e-12)
        np.testing.assert_allclose(speed, np.hypot(base.vx, base.vz)[j:j + n], rtol=1e-12)
        np.testing.assert_allclose(np.diff(truth.t), np.diff(base.t[j:j + n]), atol=1e-9)
        np.testing.assert_allclose(truth.h, base.h[j:j + n])
        # velocity rotated with the position: the motion between samples matches it
        t = np.linspace(w0, w1, 200)
        s = truth.at(t)
        mid = 0.5 * (t[1:] + t[:-1])
        sm = truth.at(mid)
        dx, dz = np.diff(s.x) / np.diff(t), np.diff(s.z) / np.diff(t)
        assert np.hypot(dx - sm.vx, dz - sm.vz).max() < 0.05 * speed.max()
    assert np.ptp(starts) > 0.5 * SPEC.duration_s  # spread over the recording


def test_decoded_plots_fly_at_aircraft_speeds(built):
    rec = read_recording(built.recording, sensor_set())
    frame = LocalFrame(*REFERENCE)
    r = rec.rows
    for address in built.addresses:
        sel = (r.mode_s == address) & (r.sensor == "ADSB")
        x, z = frame.to_plane(r.lat_deg[sel], r.lon_deg[sel])
        t = r.t[sel]
        v = np.hypot(np.diff(x), np.diff(z)) / np.diff(t)
        assert np.median(v) < SPEED_BOUNDS[1]  # noise of 30 m on 5-s steps adds little
        assert np.median(v) > SPEED_BOUNDS[0] - 20.0


def test_in_task_rate_compares_the_same_tracks(tmp_path):
    ledger = [{"aircraft": "A", "status": "done", "plots": 100, "elapsed_s": 0.2},
              {"aircraft": "B", "status": "failed", "plots": 50, "elapsed_s": 0.1},
              {"aircraft": "C", "status": "done", "plots": 300, "elapsed_s": 0.5},
              {"aircraft": "D", "status": "done", "plots": 80, "elapsed_s": 0.1}]
    (tmp_path / "progress.jsonl").write_text(
        "".join(json.dumps(e) + "\n" for e in ledger) + '{"airc')  # a torn last line
    sample = {"per_track": [{"aircraft": "A", "plots": 100, "s": 0.1},
                            {"aircraft": "B", "plots": 50, "s": 0.05},
                            {"aircraft": "C", "plots": 300, "s": 0.3},
                            {"aircraft": "E", "plots": 70, "s": 0.07}]}
    r = in_task_rate(tmp_path, sample)
    assert r is not None
    # A and C only: B failed in the run, D is not in the sample, E not in the run
    assert (r["tracks"], r["plots"]) == (2, 400)
    assert r["plots_per_s"] == pytest.approx(400 / 0.7)
    assert r["in_process_plots_per_s"] == pytest.approx(400 / 0.4)
    assert in_task_rate(tmp_path / "nothing", sample) is None
    assert "plots_per_cpu_s" not in r  # a ledger from before cpu_s was recorded
    for e, cpu in zip(ledger, (0.15, 0.1, 0.45, 0.1), strict=True):
        e["cpu_s"] = cpu
    (tmp_path / "progress.jsonl").write_text("".join(json.dumps(e) + "\n" for e in ledger))
    assert in_task_rate(tmp_path, sample)["plots_per_cpu_s"] == pytest.approx(400 / 0.6)


def test_the_in_process_reference_pools_every_timing():
    before = {"plots": 1000, "elapsed_s": 0.5, "cpu_s": 0.4, "plots_per_s": 2000.0}
    after = {"plots": 1000, "elapsed_s": 1.5, "cpu_s": 1.0, "plots_per_s": 1000 / 1.5}
    assert pooled_in_process({}) is None
    once = pooled_in_process({"in_process": before})
    assert once is not None and once["plots_per_s"] == pytest.approx(2000.0)
    ref = pooled_in_process({"in_process": before, "in_process_after": {"1": after}})
    assert ref is not None and ref["timings"] == 2
    assert ref["plots_per_s"] == pytest.approx(2000 / 2.0)  # plots over time, not a mean of rates
    assert ref["plots_per_cpu_s"] == pytest.approx(2000 / 1.4)
    assert ref["each_plots_per_s"] == [2000, 667]


def test_a_sample_recording_for_the_command_line(tmp_path, capsys):
    """``--build-only`` (the README's way to a first recording) writes a recording and its
    sensor file that read back whole, and measures nothing."""
    from benchmarks.recording import main
    from solver.io.sensors_file import load_sensors

    assert main(["--quick", "--aircraft", "3", "--build-only", "--work", str(tmp_path)]) == 0
    assert "plots of 3 aircraft" in capsys.readouterr().out
    rec = read_recording(tmp_path / "recording.ast", load_sensors(tmp_path / "sensors.json"))
    assert len(rec.rows) > 100 and not rec.problems
    assert sorted(p.name for p in tmp_path.iterdir()) == ["built.json", "recording.ast",
                                                          "sensors.json"]


def test_the_deadline_is_the_next_time_the_clock_reads_it():
    """A run started at 23:52 UTC with --deadline-utc 00:40 stopped at once: today's 00:40 had
    passed. The deadline is the next 00:40."""
    at_2352 = 1_764_287_520.0  # 2025-11-27 23:52:00 UTC
    assert time.gmtime(at_2352)[3:5] == (23, 52)
    assert deadline_epoch("00:40", at_2352) == at_2352 + 48 * 60
    assert deadline_epoch("23:58", at_2352) == at_2352 + 6 * 60
    assert deadline_epoch("23:52", at_2352 + 30) == at_2352 + 86_400
