"""A whole synthetic recording through the command line's pipeline (issue 16's benchmark).

``python -m benchmarks.recording [--aircraft N] [--quick]`` builds a recording from the six
real ADS-B trajectories (:mod:`benchmarks.truth`) and measures the command line
(:func:`solver.cli.run`, as a subprocess: the memory of the whole process tree is counted)
from the file to Parquet.

The recording (:func:`build`). Aircraft ``i`` flies a window of ``window_s`` seconds of the
real truth ``i mod 6`` (the window's start drawn in the truth), rotated about the plane's
reference by a drawn angle (the truth's ``(x, z)`` and velocity turn together, so speeds, turn
rates and the range from the first radar are the truth's) and shifted in time to a start drawn
uniformly over the recording, whose length is set so that ``in_air`` aircraft fly at once on
average. Every aircraft has its own Mode S address, Mode 3/A code and a track number per radar
(``modeac_share``: a drawn share of the aircraft has no Mode S, squawks 7000 and is seen by the
radars alone). Sensors (one plane about :data:`REFERENCE`, near Vienna): radar ``R1`` at the
reference (4 s scan, 50 m / 0.08 deg, Pd 0.97), ``R2`` 45 km south-east on a hill (6 s, 70 m /
0.1 deg, Pd 0.95), both with Mode C, and ``ADSB`` (5 s reports, 30 m, outages), simulated
through the curved earth by :func:`benchmarks.earth.simulate_sensor`. The plots are ordered by
4-s stretches, sensor, time (each sensor's times increase; across sensors they are out of order
by less than 4 s) and encoded as raw ASTERIX CAT048 / CAT021 with
:func:`solver.io.asterix.encode_rows` (encoded in parallel by time slices), with a CAT034 north
marker (I041 rotation period) per radar every 8 minutes. Written as ``recording.ast`` beside
``sensors.json``. Deterministic per (aircraft, seed).

Measured (:func:`measure`), all in one run: the command line with 1 and with 2 Dask workers
(wall time of the process from start to exit, plots reconstructed, plots/s; the peak RSS of
the process tree sampled with psutil every 0.2 s; the time to the first result from
``summary.json``), the single-track in-process throughput of ``reconstruct`` on a sample of
the same decoded tracks spread over the recording (one process, after a warm-up track; timed
before the runs and again after each run of the full recording, pooled), and the peak memory
at two
recording lengths (the same aircraft density, ``--aircraft`` and a quarter of it).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from solver.frames import LocalFrame
from solver.io.sensors_file import SensorSet, parse_sensors
from solver.io.tables import FL_M, PlotRows
from solver.sensors import Site

from .earth import GEOD, EarthTruth, SensorSpec, simulate_sensor
from .truth import Truth, load_truth, truth_names

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).parent / "results"
REFERENCE = (48.11, 16.57)  # the plane's tangent point and R1's site (Vienna Schwechat)
R2_BEARING_DEG, R2_DISTANCE_M = 135.0, 45e3
PROFILE = "recording"
ADDRESS0 = 0x440000  # first Mode S address (then one per aircraft)
TRACK_NUMBERS = 4096  # I048/161 has 12 bits
BUCKET_S = 4.0  # plots ordered by stretches of this length, then sensor, then time
SERVICE_EVERY_S = 480.0  # a CAT034 north marker per radar this often
SPEED_BOUNDS = (30.0, 350.0)  # m/s: what a rotated, shifted truth must stay within

SPECS: tuple[SensorSpec, ...] = (
    SensorSpec("R1", "radar", 4.0, 0.97, 0, 50.0, np.deg2rad(0.08), 150.0, np.deg2rad(0.24),
               mode_c=True),
    SensorSpec("R2", "radar", 6.0, 0.95, 1, 70.0, np.deg2rad(0.10), 200.0, np.deg2rad(0.3),
               mode_c=True),
    SensorSpec("ADSB", "position", 5.0, 0.98, sigma_pos=30.0, gaps_per_hour=2.0,
               gap_s=(20.0, 60.0)),
)
CODES = {"R1": (25, 11), "R2": (25, 12), "ADSB": (25, 1)}


@dataclass(frozen=True)
class RecordingSpec:
    """What to build: ``aircraft`` windows of ``window_s`` s, ``in_air`` at once on
    average, from ``start_tod_s`` (time of day), drawn with ``seed``."""

    aircraft: int = 2000
    window_s: float = 900.0
    in_air: float = 60.0
    seed: int = 16
    start_tod_s: float = 6 * 3600.0
    modeac_share: float = 0.0
    """Share of the aircraft drawn (independently of the rest) to have no Mode S: their radar
    plots carry no address and Mode 3/A 7000 (VFR), and no ADS-B sees them."""
    modeac_mode_c: bool = True
    """Whether the aircraft without Mode S report Mode C (False: their plots have no altitude,
    a PSR or a transponder without an altitude encoder)."""

    @property
    def duration_s(self) -> float:
        """Span of the aircraft's start times."""
        return self.aircraft * self.window_s / self.in_air


@dataclass
class Built:
    """A recording on disk and what went into it."""

    spec: RecordingSpec
    recording: Path
    sensors: Path
    aircraft: int
    plots: int
    plots_per_sensor: dict[str, int]
    addresses: list[int]
    bytes: int
    build_s: float


