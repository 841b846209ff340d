"""Mode C pressure altitudes made geometric by the aircraft's own ADS-B.

A radar plot's slant range becomes a ground range with the aircraft's height above the radar
(:mod:`solver.sensors`), and Mode C gives a *pressure* altitude (``FL * 30.48`` m, the standard
atmosphere), which differs from the geometric height (above the WGS-84 ellipsoid, as the radar
sites are given) by the day's pressure and temperature and the geoid: typically 100-300 m, and
more with height in a warm or cold air mass. Near a radar that error is a ground-range error
of ``h * dh / d``: on the benchmark's SSR tracks a 100-300 m offset doubled the error within
30 km of the radar (23.6 -> 44.1 m, ``benchmarks/results/mode_c.md``), and a 250-m offset showed
in the radar's statistics as a -54 to -60 m range bias.

An aircraft that reports ADS-B gives both its geometric height (CAT021 I140) and its barometric
altitude (I145, the same encoder as its Mode C): their difference is the offset, report by
report. :func:`geometric_altitudes` takes the running median of those differences over
:data:`OFFSET_WINDOW_S` (the quantisation of both, 25 ft, averages out; the offset drifts as
the aircraft climbs) and adds it to every pressure altitude of the track (held at the value
nearest in time beyond the reports' ends). Without such pairs in one report, a geometric height
within :data:`MATCH_S` of a pressure altitude of the same aircraft (another sensor) pairs with
it. Without any pair, or with fewer than :data:`MIN_PAIRS`, the altitudes stay as they are.

Which altitude is which, from the plot rows (:class:`solver.io.tables.PlotRows`): a row's
``altitude_m`` is a pressure altitude when it is its ``flight_level`` times 30.48 m (the readers
set it so from a Mode C or an I145 flight level, a table from its ``flight_level`` column), and
geometric when a position sensor's row carries another (CAT021 I140, a table's own
``altitude_m`` beside or without a flight level). A radar row with its own ``altitude_m`` that is
not its flight level's (a 3-D radar's height, a user's table) is left as it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..inputs import FloatArray
from .tables import FL_M

OFFSET_WINDOW_S = 120.0
"""The running median of the offsets spans this many seconds."""
MATCH_S = 5.0
"""A geometric height pairs with a pressure altitude of another plot at most this far in time."""
MIN_PAIRS = 3
"""Fewer pairs than this leave the altitudes as they are."""
MAX_OFFSET_M = 1_500.0
"""A geometric height further than this from the barometric altitude is not an offset of the
atmosphere (QNH moves it some 400 m at sea level, a 30 K warm or cold air mass 10 % of the
height) but a bad height (a report of 0 m at 9 km moved every Mode C of its aircraft to 0 m: a
review helper): such pairs are not used, and counted (``rejected``)."""
PRESSURE_TOLERANCE_M = 0.01
"""An altitude within this of its flight level's is that flight level's pressure altitude."""


@dataclass(frozen=True)
class Offsets:
    """The altitudes with the pressure ones made geometric (``altitude_m``), how many were
    (``corrected``), and the offset's median and pair count (None and 0 without pairs)."""

    altitude_m: FloatArray
    corrected: int
    median_m: float | None
    pairs: int
    rejected: int = 0  # pairs further apart than MAX_OFFSET_M, not used


