"""Issue 16's cross-sensor association measured on :mod:`benchmarks.recording`'s recording
with a share of aircraft without Mode S (squawking 7000, seen by R1 and R2 alone).

``python -m benchmarks.association [--aircraft 150] [--share 0.3] [--reconstruct]``: the
recording's rows are simulated (not encoded: the split is measured; Mode C put in
``altitude_m`` as the readers do) and split with the
association off (before) and on (after): CPU time of :func:`solver.io.split.split_aircraft`
on the whole and of :func:`solver.io.split.split_stream` over 32,768-row parts (the command
line's), best of ``--repeat``; the tracks of the aircraft without Mode S against the true
aircraft (a plot's aircraft from its radar's track number, ``(3 i + k) mod 4096``): tracks
out, wrong merges (a track with plots of two true aircraft) and missed merges (a true
aircraft seen by both radars at once in more than one track); with ``--reconstruct`` the RMS
horizontal position error of those tracks' reconstructions (every state at a plot time
against the truth of the track's aircraft, pooled over plots) and the share of those
aircraft's plots reconstructed with both radars.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from dataclasses import replace
from typing import Any

import numpy as np

from solver.io.problems import Problems
from solver.io.split import split_aircraft, split_stream
from solver.io.tables import FL_M, PlotRows

from .recording import (
    TRACK_NUMBERS,
    RecordingSpec,
    aircraft_truths,
    modeac_aircraft,
    sensor_set,
    simulate,
)

PARTS = 1 << 15


def owners(rows: PlotRows, spec: RecordingSpec) -> np.ndarray:
    """Each row's true aircraft from its radar's track number (-1: ADS-B)."""
    k = np.where(rows.sensor == "R1", 0, np.where(rows.sensor == "R2", 1, -1))
    tn = rows.track_number
    # (3 i + k) mod 4096 with 3 i + k < 4096 for the aircraft measured
    assert 3 * spec.aircraft < TRACK_NUMBERS, "track numbers wrap: owners ambiguous"
    return np.where(k >= 0, (tn - k) // 3, -1)


def split_cpu(rows: PlotRows, associate: bool, repeat: int) -> dict[str, Any]:
    sensors = sensor_set()
    whole, stream = [], []
    for _ in range(repeat):
        p = Problems()
        c0 = time.process_time()
        tracks = list(split_aircraft(rows, sensors, problems=p, associate_tracks=associate))
        whole.append(time.process_time() - c0)
        parts = [rows.take(np.arange(a, min(a + PARTS, len(rows))))
                 for a in range(0, len(rows), PARTS)]
        c0 = time.process_time()
        streamed = list(split_stream(parts, sensors, associate_tracks=associate))
        stream.append(time.process_time() - c0)
    assert sorted(t.key for t in streamed) == sorted(t.key for t in tracks)
    return {"tracks": tracks, "problems": p, "whole_cpu_s": min(whole),
            "stream_cpu_s": min(stream)}


def judge(rows: PlotRows, spec: RecordingSpec, tracks: list[Any]) -> dict[str, Any]:
    """Tracks of the aircraft without Mode S against the truth."""
    who = owners(rows, spec)
    modeac = modeac_aircraft(spec)
    mine = [tr for tr in tracks if (rows.mode_s[tr.rows] < 0).all()
            and bool(set(who[tr.rows].tolist()) & modeac)]
    per_track = [Counter(who[tr.rows].tolist()) for tr in mine]
    wrong = sum(len(c) > 1 for c in per_track)
    in_tracks: dict[int, int] = Counter(a for c in per_track for a in c)
    # aircraft seen by both radars within 30 s of each other: one track expected
    both = set()
    for a in modeac:
        t1 = np.sort(rows.t[(who == a) & (rows.sensor == "R1")])
        t2 = rows.t[(who == a) & (rows.sensor == "R2")]
        if t1.size and t2.size:
            j = np.clip(np.searchsorted(t1, t2), 1, t1.size) - 1
            near = np.minimum(np.abs(t2 - t1[j]), np.abs(t2 - t1[np.minimum(j + 1, t1.size - 1)]))
            if (near <= 30.0).sum() >= 5:
                both.add(a)
    missed = sum(in_tracks.get(a, 0) > 1 for a in both)
    seen = {a for a in modeac if (who == a).any()}
    return {"modeac_aircraft": len(seen), "seen_by_both": len(both), "tracks": len(mine),
            "wrong_merges": wrong, "missed_merges": missed,
            "plots_in_two_radar_tracks": int(sum(tr.rows.size for tr in mine
                                                 if len(tr.table.sensors) > 1)),
            "plots": int(sum(tr.rows.size for tr in mine))}


def rms_error(rows: PlotRows, spec: RecordingSpec, tracks: list[Any]) -> dict[str, Any]:
    """RMS horizontal error of the reconstructions of the tracks of aircraft without Mode S
    (each against its majority aircraft's truth), pooled over plots."""
    from solver.config import ReconstructionConfig
    from solver.reconstruct import reconstruct

    who = owners(rows, spec)
    modeac = modeac_aircraft(spec)
    truths = aircraft_truths(spec)
    config = ReconstructionConfig()
    sq, n, failed, cpu = 0.0, 0, 0, 0.0
    for tr in tracks:
        if not (rows.mode_s[tr.rows] < 0).all():
            continue
        owner = Counter(who[tr.rows].tolist()).most_common(1)[0][0]
        if owner not in modeac:
            continue
        c0 = time.process_time()
        try:
            rec = reconstruct(tr.table, config=config)
        except Exception:  # counted: a failure is a result here
            failed += 1
            continue
        cpu += time.process_time() - c0
        truth = truths[owner][0].at(rec.at_plots.t)
        e2 = (rec.at_plots.x - truth.x) ** 2 + (rec.at_plots.z - truth.z) ** 2
        sq += float(e2.sum())
        n += e2.size
    return {"rms_m": float(np.sqrt(sq / n)) if n else None, "states": n, "failed": failed,
            "reconstruct_cpu_s": cpu}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--aircraft", type=int, default=150)
    ap.add_argument("--share", type=float, default=0.3, help="share without Mode S")
    ap.add_argument("--window", type=float, default=900.0)
    ap.add_argument("--in-air", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-mode-c", action="store_true", help="the aircraft without Mode S "
                    "report no altitude either")
    ap.add_argument("--reconstruct", action="store_true")
    ap.add_argument("--out", default=None, help="JSON report path")
    a = ap.parse_args(argv)
    spec = RecordingSpec(aircraft=a.aircraft, window_s=a.window, in_air=a.in_air, seed=a.seed,
                         modeac_share=a.share, modeac_mode_c=not a.no_mode_c)
    rows, _ = simulate(spec)
    # Mode C as the readers give it (ASTERIX I090, a table's flight_level): the pressure
    # altitude in altitude_m (simulate's rows carry the flight level alone)
    rows = replace(rows, altitude_m=np.where(np.isfinite(rows.altitude_m), rows.altitude_m,
                                             rows.flight_level * FL_M))
    report: dict[str, Any] = {"spec": spec.__dict__, "rows": len(rows)}
    for label, on in (("before", False), ("after", True)):
        s = split_cpu(rows, on, a.repeat)
        r = {"whole_cpu_s": round(s["whole_cpu_s"], 3),
             "stream_cpu_s": round(s["stream_cpu_s"], 3),
             "all_tracks": len(s["tracks"]), **judge(rows, spec, s["tracks"]),
             "problems": s["problems"].counts}
        if a.reconstruct:
            r |= rms_error(rows, spec, s["tracks"])
        report[label] = r
        print(label, json.dumps(r), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(report, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