def sites() -> tuple[Site, Site]:
    lat0, lon0 = REFERENCE
    lon2, lat2, _ = GEOD.fwd(lon0, lat0, R2_BEARING_DEG, R2_DISTANCE_M)
    return Site(lat0, lon0, 320.0), Site(round(float(lat2), 6), round(float(lon2), 6), 870.0)


def sensor_file() -> dict[str, Any]:
    """The recording's sensor file (JSON object)."""
    s1, s2 = sites()
    radars = []
    for spec, site in zip(SPECS[:2], (s1, s2), strict=True):
        sac, sic = CODES[spec.id]
        radars.append({"id": spec.id, "kind": "radar", "sac": sac, "sic": sic,
                       "lat_deg": site.lat_deg, "lon_deg": site.lon_deg,
                       "height_m": site.height_m, "range_error_m": spec.eps_r,
                       "azimuth_error_deg": float(np.rad2deg(spec.eps_psi)),
                       "range_sigma_m": spec.sigma_r,
                       "azimuth_sigma_deg": float(np.rad2deg(spec.sigma_psi))})
    sac, sic = CODES["ADSB"]
    return {"sensors": [*radars, {"id": "ADSB", "kind": "position", "sac": sac, "sic": sic,
                                  "position_sigma_m": SPECS[2].sigma_pos}],
            "reference": {"lat_deg": REFERENCE[0], "lon_deg": REFERENCE[1]}}


def real_truths() -> list[str]:
    return [n for n in truth_names() if not n.startswith("synthetic")]


def transformed(base: Truth, name: str, t_from: float, t_to: float, shift: float,
                angle: float) -> Truth:
    """``base`` between ``t_from`` and ``t_to`` (with a margin of samples), rotated by
    ``angle`` (rad, clockwise seen from above: heading + angle) about the plane's origin and
    shifted by ``shift`` seconds."""
    i0 = max(int(np.searchsorted(base.t, t_from)) - 3, 0)
    i1 = min(int(np.searchsorted(base.t, t_to)) + 3, base.t.size)
    sl = slice(i0, i1)
    c, s = np.cos(angle), np.sin(angle)
    x, z, vx, vz = base.x[sl], base.z[sl], base.vx[sl], base.vz[sl]
    return Truth(name, base.t[sl] + shift, c * x - s * z, s * x + c * z, base.h[sl].copy(),
                 c * vx - s * vz, s * vx + c * vz)


def aircraft_truths(spec: RecordingSpec) -> list[tuple[Truth, float, float]]:
    """Every aircraft's truth (times in seconds of the recording from 0) and the start and
    end of its window."""
    rng = np.random.default_rng([spec.seed, spec.aircraft])
    names = real_truths()
    out = []
    for i in range(spec.aircraft):
        base = load_truth(names[i % len(names)])
        length = min(spec.window_s, base.duration)
        t_from = float(base.t[0] + rng.uniform(0.0, base.duration - length))
        start = float(rng.uniform(0.0, spec.duration_s))
        angle = float(rng.uniform(-np.pi, np.pi))
        truth = transformed(base, f"{base.name}#{i}", t_from, t_from + length,
                            start - t_from, angle)
        out.append((truth, start, start + length))
    return out


def modeac_aircraft(spec: RecordingSpec) -> set[int]:
    """The aircraft without Mode S (:attr:`RecordingSpec.modeac_share`), by index."""
    if spec.modeac_share <= 0:
        return set()
    rng = np.random.default_rng([spec.seed, spec.aircraft, 2])
    return set(np.flatnonzero(rng.random(spec.aircraft) < spec.modeac_share).tolist())


def simulate(spec: RecordingSpec) -> tuple[PlotRows, list[int]]:
    """Every aircraft's plots by every sensor as recording rows (ordered as the module
    docstring says), and the Mode S addresses of the aircraft that have one. Aircraft ``i``'s
    track number on radar ``k`` is ``(3 i + k) mod 4096``."""
    frame = LocalFrame(*REFERENCE)
    s1, s2 = sites()
    rng = np.random.default_rng([spec.seed, spec.aircraft, 1])
    cols: dict[str, list[np.ndarray]] = {k: [] for k in (
        "t", "sensor", "range_m", "azimuth_deg", "lat_deg", "lon_deg", "flight_level",
        "mode_s", "mode_3a", "track_number")}
    addresses = []
    modeac = modeac_aircraft(spec)
    for i, (win, w0, w1) in enumerate(aircraft_truths(spec)):
        et = EarthTruth(win, frame, (s1, s2))
        address = ADDRESS0 + i
        mode_3a = int(rng.integers(0, 0o10000))
        if i in modeac:
            address, mode_3a = -1, 0o7000
        else:
            addresses.append(address)
        for k, sspec in enumerate(SPECS):
            if address < 0 and sspec.kind == "position":
                continue
            p = simulate_sensor(et, sspec, PROFILE, spec.seed)
            keep = (p.t >= w0) & (p.t <= w1)
            n = int(keep.sum())
            cols["t"].append(p.t[keep])
            cols["sensor"].append(np.full(n, sspec.id, dtype=object))
            nan = np.full(n, np.nan)
            if p.range_m is not None and p.azimuth_rad is not None:
                cols["range_m"].append(p.range_m[keep])
                cols["azimuth_deg"].append(np.rad2deg(p.azimuth_rad[keep]))
                cols["lat_deg"].append(nan)
                cols["lon_deg"].append(nan)
            else:
                assert p.lat_deg is not None and p.lon_deg is not None
                cols["range_m"].append(nan)
                cols["azimuth_deg"].append(nan)
                cols["lat_deg"].append(p.lat_deg[keep])
                cols["lon_deg"].append(p.lon_deg[keep])
            h = win.altitude_at(p.t[keep])  # Mode C / ADS-B level: the height, in FL
            if address < 0 and not spec.modeac_mode_c:
                h = np.full(n, np.nan)
            cols["flight_level"].append(np.round(h / FL_M * 4.0) / 4.0)
            cols["mode_s"].append(np.full(n, address, np.int64))
            cols["mode_3a"].append(np.full(n, mode_3a, np.int64))
            cols["track_number"].append(np.full(n, (i * 3 + k) % TRACK_NUMBERS if k < 2
                                                else -1, np.int64))
    flat = {k: np.concatenate(v) if v else np.array([]) for k, v in cols.items()}
    sensor_order = {s.id: j for j, s in enumerate(SPECS)}
    sid = np.array([sensor_order[s] for s in flat["sensor"].tolist()], dtype=int)
    order = np.lexsort((flat["t"], sid, np.floor(flat["t"] / BUCKET_S)))
    n = order.size
    t = flat["t"][order]
    rows = PlotRows.from_columns(
        n, "row", t=t, time_of_day_s=np.mod(spec.start_tod_s + t, 86_400.0),
        **{k: v[order] for k, v in flat.items() if k != "t"})
    return rows, addresses


