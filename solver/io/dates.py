"""A recording's date: the UTC date of the midnight its ``t`` counts from, and UTC times of it.

Recordings timed by time of day (ASTERIX; a plot table's ``time_of_day_s``) have ``t`` in
seconds from the UTC midnight before their first plot, and no date. It is known:

- from a capture's packet times (epoch seconds, :class:`CaptureClock`): each row's packet time
  less its ``t`` is that midnight, up to the network's latency and the capture clock's error;
  rows where it is more than :data:`CLOCK_TOLERANCE_S` off a midnight are reported
  (``clock_disagreement``), and the date is taken only where most rows agree on one;
- from a plot table's ``timestamp`` column (:mod:`solver.io.tables`);
- from the user (``--date``, a job's ``options.date``; :func:`parse_date`), checked
  against the recording's own (:func:`resolve_date`): it overrides a capture's (a host clock
  may be whole days off with the right time of day, which the check above cannot see),
  reported (``date_override``); one that contradicts a table's ``timestamp`` is an error.

An IOSS (FINAL) frame's one-byte "recording day" gives no date: 0 in jASTERIX's samples, no
month or year (a day count of the recorder's, not a calendar date), so it is not used.

UTC times are ``date`` midnight plus ``t`` (:func:`utc_times`), numpy ``datetime64`` and
Arrow ``timestamp[us, tz=UTC]`` arithmetic (POSIX time: no leap seconds, as ASTERIX's time of
day and the tools it is compared with, SASS-C, TRES, ARTAS, ``traffic``).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from ..inputs import FloatArray, InputError
from .problems import Problems

DAY_S = 86_400.0
UTC = pa.timestamp("us", tz="UTC")
"""Arrow type of the UTC time columns (microseconds: ASTERIX's 1/128 s to half a microsecond;
read by pandas, Spark and every Parquet reader)."""
CLOCK_TOLERANCE_S = 60.0
"""How far a capture's packet time may be from its report's time of day (s): a radar sends a
sector's plots within its scan (4-12 s), an ADS-B ground station within 1-2 s, the network
adds milliseconds, and a capturing host's clock without NTP drifts seconds a day. A capture
replayed later, or a recording captured on another host clock, is off by hours: reported, and
its packet times give no date."""
_DATE = re.compile(r"\d{4}-\d{2}-\d{2}")


def parse_date(text: str, loc: tuple[str | int, ...] = ("date",)) -> str:
    """``YYYY-MM-DD`` checked (a real calendar day, by numpy); :class:`InputError` at
    ``loc`` otherwise."""
    text = text.strip()
    day: np.datetime64 | None = None
    if _DATE.fullmatch(text):
        try:
            day = np.datetime64(text, "D")
        except ValueError:
            day = None
    if day is None or str(day) != text:
        raise InputError(loc, f"{text!r} is not a date YYYY-MM-DD (the UTC date of the "
                         "midnight the recording's times of day count from)")
    return text


def utc_times(t: FloatArray, date: str | None) -> pa.Array:
    """``date``'s UTC midnight plus ``t`` seconds as ``timestamp[us, tz=UTC]`` (null where
    ``t`` is not finite, all null without a date)."""
    t = np.asarray(t, dtype=float)
    fin = np.isfinite(t)
    if date is None:
        return pa.nulls(t.size, UTC)
    us = np.round(np.where(fin, t, 0.0) * 1e6).astype(np.int64)
    stamps = np.datetime64(date, "us") + us.astype("timedelta64[us]")
    return pa.array(stamps.astype(np.int64), pa.int64(), mask=~fin).cast(UTC)


def midnight_us(states: pa.Table) -> int | None:
    """The UTC time (epoch us) a run's ``t`` counts from, off its stored states: ``time_utc -
    t`` of the first state that has both; None where none has (the recording's date is not
    known, or the states were stored before the column)."""
    if "time_utc" not in states.column_names:
        return None
    utc = states.column("time_utc").cast(UTC).cast(pa.int64())
    t = states.column("t")
    known = np.flatnonzero(utc.is_valid().to_numpy(zero_copy_only=False)
                           & np.isfinite(t.to_numpy(zero_copy_only=False).astype(float)))
    if not known.size:
        return None
    i = int(known[0])
    return int(utc[i].as_py()) - round(float(t[i].as_py()) * 1e6)


def date_of(midnight: int | None) -> str | None:
    """``YYYY-MM-DD`` of a midnight in epoch us (:func:`midnight_us`)."""
    return None if midnight is None else str(np.datetime64(midnight, "us").astype("datetime64[D]"))


def iso_utc(times: pa.Array | pa.ChunkedArray) -> pa.Array | pa.ChunkedArray:
    """UTC times as ISO 8601 text ending in ``Z`` (``2024-03-09T10:00:00.007812Z``; null where
    null)."""
    return pc.strftime(times.cast(UTC), format="%Y-%m-%dT%H:%M:%SZ")


@dataclass
class CaptureClock:
    """The date a capture's packet times give its rows (fed part by part, in order).

    For each row with a packet time ``p`` (epoch s) and ``t`` (s from the recording's
    midnight), ``p - t`` is that midnight plus the row's delay and the clock's error: the
    nearest midnight is the row's vote, taken where it is within :data:`CLOCK_TOLERANCE_S`.
    The first part with timed rows decides (parts are read before any track is reconstructed
    from them): the day most agreeing rows give, if they are the majority of the part's timed
    rows. Every disagreeing row is counted in a ``clock_disagreement`` problem (located at its
    first), and agreeing rows of another day in a ``date_disagreement`` one: the times of day
    then do not count from one midnight (two captures of different days joined)."""

    date: str | None = None
    decided: bool = False

    def add(self, t: FloatArray, received_s: FloatArray, where: Callable[[int], str],
            problems: Problems) -> None:
        """Rows' ``t`` and packet times (NaN: none; a time on 1970-01-01, a clock never set, as
        dpkt's writer's default 0, counts as none); ``where(i)``: where row ``i`` is (for the
        problems). Vectorised but for one ``Problems.add`` per disagreeing row (its count)."""
        t = np.asarray(t, float)
        p = np.asarray(received_s, float)
        timed = np.isfinite(t) & np.isfinite(p) & (p >= DAY_S)
        if not timed.any():
            return
        idx = np.flatnonzero(timed)
        off = p[idx] - t[idx]
        day = np.round(off / DAY_S)
        err = off - day * DAY_S
        agree = np.abs(err) <= CLOCK_TOLERANCE_S
        bad = np.flatnonzero(~agree)
        if bad.size:
            at, message = where(int(idx[bad[0]])), (
                f"the packet time is {err[bad[0]]:+.1f} s off the report's time of day (more "
                f"than {CLOCK_TOLERANCE_S:g} s): a replayed capture, or the capturing host's "
                "clock is wrong; its packet times give no date where they disagree")
            for _ in range(bad.size):  # one per row: the count is the rows'
                problems.add("clock_disagreement", at, message, key="clock")
        days, votes = np.unique(day[agree].astype(np.int64), return_counts=True)
        names = [str(d) for d in days.astype("datetime64[D]")]
        if not self.decided:
            self.decided = True
            if 2 * int(votes.sum()) > off.size:
                self.date = names[int(np.argmax(votes))]
            else:
                problems.add("clock_disagreement", "capture", f"{bad.size} of the first "
                             f"{off.size} packet-timed reports disagree with their packet "
                             "times: the capture gives no date (give it: --date, a job's "
                             "options.date)", key="no date")
        if self.date is None:
            return
        for d, name in zip(days.tolist(), names, strict=True):
            if name == self.date:
                continue
            rows = idx[np.flatnonzero(agree & (day == d))]
            at = where(int(rows[0]))
            message = (f"packet times put this report on a day counted from {name}, the "
                       f"capture's is {self.date}: its times of day do not count from one "
                       "midnight (captures of several days joined?)")
            for _ in range(rows.size):
                problems.add("date_disagreement", at, message, key=name)


def resolve_date(own: str | None, given: str | None, what: str, *, clock: bool = False,
                 problems: Problems | None = None) -> str | None:
    """The date to time a recording by: the one given, else its own (``what`` says where
    from). When both are known and differ: a date of a capture's packet times (``clock``: a
    host clock whole days off keeps the right time of day, so no ``clock_disagreement`` shows
    it) yields to the given one, reported in ``problems`` as ``date_override`` naming both;
    a date the data hold (a table's ``timestamp``) is an :class:`InputError` at ``date``."""
    if given is None or own is None or given == own:
        return own if own is not None else given
    if not clock:
        raise InputError(("date",), f"{given} contradicts the recording's own date {own} "
                         f"({what}): leave the date out, or correct it")
    if problems is not None:
        problems.add("date_override", "date", f"the date given, {given}, overrides {own} "
                     f"({what}): the capturing host's clock is taken as wrong by "
                     f"{_days_between(own, given)}; the UTC times are on {given}", key="date")
    return given


def _days_between(own: str, given: str) -> str:
    days = int((np.datetime64(given, "D") - np.datetime64(own, "D")).astype(int))
    return f"{abs(days)} day{'s' * (abs(days) != 1)} ({'behind' if days > 0 else 'ahead'})"