def geometric_altitudes(t: FloatArray, altitude_m: FloatArray, flight_level: FloatArray,
                        is_position: np.ndarray) -> Offsets:
    """One aircraft's altitudes (rows in time order) with every pressure altitude moved by the
    offset its ADS-B reports give (module docstring)."""
    t = np.asarray(t, dtype=float)
    alt = np.asarray(altitude_m, dtype=float)
    fl = np.asarray(flight_level, dtype=float)
    pressure = np.isfinite(fl) & np.isfinite(alt) & (
        np.abs(alt - fl * FL_M) <= PRESSURE_TOLERANCE_M)
    geometric = np.asarray(is_position, dtype=bool) & np.isfinite(alt) & ~pressure
    both = geometric & np.isfinite(fl)  # a report with both: its own offset
    if np.count_nonzero(both) >= MIN_PAIRS:
        at, offset = t[both], alt[both] - fl[both] * FL_M
    else:
        at, offset = _matched(t, alt, fl, pressure, geometric)
    plausible = np.abs(offset) <= MAX_OFFSET_M
    rejected = int(np.count_nonzero(~plausible))
    at, offset = at[plausible], offset[plausible]
    if at.size < MIN_PAIRS or not pressure.any():
        return Offsets(alt, 0, None, int(at.size), rejected)
    smooth = _running_median(at, offset, OFFSET_WINDOW_S)
    out = alt.copy()
    out[pressure] = alt[pressure] + np.interp(t[pressure], at, smooth)
    return Offsets(out, int(np.count_nonzero(pressure)), float(np.median(offset)), int(at.size),
                   rejected)


def moved_note(got: Offsets) -> str | None:
    """What a track's answer says of its pressure altitudes made geometric (None: none
    moved): the single request's warning, and a job's or the command line's track's."""
    if not got.corrected or got.median_m is None:
        return None
    return (f"{got.corrected} pressure altitude(s) made geometric by the aircraft's ADS-B: "
            f"{got.median_m:+.1f} m (median of {got.pairs} pairs; running median over "
            f"{OFFSET_WINDOW_S:g} s)")


def _matched(t: FloatArray, alt: FloatArray, fl: FloatArray, pressure: np.ndarray,
             geometric: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """``(times, geometric - pressure)`` of each pressure altitude with a geometric height of
    the aircraft within :data:`MATCH_S`, that height interpolated between its neighbours (or
    the nearest when only one side is that close)."""
    g = np.flatnonzero(geometric)
    p = np.flatnonzero(pressure)
    if g.size == 0 or p.size == 0:
        return np.empty(0), np.empty(0)
    tg, hg = t[g], alt[g]
    j = np.searchsorted(tg, t[p])
    before = np.clip(j - 1, 0, g.size - 1)
    after = np.clip(j, 0, g.size - 1)
    gap_before = np.abs(t[p] - tg[before])
    gap_after = np.abs(tg[after] - t[p])
    near = np.minimum(gap_before, gap_after) <= MATCH_S
    both_sides = (gap_before <= MATCH_S) & (gap_after <= MATCH_S) & (after > before)
    h = np.where(gap_before <= gap_after, hg[before], hg[after])
    span = tg[after] - tg[before]
    w = np.divide(t[p] - tg[before], span, out=np.zeros_like(span), where=span > 0)
    h = np.where(both_sides, hg[before] + w * (hg[after] - hg[before]), h)
    return t[p][near], (h - fl[p] * FL_M)[near]


def _running_median(t: FloatArray, v: FloatArray, window_s: float) -> FloatArray:
    """Median of ``v`` over about ``window_s`` around each value (``t`` sorted): a window of
    as many values as the median spacing puts in it, the ends padded with the end values
    (numpy's sliding windows: reports come at a steady rate, and a Python median per value
    cost 10 us each in the reader's thread; scipy.ndimage is not in the Docker image)."""
    step = float(np.median(np.diff(t))) if t.size > 1 else window_s
    size = int(np.clip(window_s / max(step, 1e-3), 1, t.size)) | 1
    padded = np.pad(v, size // 2, mode="edge")
    return np.median(sliding_window_view(padded, size), axis=1)


def offsets_summary(offsets: list[float]) -> dict[str, float | int] | None:
    """What a run's ``summary.json`` says of the tracks whose Mode C was moved
    (``mode_c_offsets``): how many, and the median and range of their offsets (m, geometric
    minus pressure); None when none was."""
    if not offsets:
        return None
    v = np.asarray(offsets, dtype=float)
    return {"tracks": int(v.size), "median_m": round(float(np.median(v)), 1),
            "min_m": round(float(v.min()), 1), "max_m": round(float(v.max()), 1)}


__all__ = ["MATCH_S", "MIN_PAIRS", "OFFSET_WINDOW_S", "Offsets", "geometric_altitudes",
           "offsets_summary"]
