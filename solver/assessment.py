"""Each radar's plots against the reconstruction over a whole run, as a figure (``sensors.png``):
the range and azimuth residuals by slant range and by azimuth, where a range-dependent bias, an
azimuth-dependent (eccentricity, north alignment) error or a sector of wild plots shows at a
glance (the plots of SASS-C's and TRES's radar assessment).

Read from ``tracks.parquet`` (its residual columns, :data:`solver.batch.RESIDUAL_COLUMNS`) one
part at a time, so memory does not grow with the run: per radar, the residuals' count, sum and
sum of squares in fixed bins (:data:`RANGE_BIN_M`, :data:`AZIMUTH_BIN_DEG`), and at most
:data:`SCATTER_POINTS` plots for the scatter (those with the smallest keys of a seeded random
draw: an even sample of the run, the same on a rerun).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from .inputs import FloatArray

RANGE_BIN_M = 10_000.0
AZIMUTH_BIN_DEG = 10.0
MAX_RANGE_M = 600_000.0  # the last range bin holds every plot beyond
SCATTER_POINTS = 20_000  # per radar
MIN_BIN_PLOTS = 5  # a bin's mean and sigma are drawn from this many plots up
_COLUMNS = ["sensor", "plot_range_m", "plot_azimuth_deg", "range_residual_m",
            "azimuth_residual_deg", "gated"]


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
class RadarResiduals:
    """One radar's residuals over a run: binned statistics, totals, and a scatter sample
    (columns: range (m), azimuth (deg), range residual (m), azimuth residual (deg), gated)."""

    sensor: str
    dr_by_range: _Binned = field(default_factory=lambda: _Binned.empty(_range_bins()))
    da_by_azimuth: _Binned = field(default_factory=lambda: _Binned.empty(_azimuth_bins()))
    plots: int = 0
    gated: int = 0
    total: np.ndarray = field(default_factory=lambda: np.zeros(5))  # n, s_dr, s_dr2, s_da, s_da2
    sample: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def add(self, rng_m: FloatArray, az_deg: FloatArray, dr: FloatArray, da: FloatArray,
            gated: np.ndarray, keys: FloatArray) -> None:
        self.plots += rng_m.size
        self.gated += int(gated.sum())
        ok = ~gated
        self.dr_by_range.add(_range_bin(rng_m[ok]), dr[ok])
        self.da_by_azimuth.add(_azimuth_bin(az_deg[ok]), da[ok])
        self.total += [ok.sum(), dr[ok].sum(), (dr[ok] ** 2).sum(), da[ok].sum(),
                       (da[ok] ** 2).sum()]
        rows = np.column_stack([rng_m, az_deg, dr, da, gated.astype(float)])
        self.sample = np.concatenate([self.sample, rows])
        self.keys = np.concatenate([self.keys, keys])
        if self.keys.size > SCATTER_POINTS:
            best = np.argpartition(self.keys, SCATTER_POINTS)[:SCATTER_POINTS]
            self.sample, self.keys = self.sample[best], self.keys[best]

    def bias_sigma(self) -> tuple[float, float, float, float]:
        """Mean and standard deviation of the range (m) and azimuth (deg) residuals outside
        the gated plots."""
        n, s1, s2, a1, a2 = self.total
        if n == 0:
            return (np.nan,) * 4  # type: ignore[return-value]
        return (s1 / n, float(np.sqrt(max(s2 / n - (s1 / n) ** 2, 0.0))), a1 / n,
                float(np.sqrt(max(a2 / n - (a1 / n) ** 2, 0.0))))


def _range_bins() -> int:
    return int(MAX_RANGE_M // RANGE_BIN_M) + 1


def _azimuth_bins() -> int:
    return round(360.0 / AZIMUTH_BIN_DEG)


def _range_bin(r: FloatArray) -> np.ndarray:
    return np.minimum((r // RANGE_BIN_M).astype(int), _range_bins() - 1)


def _azimuth_bin(a: FloatArray) -> np.ndarray:
    return (np.mod(a, 360.0) // AZIMUTH_BIN_DEG).astype(int) % _azimuth_bins()


def radar_residuals(out: Path, order: Sequence[str] = ()) -> list[RadarResiduals]:
    """Every radar's residuals in the run at ``out`` (its ``tracks.parquet`` parts), in the
    order of the ids ``order`` (the sensor file's), others after them by id; radars without a
    residual (none reconstructed) are left out."""
    rng = np.random.default_rng(0)
    radars: dict[str, RadarResiduals] = {}
    for part in sorted((out / "tracks.parquet").glob("part-*.parquet")):
        names = set(pq.read_schema(part).names)
        if not set(_COLUMNS) <= names:  # a part of an earlier version: no residuals
            continue
        t = pq.read_table(part, columns=_COLUMNS)
        cols = {c: t.column(c).to_numpy(zero_copy_only=False) for c in _COLUMNS}
        dr = cols["range_residual_m"].astype(float)
        found = np.isfinite(dr)
        sensors = cols["sensor"].astype(str)
        keys = rng.random(t.num_rows)
        for sid in dict.fromkeys(sensors[found].tolist()):
            sel = found & (sensors == sid)
            radars.setdefault(sid, RadarResiduals(sid)).add(
                cols["plot_range_m"][sel].astype(float), cols["plot_azimuth_deg"][sel].astype(
                    float), dr[sel], cols["azimuth_residual_deg"][sel].astype(float),
                cols["gated"][sel].astype(bool), keys[sel])
    rank = {sid: k for k, sid in enumerate(order)}
    return sorted(radars.values(), key=lambda x: (rank.get(x.sensor, len(rank)), x.sensor))


def write_sensors_figure(out: Path, order: Sequence[str] = ()) -> Path | None:
    """``out/sensors.png`` (:func:`solver.figures.residuals_figure`; radars in the order of the
    ids ``order``), or None when no radar plot has a residual."""
    from .figures import residuals_figure, save

    radars = radar_residuals(out, order)
    if not radars:
        return None
    return save(residuals_figure(radars), out / "sensors.png")