def _encode_slice(rows: PlotRows, sensors_json: dict[str, Any]) -> bytes:
    from solver.io.asterix import encode_rows

    return encode_rows(rows, parse_sensors(sensors_json))


def _service_blocks(t0: float, t1: float, start_tod: float) -> list[tuple[float, bytes]]:
    """CAT034 north markers with the rotation period (I041) per radar."""
    import asterix.generated as ast

    c034 = ast.Cat_034_1_29
    out = []
    for spec in SPECS[:2]:
        sac, sic = CODES[spec.id]
        for t in np.arange(t0, t1, SERVICE_EVERY_S):
            tod = float(np.mod(start_tod + t, 86_400.0))
            block = c034.create([c034.cv_record.create({
                "000": 1, "010": (("SAC", sac), ("SIC", sic)), "030": (tod, "s"),
                "041": (spec.scan_s, "s")})]).unparse().to_bytes()
            out.append((float(t), block))
    return out


def build(spec: RecordingSpec, out_dir: Path, *, processes: int = 2) -> Built:
    """Simulate and encode the recording into ``out_dir`` (see the module docstring); one
    built there before from the same spec (``built.json``) is reused."""
    started = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    cached = out_dir / "built.json"
    if cached.exists():
        b = json.loads(cached.read_text())
        if b["spec"] == asdict(spec) and Path(b["recording"]).exists():
            return Built(**{**b, "spec": spec, "recording": Path(b["recording"]),
                            "sensors": Path(b["sensors"])})
    sensors_json = sensor_file()
    rows, addresses = simulate(spec)
    # time slices at bucket boundaries (each sensor's times stay increasing), in parallel
    n_slices = max(1, min(64, len(rows) // 20_000))
    bucket = np.floor(rows.t / BUCKET_S)
    cuts = [0]
    for k in range(1, n_slices):
        j = int(np.searchsorted(bucket, bucket[min(len(rows) * k // n_slices, len(rows) - 1)]))
        if j > cuts[-1]:
            cuts.append(j)
    cuts.append(len(rows))
    slices = [rows.take(np.arange(a, b)) for a, b in itertools.pairwise(cuts)
              if b > a]
    if processes > 1 and len(slices) > 1:
        with ProcessPoolExecutor(processes) as pool:
            encoded = list(pool.map(_encode_slice, slices, [sensors_json] * len(slices)))
    else:
        encoded = [_encode_slice(s, sensors_json) for s in slices]
    service = _service_blocks(float(rows.t[0]) if len(rows) else 0.0,
                              float(rows.t[-1]) if len(rows) else 0.0, spec.start_tod_s)
    recording = out_dir / "recording.ast"
    size = 0
    with open(recording, "wb") as f:
        k = 0
        for s, data in zip(slices, encoded, strict=True):
            while k < len(service) and service[k][0] <= float(s.t[0]):
                f.write(service[k][1])
                size += len(service[k][1])
                k += 1
            f.write(data)
            size += len(data)
    sensors_path = out_dir / "sensors.json"
    sensors_path.write_text(json.dumps(sensors_json, indent=1) + "\n", encoding="utf-8")
    per_sensor = {s.id: int(np.sum(rows.sensor == s.id)) for s in SPECS}
    built = Built(spec, recording, sensors_path, spec.aircraft, len(rows), per_sensor,
                  addresses, size, time.perf_counter() - started)
    cached.write_text(json.dumps(asdict(built) | {"recording": str(recording),
                                                  "sensors": str(sensors_path)}))
    return built


def sensor_set() -> SensorSet:
    return parse_sensors(sensor_file())


# ------------------------------------------------------------------------------ measuring


class TreeSampler:
    """Peak and time series of the RSS of a process and its children (psutil), sampled in a
    thread every ``every_s``."""

    def __init__(self, pid: int, every_s: float = 0.2):
        import psutil

        self.root = psutil.Process(pid)
        self.every_s = every_s
        self.peak = 0
        self.series: list[tuple[float, int]] = []
        self.cpu: dict[int, float] = {}  # last user + system CPU seconds seen per process
        self.root_series: list[tuple[float, int]] = []  # RSS of the root process alone
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._t0 = time.perf_counter()
        self._thread.start()

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            total = 0
            try:
                procs = [self.root, *self.root.children(recursive=True)]
            except psutil.Error:
                procs = []
            for p in procs:
                try:
                    rss = p.memory_info().rss
                    total += rss
                    if p.pid == self.root.pid:
                        self.root_series.append((time.perf_counter() - self._t0, rss))
                    c = p.cpu_times()
                    self.cpu[p.pid] = c.user + c.system
                except psutil.Error:
                    pass
            if total:
                self.peak = max(self.peak, total)
                self.series.append((time.perf_counter() - self._t0, total))
            self._stop.wait(self.every_s)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def run_cli(built: Built, out: Path, workers: int, log: Path, deadline: float | None = None,
            budget_s: float | None = None, decode: str | None = None) -> dict[str, Any]:
    """The console script's pipeline (``python -m solver.cli``) as a subprocess; wall time,
    peak RSS and CPU time of the tree, and its ``summary.json``. At ``deadline`` (epoch s)
    or after ``budget_s`` the run is stopped and measured on the tracks committed by then
    (``partial``)."""
    if budget_s is not None:
        deadline = min(deadline or np.inf, time.time() + budget_s)
    import psutil

    # a cold run: the command line resumes from what an earlier run left in ``out``
    shutil.rmtree(out, ignore_errors=True)

    cmd = [sys.executable, "-m", "solver.cli", str(built.recording), "--sensors",
           str(built.sensors), "--out", str(out), "--workers", str(workers), "--no-progress"]
    if decode is not None:
        cmd += ["--decode", decode]
    load_before = os.getloadavg()
    started = time.perf_counter()
    partial = False
    first_commit: float | None = None
    with open(log, "w", encoding="utf-8") as f:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)
        sampler = TreeSampler(proc.pid)
        while True:
            try:
                code: int | None = proc.wait(timeout=1.0)
                break
            except subprocess.TimeoutExpired:
                ledger = out / "progress.jsonl"
                if first_commit is None and ledger.exists() and ledger.stat().st_size:
                    first_commit = time.perf_counter() - started
                if deadline is not None and time.time() > deadline:
                    partial = True
                    committed = _committed_plots(out)
                    wall_at_stop = time.perf_counter() - started
                    for p in [*psutil.Process(proc.pid).children(recursive=True)]:
                        p.terminate()
                    proc.terminate()
                    code = proc.wait()
                    break
        sampler.stop()
    wall = time.perf_counter() - started
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json"
                                                                 ).exists() else {}
    if partial:
        wall = wall_at_stop
        summary = {"plots": committed[0], "tracks": committed[1], "done": committed[1],
                   "failed": committed[2], "time_to_first_result_s": first_commit}
    series = sampler.series
    # memory over the run's halves: flat means the second half's peak is not above the first's
    half = wall / 2
    first = max((m for t, m in series if t <= half), default=0)
    second = max((m for t, m in series if t > half), default=0)
    return {"workers": workers, "exit_code": code, "wall_s": wall, "partial": partial,
            "cpu_s": sum(sampler.cpu.values()),
            "cpu_cli_s": sampler.cpu.get(proc.pid, 0.0),  # reading, decoding, split, client
            "load_avg_before": load_before, "load_avg_after": os.getloadavg(),
            "plots": summary.get("plots"), "tracks": summary.get("tracks"),
            "done": summary.get("done"), "failed": summary.get("failed"),
            "plots_per_s_end_to_end": (summary.get("plots", 0) / wall) if wall else None,
            "plots_per_s_reconstruct": summary.get("plots_per_s"),
            "reconstruct_s": summary.get("reconstruct_s"),
            "time_to_first_result_s": summary.get("time_to_first_result_s"),
            "rows_in_recording": summary.get("rows_in_recording"),
            "problems": summary.get("problems"),
            "peak_rss_mb": sampler.peak / 2**20,
            "peak_rss_first_half_mb": first / 2**20, "peak_rss_second_half_mb": second / 2**20,
            "rss_series_mb": [(round(t, 1), round(m / 2**20, 1)) for t, m in series[::25]],
            # the command line's own process (reading, decoding, splitting, Dask client and
            # the embedded cluster's scheduler): peak, and peak over each half of the run
            "peak_rss_cli_mb": max((m for _, m in sampler.root_series), default=0) / 2**20,
            "rss_cli_series_mb": [(round(t, 1), round(m / 2**20, 1))
                                  for t, m in sampler.root_series[::5]],
            "peak_rss_cli_halves_mb": [
                max((m for t, m in sampler.root_series if t <= half), default=0) / 2**20,
                max((m for t, m in sampler.root_series if t > half), default=0) / 2**20],
            "command": " ".join(cmd[1:]), "out": str(out)}


def in_task_rate(out: Path, in_process: dict[str, Any]) -> dict[str, Any] | None:
    """The in-process sample's tracks as a command-line run reconstructed them: plots per
    second of their ``elapsed_s`` in the run's ``progress.jsonl`` (the task on the worker,
    ``assess_track``, without Dask's per-task work or the start-up), beside the in-process
    rate of the same tracks. None without a ledger or a common track."""
    from solver.batch import ledger_entries

    sample = {t["aircraft"]: t for t in in_process["per_track"]}
    seen = {e["aircraft"]: e for e in ledger_entries(out)
            if e["status"] == "done" and e["aircraft"] in sample}
    if not seen:
        return None
    plots = sum(sample[k]["plots"] for k in seen)
    in_task = sum(e["elapsed_s"] for e in seen.values())
    here = sum(sample[k]["s"] for k in seen)
    out = {"tracks": len(seen), "plots": plots, "in_task_s": in_task, "in_process_s": here,
           "plots_per_s": plots / in_task, "in_process_plots_per_s": plots / here}
    if all(e.get("cpu_s") for e in seen.values()):  # ledgers from before cpu_s: wall only
        out["in_task_cpu_s"] = sum(e["cpu_s"] for e in seen.values())
        out["plots_per_cpu_s"] = plots / out["in_task_cpu_s"]
    return out


def _committed_plots(out: Path) -> tuple[int, int, int]:
    """(plots of the done tracks, done tracks, failed tracks) in ``progress.jsonl``."""
    plots = done = failed = 0
    path = out / "progress.jsonl"
    if path.exists():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                e = json.loads(line)
            except ValueError:
                continue
            if e["status"] == "done":
                plots += e["plots"]
                done += 1
            else:
                failed += 1
    return plots, done, failed


def pick_sample(built: Built, sample: int) -> list[Any]:
    """``sample`` tracks spread over the whole recording (every ``aircraft // sample``-th
    decoded track from its start) and one more in front of them for the warm-up: the
    in-process reference must cost what the runs' tracks cost, wherever a run stops."""
    from solver.io.asterix import iter_recording
    from solver.io.split import split_stream

    sensors = sensor_set()
    every = max(1, built.aircraft // sample)
    chosen = []
    for k, tr in enumerate(split_stream((p.rows for p in iter_recording(built.recording,
                                                                        sensors)), sensors)):
        if k % every == 0:
            chosen.append(tr)
        if len(chosen) > sample:
            break
    return chosen


def in_process_rate(chosen: list[Any]) -> dict[str, Any]:
    """Plots/s of ``reconstruct`` in this process on the tracks of :func:`pick_sample`
    (the first one an untimed warm-up)."""
    from solver.config import ReconstructionConfig
    from solver.reconstruct import reconstruct

    config = ReconstructionConfig()
    reconstruct(chosen[0].table, config=config)  # warm-up: solvers built and cached
    plots = 0
    elapsed = 0.0
    cpu = 0.0
    per_track = []
    for tr in chosen[1:]:
        t0, c0 = time.perf_counter(), time.process_time()
        reconstruct(tr.table, config=config)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        plots += len(tr.table)
        elapsed += dt
        cpu += dc
        per_track.append({"aircraft": tr.key, "plots": len(tr.table), "s": round(dt, 3),
                          "cpu_s": round(dc, 4)})
    return {"tracks": len(per_track), "plots": plots, "elapsed_s": elapsed, "cpu_s": cpu,
            "plots_per_s": plots / elapsed if elapsed else None,
            "plots_per_cpu_s": plots / cpu if cpu else None, "per_track": per_track,
            "utc": time.strftime("%H:%M:%S", time.gmtime())}


def pooled_in_process(r: dict[str, Any]) -> dict[str, Any] | None:
    """The in-process reference over every timing of the sample (before the runs and after
    each run of the full recording): the machine's speed drifts by 10-20 % within minutes
    (measured: one worker's tasks, CPU time per plot by fifths of a 7-min run, 1,942 to 2,302
    plots per CPU-s, nothing else running), so a reference timed once, in seconds, can sit
    anywhere in that range. None without a timing."""
    timings = [r["in_process"]] if r.get("in_process") else []
    timings += list(r.get("in_process_after", {}).values())
    if not timings:
        return None
    plots = sum(t["plots"] for t in timings)
    elapsed = sum(t["elapsed_s"] for t in timings)
    cpu = sum(t["cpu_s"] for t in timings)
    return {"timings": len(timings), "plots": plots, "plots_per_s": plots / elapsed,
            "plots_per_cpu_s": plots / cpu,
            "each_plots_per_s": [round(t["plots_per_s"]) for t in timings]}


def machine() -> dict[str, Any]:
    import psutil

    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True
                              ).stdout.strip()
    return {"python": platform.python_version(), "platform": platform.platform(),
            "cpu": platform.processor() or platform.machine(),
            "cores": len(os.sched_getaffinity(0)),
            "memory_gb": round(psutil.virtual_memory().total / 2**30, 1),
            "load_avg_at_start": os.getloadavg(),
            "commit": git("rev-parse", "--short", "HEAD"),
            "dirty_files": git("status", "--porcelain", "--untracked-files=no").count("\n")
            + bool(git("status", "--porcelain", "--untracked-files=no"))}


def measure(spec: RecordingSpec, work: Path, *, sample: int, small_fraction: float,
            save: Path, workers: tuple[int, ...] = (2, 1), deadline: float | None = None,
            budget_s: float | None = None) -> dict[str, Any]:
    """Build the recording (and a shorter one of the same density), run the command line on
    them, and the in-process throughput (see the module docstring); the results so far are
    saved to ``save`` after each step."""
    result: dict[str, Any] = {"spec": asdict(spec), "machine": machine(), "cli": {},
                              "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}

    def keep() -> None:
        save.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")

    built = build(spec, work / "rec")
    result["recording"] = {k: v for k, v in asdict(built).items()
                           if k not in ("addresses", "spec")} | {
        "recording": str(built.recording), "sensors": str(built.sensors),
        "duration_s": spec.duration_s + spec.window_s}
    keep()
    _log(f"built {built.aircraft} aircraft, {built.plots} plots, {built.bytes / 2**20:.1f} MiB "
         f"in {built.build_s:.0f} s")
    chosen = pick_sample(built, sample)
    result["in_process"] = in_process_rate(chosen)
    result["in_process_after"] = {}
    keep()
    _log(f"in process: {result['in_process']['plots_per_s']:.0f} plots/s")
    result["decode"] = decode_rate(built.recording)
    keep()
    small_spec = replace(spec, aircraft=max(10, int(spec.aircraft * small_fraction)))
    small = build(small_spec, work / "rec-small")
    n = max(workers)
    result["short_recording"] = {"aircraft": small.aircraft, "plots": small.plots,
                                 "duration_s": small_spec.duration_s + spec.window_s,
                                 "cli": run_cli(small, work / "out-small", n,
                                                work / "cli-small.log")}
    keep()
    _log(f"short recording: peak {result['short_recording']['cli']['peak_rss_mb']:.0f} MB")
    for n in workers:
        c = result["cli"][str(n)] = run_cli(built, work / f"out-{n}", n, work / f"cli-{n}.log",
                                            deadline, budget_s)
        c["same_tracks_in_task"] = in_task_rate(work / f"out-{n}", result["in_process"])
        result["in_process_after"][str(n)] = in_process_rate(chosen)  # see pooled_in_process
        keep()
        _log(f"{n} worker(s): {c['plots_per_s_end_to_end']:.0f} plots/s, peak "
             f"{c['peak_rss_mb']:.0f} MB, {c['wall_s']:.0f} s, exit {c['exit_code']}, "
             f"partial {c['partial']}")
    result["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    keep()
    return result


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# ------------------------------------------------------------------------------ report


def deadline_epoch(hh_mm: str, now: float | None = None) -> float:
    """The next time (epoch s) the UTC clock reads ``HH:MM``: tomorrow's when today's has
    passed (a run started at 23:52 with 00:40 stopped at once, today's 00:40 being past)."""
    now = time.time() if now is None else now
    hh, mm = (int(x) for x in hh_mm.split(":"))
    t = time.gmtime(now)
    at = now + ((hh * 60 + mm) - (t.tm_hour * 60 + t.tm_min)) * 60.0 - t.tm_sec
    return at if at > now else at + 86_400.0


def decode_rate(recording: Path, max_bytes: int = 2 << 20,
                chunk_bytes: int | None = None) -> dict[str, Any]:
    """Plots per second (wall and CPU) of decoding the recording's first ``max_bytes`` in
    this process (libasterix, one core) as the command line decodes it: ``iter_recording``
    in units of ``chunk_bytes`` (default the command line's ``STREAM_CHUNK_BYTES``), times
    unwrapped across the units."""
    from solver.io.asterix import block_chunks, iter_recording
    from solver.io.reading import STREAM_CHUNK_BYTES

    chunk = chunk_bytes or STREAM_CHUNK_BYTES
    with open(recording, "rb") as f:
        data = f.read(max_bytes + (1 << 16))
    a, b = block_chunks(data, max_bytes)[0]
    sensors = sensor_set()
    t0, c0 = time.perf_counter(), time.process_time()
    records = plots = 0
    for part in iter_recording(data[a:b], sensors, chunk_bytes=chunk):
        records += part.records
        plots += len(part.rows)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"bytes": b - a, "chunk_bytes": chunk, "records": records, "plots": plots,
            "wall_s": wall, "cpu_s": cpu, "plots_per_s": plots / wall,
            "plots_per_cpu_s": plots / cpu, "ms_cpu_per_plot": cpu / plots * 1e3}


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def verdicts(r: dict[str, Any]) -> dict[str, Any]:
    one, two = r["cli"].get("1"), r["cli"].get("2")
    out: dict[str, Any] = {}
    if one and two:
        ratio = _ratio(two["plots_per_s_end_to_end"], one["plots_per_s_end_to_end"])
        out["speedup_2_vs_1"] = {"value": ratio, "target": 1.8,
                                 "met": ratio is not None and ratio >= 1.8}
    ref = pooled_in_process(r)
    if one and ref:
        ratio = _ratio(one["plots_per_s_end_to_end"], ref["plots_per_s"])
        out["one_worker_vs_in_process"] = {"value": ratio, "target": 0.9,
                                           "met": ratio is not None and ratio >= 0.9}
    runs = [*r["cli"].values()] + ([r["short_recording"]["cli"]]
                                   if r.get("short_recording") else [])
    if runs:
        peak = max(c["peak_rss_mb"] for c in runs)
        out["peak_memory_mb"] = {"value": peak, "target": 2048, "met": peak < 2048}
    big = r["cli"].get("2") or r["cli"].get("1")
    if r.get("short_recording") and big:
        short = r["short_recording"]["cli"]
        if short["workers"] == big["workers"]:
            out["memory_flat"] = {
                "short_mb": short["peak_rss_mb"], "long_mb": big["peak_rss_mb"],
                "ratio": big["peak_rss_mb"] / short["peak_rss_mb"],
                "length_ratio": r["recording"]["plots"] / r["short_recording"]["plots"],
                "workers": big["workers"],
                "met": big["peak_rss_mb"] / short["peak_rss_mb"] < 1.25}
    return out


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def _row(label: str, c: dict[str, Any]) -> str:
    steady = None
    if c.get("time_to_first_result_s") and c.get("plots"):
        steady = c["plots"] / (c["wall_s"] - c["time_to_first_result_s"])
    return (f"| {label}{' (stopped at its time budget)' if c.get('partial') else ''} | "
            f"{c['workers']} | {c['plots']} | {c['wall_s']:.0f} | "
            f"{_f(c['plots_per_s_end_to_end'], '.0f')} | {_f(steady, '.0f')} | "
            f"{_f(c.get('plots_per_s_reconstruct'), '.0f')} | "
            f"{_f(_ratio(c['plots'], c.get('cpu_s')), '.0f')} | "
            f"{_f(c.get('time_to_first_result_s'), '.1f')} | {c['peak_rss_mb']:.0f} "
            f"({c['peak_rss_first_half_mb']:.0f} / {c['peak_rss_second_half_mb']:.0f}) | "
            f"{_f((c.get('load_avg_before') or [None])[0], '.1f')} / "
            f"{_f((c.get('load_avg_after') or [None])[0], '.1f')} |")


def write_report(r: dict[str, Any], out: Path, command: str) -> None:
    v = verdicts(r)
    r["verdicts"] = v
    out.with_suffix(".json").write_text(json.dumps(r, indent=1) + "\n", encoding="utf-8")
    rec, m = r["recording"], r["machine"]
    lines = [
        "# Whole recordings: the command line end to end (issue 16)", "",
        f"Command: `{command}` (commit {m['commit']}; {m['dirty_files']} tracked files with "
        f"other engineers' uncommitted changes in the tree); {r['started_utc']} to "
        f"{r.get('finished_utc', '(not finished)')}.",
        f"Machine: {m['cores']} cores ({m['cpu']}), shared with other engineers' work (load "
        f"average {m['load_avg_at_start'][0]:.1f} at the start), {m['memory_gb']} GB, "
        f"Python {m['python']}, {m['platform']}.", "",
        f"Recording: {rec['aircraft']} aircraft, {rec['plots']} plots "
        f"({', '.join(f'{k} {n}' for k, n in rec['plots_per_sensor'].items())}), "
        f"{rec['bytes'] / 2**20:.1f} MiB of raw ASTERIX CAT048/CAT021/CAT034, "
        f"{rec['duration_s'] / 3600:.1f} h, built in {rec['build_s']:.0f} s "
        "(see `benchmarks/recording.py` for how).", "",
        "Each run is `python -m solver.cli RECORDING --sensors SENSORS --out DIR --workers N "
        "--no-progress` in a subprocess (cold: a new LocalCluster, every worker builds its "
        "solvers), from the file to Parquet, CSV, GeoJSON, map and summary. *End to end*: "
        "plots reconstructed / wall time of the process. *After the first result*: plots / "
        "(wall - time to first result), i.e. without the start-up (cluster, solver builds, "
        "first decoding). *Reconstructing*: the summary's rate over `reconstruct_many`. "
        "*Per CPU-s*: plots / CPU seconds of the whole process tree (psutil). Memory: RSS of "
        "the process tree sampled every 0.2 s.", "",
        "| run | workers | plots | wall s | plots/s end to end | plots/s after the first "
        "result | plots/s reconstructing | plots per CPU-s | first result s | peak RSS MB "
        "(1st half / 2nd half of the run) | load avg before / after |",
        "|---|---|---|---|---|---|---|---|---|---|---|"]
    for k, c in r["cli"].items():
        lines.append(_row("full recording", c | {"workers": k}))
    for label, c in r.get("cli_variants", {}).items():
        lines.append(_row(f"full recording, {label}", c))
    if r.get("short_recording"):
        s = r["short_recording"]
        lines.append(_row(f"short recording ({s['aircraft']} aircraft, {s['plots']} plots)",
                          s["cli"]))
    ip, ref = r.get("in_process"), pooled_in_process(r)
    if ip and ref:
        after = r.get("in_process_after", {})
        spread = (f"{ref['timings']} timings: before the runs "
                  f"{ip['plots_per_s']:.0f}"
                  + "".join(f", after the {k}-worker run {t['plots_per_s']:.0f}"
                            for k, t in after.items()) + " plots/s") if after else (
            "timed once, before the runs")
        lines += ["", f"In process (`reconstruct`, one process, {ip['tracks']} decoded "
                  "tracks spread over the recording, after a warm-up track; "
                  f"{spread}): {ref['plots_per_s']:.0f} plots/s pooled "
                  f"({ref['plots_per_cpu_s']:.0f} plots per CPU-second). The one-worker "
                  "target compares with the pooled rate: the machine's speed drifts within "
                  "minutes (see `pooled_in_process`)."]
        for k, c in r["cli"].items():
            same = c.get("same_tracks_in_task")
            if same:
                cpu = (f"; per CPU-second of the task thread {same['plots_per_cpu_s']:.0f}"
                       if same.get("plots_per_cpu_s") else "")
                lines += ["", f"The same {same['tracks']} tracks inside the {k}-worker run's "
                          "tasks (their `elapsed_s` in its `progress.jsonl`: `assess_track` "
                          "on the worker, without Dask's per-task work or the start-up): "
                          f"{same['plots_per_s']:.0f} plots/s{cpu}; "
                          f"{same['plots_per_s'] / same['in_process_plots_per_s']:.2f}x the "
                          "first in-process timing of those tracks."]
    d = r.get("decode")
    if d:
        unit = (f", in units of {d['chunk_bytes'] // 1024} KiB as the command line"
                if d.get("chunk_bytes") else "")
        lines += ["", f"Decoding alone (libasterix, one process, the first "
                  f"{d['bytes'] / 2**20:.1f} MiB{unit}): {d['plots']} plots in "
                  f"{d['wall_s']:.1f} s = "
                  f"{d['plots_per_s']:.0f} plots/s ({d['plots_per_cpu_s']:.0f} per CPU-second)."]
    lines += ["", "## Targets", ""]
    if "speedup_2_vs_1" in v:
        x = v["speedup_2_vs_1"]
        lines.append(f"- 2 workers >= 1.8x one worker (end to end): "
                     f"**{'met' if x['met'] else 'missed'}** ({_f(x['value'], '.4f')}x).")
    if "one_worker_vs_in_process" in v:
        x = v["one_worker_vs_in_process"]
        lines.append(f"- one worker (end to end) >= 0.9x the in-process throughput: "
                     f"**{'met' if x['met'] else 'missed'}** ({_f(x['value'], '.4f')}x).")
    if "peak_memory_mb" in v:
        x = v["peak_memory_mb"]
        lines.append(f"- peak memory < 2 GB: **{'met' if x['met'] else 'missed'}** "
                     f"({x['value']:.0f} MB, RSS of the whole process tree, every run).")
    if "memory_flat" in v:
        x = v["memory_flat"]
        lines.append(f"- memory flat in the recording's length: "
                     f"**{'met' if x['met'] else 'missed'}** ({x['short_mb']:.0f} MB for the "
                     f"short recording, {x['long_mb']:.0f} MB for one {x['length_ratio']:.1f}x "
                     f"as long, {x['workers']} workers both).")
    lines += ["", "## Notes", "", *r.get("notes", [])]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n", encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--aircraft", type=int, default=None, help="default 2000 (quick: 60)")
    ap.add_argument("--quick", action="store_true", help="a short run: 60 aircraft of 300 s")
    ap.add_argument("--sample", type=int, default=None, help="tracks for the in-process rate")
    ap.add_argument("--small-fraction", type=float, default=0.25,
                    help="the shorter recording's aircraft (same density), as a fraction")
    ap.add_argument("--work", default=None, help="working directory, kept (default: a "
                    "temporary one)")
    ap.add_argument("--out", default=None, help="report path without suffix")
    ap.add_argument("--run-budget-s", type=float, default=None, help="stop each run of the "
                    "full recording after this long and measure it on the tracks committed "
                    "(labelled)")
    ap.add_argument("--deadline-utc", default=None, help="HH:MM: a command-line run still "
                    "going then is stopped and measured on the tracks committed (labelled)")
    ap.add_argument("--report-from", default=None, help="only write the report from this "
                    "results JSON (adds the decoding rate if missing and the recording is "
                    "still there)")
    ap.add_argument("--notes", default=None, help="a text file of notes for the report")
    ap.add_argument("--build-only", action="store_true", help="write the recording and its "
                    "sensors.json into --work (default rec/) and stop: a sample recording")
    args = ap.parse_args(argv)
    if args.report_from:
        r = json.loads(Path(args.report_from).read_text())
        if "decode" not in r and Path(r["recording"]["recording"]).exists():
            r["decode"] = decode_rate(Path(r["recording"]["recording"]))
        for c in r["cli"].values():  # runs from before the comparison was recorded
            if "same_tracks_in_task" not in c and r.get("in_process"):
                out_dir = c.get("out") or c["command"].split("--out ")[1].split()[0]
                c["same_tracks_in_task"] = in_task_rate(Path(out_dir), r["in_process"])
        if args.notes:
            r["notes"] = Path(args.notes).read_text().strip().split("\n")
        target = Path(args.out) if args.out else Path(args.report_from).with_suffix("")
        target = target.with_name(target.name.removesuffix(".partial"))
        write_report(r, target, r.get("command", "python -m benchmarks.recording"))
        print(target.with_suffix(".md").read_text())
        return 0
    if args.quick:
        spec = RecordingSpec(aircraft=args.aircraft or 60, window_s=300.0, in_air=20.0)
        out = Path(args.out or RESULTS / "quick" / "recording")
    else:
        spec = RecordingSpec(aircraft=args.aircraft or 2000)
        out = Path(args.out or RESULTS / "recording")
    if args.build_only:
        built = build(spec, Path(args.work or "rec"))
        print(f"{built.recording} ({built.plots} plots of {spec.aircraft} aircraft) and "
              f"{built.sensors}")
        return 0
    out.parent.mkdir(parents=True, exist_ok=True)
    sample = args.sample or (8 if args.quick else 120)
    command = "python -m benchmarks.recording " + " ".join(argv if argv is not None
                                                            else sys.argv[1:])
    save = out.with_name(out.name + ".partial.json")
    deadline = None
    if args.deadline_utc:
        deadline = deadline_epoch(args.deadline_utc)
    if args.work:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
        r = measure(spec, work, sample=sample, small_fraction=args.small_fraction, save=save,
                    deadline=deadline, budget_s=args.run_budget_s)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            r = measure(spec, Path(tmp), sample=sample, small_fraction=args.small_fraction,
                        save=save, deadline=deadline, budget_s=args.run_budget_s)
    save.unlink(missing_ok=True)
    r["command"] = command
    write_report(r, out, command)
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
