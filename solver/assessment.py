"""Each sensor's plots against the reconstruction over a whole run, as a figure (``sensors.png``):
a radar's range and azimuth residuals by slant range and by azimuth, where a range-dependent
bias, an azimuth-dependent (eccentricity, north alignment) error or a sector of wild plots shows
at a glance (the plots of SASS-C's and TRES's radar assessment); a position sensor's (ADS-B)
residuals along and across the track by ground speed, where a report latency shows as an
along-track offset growing with the speed.

Read from ``tracks.parquet`` (its residual columns, :data:`solver.batch.RESIDUAL_COLUMNS`) one
part at a time, so memory does not grow with the run: per sensor, the residuals' count, sum and
sum of squares in fixed bins (:data:`RANGE_BIN_M`, :data:`AZIMUTH_BIN_DEG`,
:data:`SPEED_BIN_MS`), and at most
:data:`SCATTER_POINTS` plots for the scatter (those with the smallest keys of a seeded random
draw: an even sample of the run, the same on a rerun).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from .inputs import FloatArray

RANGE_BIN_M = 10_000.0
AZIMUTH_BIN_DEG = 10.0
MAX_RANGE_M = 600_000.0  # the last range bin holds every plot beyond
SCATTER_POINTS = 20_000  # per sensor
SPEED_BIN_MS = 10.0
MAX_SPEED_MS = 400.0  # the last speed bin holds every plot beyond
MIN_BIN_PLOTS = 5  # a bin's mean and sigma are drawn from this many plots up
_COLUMNS = ["sensor", "plot_range_m", "plot_azimuth_deg", "range_residual_m",
            "azimuth_residual_deg", "gated"]
_POSITION_COLUMNS = ["speed", "along_track_residual_m", "cross_track_residual_m"]


@dataclass
class _Binned:
    """Count, sum and sum of squares of a residual per bin."""

    n: np.ndarray
    s: np.ndarray
    s2: np.ndarray

    @classmethod
    def empty(cls, bins: int) -> _Binned:
        return cls(np.zeros(bins), np.zeros(bins), np.zeros(bins))

    def add(self, b: np.ndarray, r: FloatArray) -> None:
        k = self.n.size
        self.n += np.bincount(b, minlength=k)
        self.s += np.bincount(b, r, minlength=k)
        self.s2 += np.bincount(b, r * r, minlength=k)

    def mean_sigma(self) -> tuple[FloatArray, FloatArray]:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.s / self.n
            sigma = np.sqrt(np.maximum(self.s2 / self.n - mean**2, 0.0))
        few = self.n < MIN_BIN_PLOTS
        mean[few] = sigma[few] = np.nan
        return mean, sigma


@dataclass
class SensorResiduals:
    """One sensor's residuals over a run in two panels, each a residual over an axis: a radar's
    range residual (m) over the slant range (m) and azimuth residual (deg) over the azimuth
    (deg); a position sensor's along- and across-track residuals (m) over the ground speed
    (m/s), where a report late by ``d`` s lies about ``speed * d`` behind. Binned statistics
    per panel, totals, and a scatter sample (columns: axis 0, axis 1, residual 0, residual 1,
    left out); the statistics leave out the wild plots and those where the track is no
    reference (``wild``, ``no_reference``), as ``sensors.json`` does."""

    sensor: str
    kind: str = "radar"
    first: _Binned = field(default_factory=lambda: _Binned.empty(_range_bins()))
    second: _Binned = field(default_factory=lambda: _Binned.empty(_azimuth_bins()))
    plots: int = 0
    wild: int = 0
    no_reference: int = 0
    total: np.ndarray = field(default_factory=lambda: np.zeros(5))  # n, s0, s00, s1, s11
    sample: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def position(cls, sensor: str) -> SensorResiduals:
        return cls(sensor, "position", _Binned.empty(_speed_bins()),
                   _Binned.empty(_speed_bins()))

    def add(self, x0: FloatArray, x1: FloatArray, y0: FloatArray, y1: FloatArray,
            wild: np.ndarray, keys: FloatArray, no_reference: np.ndarray | None = None
            ) -> None:
        self.plots += x0.size
        far = np.zeros(x0.size, bool) if no_reference is None else no_reference
        self.wild += int((wild & ~far).sum())
        self.no_reference += int(far.sum())
        wild = wild | far
        ok = ~wild
        bins = ((_range_bin(x0[ok]), _azimuth_bin(x1[ok])) if self.kind == "radar"
                else (_speed_bin(x0[ok]), _speed_bin(x1[ok])))
        self.first.add(bins[0], y0[ok])
        self.second.add(bins[1], y1[ok])
        self.total += [ok.sum(), y0[ok].sum(), (y0[ok] ** 2).sum(), y1[ok].sum(),
                       (y1[ok] ** 2).sum()]
        rows = np.column_stack([x0, x1, y0, y1, wild.astype(float)])
        self.sample = np.concatenate([self.sample, rows])
        self.keys = np.concatenate([self.keys, keys])
        if self.keys.size > SCATTER_POINTS:
            best = np.argpartition(self.keys, SCATTER_POINTS)[:SCATTER_POINTS]
            self.sample, self.keys = self.sample[best], self.keys[best]

    def bias_sigma(self) -> tuple[float, float, float, float]:
        """Mean and standard deviation of the two residuals outside the wild plots (a
        radar's range in m and azimuth in deg; a position sensor's along and across the
        track, m)."""
        n, s1, s2, a1, a2 = self.total
        if n == 0:
            return (np.nan,) * 4  # type: ignore[return-value]
        return (s1 / n, float(np.sqrt(max(s2 / n - (s1 / n) ** 2, 0.0))), a1 / n,
                float(np.sqrt(max(a2 / n - (a1 / n) ** 2, 0.0))))


def _speed_bins() -> int:
    return int(MAX_SPEED_MS // SPEED_BIN_MS) + 1


def _speed_bin(v: FloatArray) -> np.ndarray:
    return np.minimum((v // SPEED_BIN_MS).astype(int), _speed_bins() - 1)


def _range_bins() -> int:
    return int(MAX_RANGE_M // RANGE_BIN_M) + 1


def _azimuth_bins() -> int:
    return round(360.0 / AZIMUTH_BIN_DEG)


def _range_bin(r: FloatArray) -> np.ndarray:
    return np.minimum((r // RANGE_BIN_M).astype(int), _range_bins() - 1)


def _azimuth_bin(a: FloatArray) -> np.ndarray:
    return (np.mod(a, 360.0) // AZIMUTH_BIN_DEG).astype(int) % _azimuth_bins()


def sensor_residuals(out: Path, order: Sequence[str] = ()) -> list[SensorResiduals]:
    """Every sensor's residuals in the run at ``out`` (its ``tracks.parquet`` parts): the
    radars', then the position sensors' (where the parts have their columns), each in the
    order of the ids ``order`` (the sensor file's), others after them by id; sensors without a
    residual (none reconstructed) are left out."""
    rng = np.random.default_rng(0)
    found: dict[tuple[str, str], SensorResiduals] = {}
    for part in sorted((out / "tracks.parquet").glob("part-*.parquet")):
        names = set(pq.read_schema(part).names)
        if not set(_COLUMNS) <= names:  # a part of an earlier version: no residuals
            continue
        wanted = _COLUMNS + (_POSITION_COLUMNS if set(_POSITION_COLUMNS) <= names else []) + (
            [c for c in ("wild", "no_reference") if c in names])
        t = pq.read_table(part, columns=wanted)
        cols = {c: t.column(c).to_numpy(zero_copy_only=False) for c in wanted}
        sensors = cols["sensor"].astype(str)
        # the plots the sensors' statistics leave out (sensors.json); a part written before
        # that column: the gated ones
        wild = cols["wild" if "wild" in cols else "gated"].astype(bool)
        far = (cols["no_reference"].astype(bool) if "no_reference" in cols
               else np.zeros(t.num_rows, bool))
        keys = rng.random(t.num_rows)
        panels = [("radar", cols["plot_range_m"], cols["plot_azimuth_deg"],
                   cols["range_residual_m"], cols["azimuth_residual_deg"])]
        if "speed" in cols:
            panels.append(("position", cols["speed"], cols["speed"],
                           cols["along_track_residual_m"], cols["cross_track_residual_m"]))
        for kind, x0, x1, y0, y1 in panels:
            y0 = y0.astype(float)
            has = np.isfinite(y0)
            for sid in dict.fromkeys(sensors[has].tolist()):
                sel = has & (sensors == sid)
                if (kind, sid) not in found:
                    found[(kind, sid)] = (SensorResiduals(sid) if kind == "radar"
                                          else SensorResiduals.position(sid))
                found[(kind, sid)].add(x0[sel].astype(float), x1[sel].astype(float), y0[sel],
                                       y1[sel].astype(float), wild[sel], keys[sel], far[sel])
    rank = {sid: k for k, sid in enumerate(order)}
    return sorted(found.values(), key=lambda x: (x.kind != "radar", rank.get(x.sensor, len(rank)),
                                                 x.sensor))


def write_sensors_figure(out: Path, order: Sequence[str] = ()) -> Path | None:
    """``out/sensors.png`` (:func:`solver.figures.residuals_figure`; sensors in the order of
    the ids ``order``), or None when no plot has a residual."""
    from .figures import residuals_figure, save

    sensors = sensor_residuals(out, order)
    if not sensors:
        return None
    return save(residuals_figure(sensors, _estimated(out / "sensors.json")),
                out / "sensors.png")


def _estimated(path: Path) -> dict[str, dict]:
    """The run's ``sensors.json`` rows by sensor id (for their estimated sigmas); none where
    it is not written yet or unreadable (the figure then shows the residuals alone)."""
    try:
        rows = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return {r["sensor"]: r for r in rows if isinstance(r, dict) and "sensor" in r} if isinstance(
        rows, list) else {}
