"""The plot table of a whole recording: one plot per row, every aircraft and sensor mixed.

:class:`PlotRows` holds it as columns (numpy arrays); :func:`read_table` reads it from CSV or
Parquet, :func:`write_table` writes it. Both the ASTERIX decoder (:mod:`solver.io.asterix`) and
a user's own table end here; :mod:`solver.io.split` cuts it into one
:class:`solver.plots.PlotTable` per aircraft.

File format (``../shared/spec/recordings.md``; units in the names; CSV with a header line, or
Parquet with these column names):

==================  =======================================================================
column              meaning
==================  =======================================================================
``t``               time (s, any epoch), or instead
``time_of_day_s``   seconds since UTC midnight, wrapping at 86400: made monotonic in row
                    order (:func:`unwrap_time_of_day`); ``t`` is then seconds since the UTC
                    midnight before the first row (with both, ``t`` is used and
                    ``time_of_day_s`` kept beside it, as :func:`write_table` writes them)
``timestamp``       or instead a UTC time (ISO 8601 text with ``Z``, an offset or none:
                    UTC; epoch seconds; a Parquet timestamp): ``t`` is then seconds since the
                    UTC midnight before the first row, ``time_of_day_s`` its time of day,
                    and that midnight's date :attr:`PlotRows.date`; a ``t`` or
                    ``time_of_day_s`` beside it must agree within 1 ms (else a bad value)
``sensor``          sensor id (of the sensor file), required
``range_m``         slant range (m) and ...
``azimuth_deg``     ... azimuth (degrees clockwise from true north): a radar plot, or
``lat_deg``         WGS-84 latitude and ...
``lon_deg``         ... longitude (degrees): a position (ADS-B) plot
``altitude_m``      optional: altitude (m; geometric or pressure altitude as the source gives it)
``flight_level``    optional: Mode C / barometric flight level (100 ft); without ``altitude_m``
                    it gives the pressure altitude ``altitude_m = FL * 30.48``
``mode_s``          optional: 24-bit ICAO aircraft address, hex (``4CA2D1``)
``mode_3a``         optional: Mode 3/A code, 4 octal digits (``7000``)
``track_number``    optional: the sensor's track number (integer >= 0)
``aircraft``        optional: an aircraft key the user already has (overrides the others; not
                    ending in ``#<number>`` or ``~<number>``, the names of a key's piece
                    after a time gap and of another aircraft found under a key)
``on_ground``       optional: ``true``/``false`` (or ``1``/``0``; Parquet: boolean or
                    integer), the report says the aircraft is on the ground or airborne
                    (ADS-B's GBS, Mode S's flight status); empty: not said. Rows voted on the
                    ground are left out, counted as ``on_ground``, and a landing ends the
                    aircraft's track (the aircraft model is that of flight;
                    :mod:`solver.io.split`)
==================  =======================================================================

Empty cells (CSV) and nulls (Parquet) are missing values; in Parquet, ``mode_s`` and
``track_number`` may be integers (the value itself) and ``mode_3a`` an integer of its octal
digits (7000), also as floats of whole numbers with NaN missing (as pandas writes an
integer column with missing values). A row needs a time, a sensor and
either ``range_m`` + ``azimuth_deg`` or ``lat_deg`` + ``lon_deg``. A missing required column
raises :class:`solver.InputError` naming it; a bad value (unparsable, non-finite, out of range)
is reported as a problem naming the row (1-based data row; in CSV files line = row + 1) and
column, the row is skipped and counted, and the rest of the table is read; other columns (a
callsign, a comment) are read past and reported once as ``unknown_column`` (``strict=True``
raises instead of either).
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from ..inputs import MAX_AZIMUTH_DEG, MAX_LON_DEG, FloatArray, InputError, wrap_lon
from .dates import iso_utc, utc_times
from .problems import Problems

DAY_S = 86_400.0
FT_M = 0.3048
FL_M = 30.48  # one flight level (100 ft) in metres
NO_INT = -1  # missing mode_s / mode_3a / track_number
PIECE_NAME = re.compile(r"#\d+$")
"""How an aircraft key's later pieces are named (``KEY#2``; :mod:`solver.io.split`)."""
APART_NAME = re.compile(r"~\d+$")
"""How another aircraft found under a key is named (``KEY~2``; :mod:`solver.io.split`)."""

FLOAT_COLUMNS = ("range_m", "azimuth_deg", "lat_deg", "lon_deg", "altitude_m", "flight_level")
INT_COLUMNS = ("mode_s", "mode_3a", "track_number")
_META = ("origin_unit", "date")  # PlotRows' fields of the whole table, not columns
STR_COLUMNS = ("sensor", "aircraft")


@dataclass(frozen=True)
class PlotRows:
    """A recording's plots as columns (rows in recording order).

    ``t``: s, monotonic across midnight when it came from a time of day; ``time_of_day_s``: the
    time of day as recorded (NaN when the source gave ``t``). Float columns are NaN where
    missing, ``mode_s`` / ``mode_3a`` / ``track_number`` -1 (``mode_3a`` holds the code's
    value, ``0o7000``), ``aircraft`` ``""``. ``origin`` locates each row in its source:
    ``origin_unit`` ``"byte"`` (offset of the row's ASTERIX record in the file) or ``"row"``
    (1-based data row of a table). ``date``: the UTC date (``YYYY-MM-DD``) of the midnight
    ``t`` counts from, where the source gives it (a capture's packet times, a table's
    ``timestamp``; :mod:`solver.io.dates`), else None.
    """

    t: FloatArray
    time_of_day_s: FloatArray
    sensor: np.ndarray  # str objects
    range_m: FloatArray
    azimuth_deg: FloatArray
    lat_deg: FloatArray
    lon_deg: FloatArray
    altitude_m: FloatArray
    flight_level: FloatArray
    mode_s: np.ndarray  # int64
    mode_3a: np.ndarray  # int64
    track_number: np.ndarray  # int64
    aircraft: np.ndarray  # str objects
    origin: np.ndarray  # int64
    on_ground: np.ndarray  # int8: 1 on the ground, 0 airborne, -1 not said
    origin_unit: str = "row"
    date: str | None = None

    @classmethod
    def from_columns(cls, n: int, origin_unit: str = "row", date: str | None = None,
                     **cols: object) -> PlotRows:
        """Rows from column arrays; absent columns are missing values."""
        out: dict[str, object] = {}
        for f in fields(cls):
            if f.name in _META:
                continue
            v = cols.pop(f.name, None)
            if f.name == "on_ground":
                arr = np.full(n, -1, np.int8) if v is None else np.asarray(v, dtype=np.int8)
            elif f.name in INT_COLUMNS or f.name == "origin":
                arr = (np.full(n, NO_INT, np.int64) if v is None
                       else np.asarray(v, dtype=np.int64))
                if f.name == "origin" and v is None:
                    arr = np.arange(1, n + 1, dtype=np.int64)
            elif f.name in STR_COLUMNS:
                arr = (np.full(n, "", dtype=object) if v is None
                       else np.asarray(v, dtype=object))
            else:
                arr = np.full(n, np.nan) if v is None else np.asarray(v, dtype=float)
            if arr.shape != (n,):
                raise ValueError(f"column {f.name} has shape {arr.shape}, expected ({n},)")
            out[f.name] = arr
        if cols:
            raise TypeError(f"unknown columns {sorted(cols)}")
        return cls(origin_unit=origin_unit, date=date, **out)  # type: ignore[arg-type]

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def take(self, idx: np.ndarray) -> PlotRows:
        """The rows ``idx`` (indexes or a boolean mask)."""
        return replace(self, **{f.name: getattr(self, f.name)[idx] for f in fields(self)
                                if f.name not in _META})

    @staticmethod
    def concat(parts: Sequence[PlotRows]) -> PlotRows:
        """Rows of several parts (same ``origin_unit``) one after the other (the first
        ``date`` known: the parts of one recording share it)."""
        if not parts:
            return PlotRows.from_columns(0)
        units = {p.origin_unit for p in parts}
        if len(units) > 1:
            raise ValueError(f"cannot concatenate rows of origins {sorted(units)}")
        date = next((p.date for p in parts if p.date is not None), None)
        return replace(parts[0], date=date, **{
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in fields(PlotRows) if f.name not in _META})

    def where(self, i: int) -> str:
        """Where row ``i`` came from, in the user's terms (``"byte 1234"``, ``"row 17"``)."""
        return f"{self.origin_unit} {int(self.origin[i])}"

    def is_radar(self) -> np.ndarray:
        """Rows carrying a slant range and an azimuth."""
        return np.isfinite(self.range_m) & np.isfinite(self.azimuth_deg)

    # ------------------------------------------------------------------------ arrow

    def to_arrow(self) -> pa.Table:
        """The documented table: ``t``, ``time_of_day_s`` (when known), ``timestamp`` (UTC, when
        the date is known), measurements, and the
        keys with nulls where missing (``mode_s`` hex, ``mode_3a`` octal strings)."""
        def floats(a: FloatArray) -> pa.Array:
            return pa.array(a, type=pa.float64(), from_pandas=True)  # NaN -> null

        def ints(a: np.ndarray) -> pa.Array:
            return pa.array(a, type=pa.int64(), mask=a < 0)

        cols: dict[str, pa.Array] = {"t": pa.array(self.t, pa.float64())}
        if np.isfinite(self.time_of_day_s).any():
            cols["time_of_day_s"] = floats(self.time_of_day_s)
        if self.date is not None:  # read back, it gives the date again
            cols["timestamp"] = utc_times(self.t, self.date)
        cols["sensor"] = pa.array(self.sensor.tolist(), pa.string())
        for name in FLOAT_COLUMNS:
            cols[name] = floats(getattr(self, name))
        cols["mode_s"] = pa.array([f"{v:06X}" if v >= 0 else None for v in self.mode_s.tolist()],
                                  pa.string())
        cols["mode_3a"] = pa.array([f"{v:04o}" if v >= 0 else None
                                    for v in self.mode_3a.tolist()], pa.string())
        cols["track_number"] = ints(self.track_number)
        cols["aircraft"] = pa.array([a or None for a in self.aircraft.tolist()], pa.string())
        if (self.on_ground >= 0).any():
            cols["on_ground"] = pa.array(self.on_ground == 1, pa.bool_(),
                                         mask=self.on_ground < 0)
        return pa.table(cols)



# ---------------------------------------------------------------------------- time of day


def unwrap_time_of_day(tod: FloatArray, previous: float = np.nan) -> FloatArray:
    """Seconds since the UTC midnight before the first value, from times of day in recording
    order: each value is put on the day that brings it closest to the value before it, so the
    times grow across midnight (86399.9 then 0.1 -> 86400.1) while a late report from just
    before midnight, arriving after one from just after, stays on its own day (jumps of less
    than 12 h either way are taken as they are). ``previous``: the unwrapped time before the
    first value (a recording read in pieces). Non-finite values stay as they are before the
    first finite one (or ``previous``), NaN after it.

    Vectorised: the day of each finite value is the day of the one before plus the rounded
    jump between the two in days (their sum over the values); where a jump is within 1e-9
    day of a half day (where rounding the day-shifted difference, as :func:`_unwrap_loop`
    does, could differ) the values are unwrapped one by one."""
    tod = np.asarray(tod, dtype=float)
    prev = float(previous)
    fin = np.isfinite(tod)
    idx = np.flatnonzero(fin)
    out = tod.copy()
    if np.isfinite(prev):
        out[~fin] = np.nan
    elif idx.size:
        after = out[idx[0] + 1:]
        after[~fin[idx[0] + 1:]] = np.nan
    if idx.size == 0:
        return out
    v = tod[idx]
    jump = (v[:-1] - v[1:]) / DAY_S
    if np.any(np.abs(np.abs(jump - np.floor(jump)) - 0.5) < 1e-9):
        return _unwrap_loop(tod, prev)
    first = np.round((prev - v[0]) / DAY_S) if np.isfinite(prev) else 0.0
    day = np.empty_like(v)
    day[0] = first
    np.cumsum(np.round(jump), out=day[1:])
    day[1:] += first
    out[idx] = v + day * DAY_S
    return out


def counts_from_midnight(rows: PlotRows) -> bool:
    """Whether the rows' ``t`` is seconds from a UTC midnight: every row has a time of day and
    it is ``t`` modulo a day (a recording timed by time of day: ASTERIX, a table with
    ``time_of_day_s`` and no ``t``). A table's own ``t`` (any epoch) is not, unless it agrees."""
    tod = rows.time_of_day_s
    if len(rows) == 0 or not np.isfinite(tod).all():
        return False
    d = np.abs(np.mod(rows.t, DAY_S) - tod)
    return bool(np.all(np.minimum(d, DAY_S - d) < 1e-6))


def _unwrap_loop(tod: FloatArray, previous: float) -> FloatArray:
    """:func:`unwrap_time_of_day` value by value."""
    out = np.empty_like(tod)
    day = 0.0
    prev = float(previous)
    for i, v in enumerate(tod.tolist()):
        if np.isfinite(prev):
            day = np.round((prev - v) / DAY_S)
        out[i] = v + day * DAY_S
        if np.isfinite(out[i]):
            prev = out[i]
    return out


# ---------------------------------------------------------------------------- reading


def time_disorder_s(path: str | Path) -> float:
    """How far (s) a row of a plot table comes after a later-timed one, at most (0: in time
    order), from its time column alone (``t``, else ``time_of_day_s`` unwrapped in row order;
    unreadable times skipped): whether it can be split as it is read in batches
    (:func:`solver.io.split.split_stream`) or must be read whole and sorted first. A file this
    cannot read gives 0: the reader then says what is wrong with it (a non-Parquet file, two
    `t` columns, CR line ends made tracebacks here; a fuzz helper)."""
    try:
        return _time_disorder_s(Path(path))
    except (csv.Error, pa.ArrowException, OSError, UnicodeDecodeError, ValueError):
        return 0.0


def _time_disorder_s(path: Path) -> float:
    path = Path(path)
    if path.suffix.lower() in (".parquet", ".pq"):
        raw_names = pq.read_schema(path).names
        names = [n.strip() for n in raw_names]
        name = _time_column(names)
        if name is None:
            return 0.0  # no time column: read_table says so
        col = pq.read_table(path, columns=[raw_names[names.index(name)]]).column(0)
    else:
        with open(path, "rb") as f:
            first = f.readline().decode("utf-8-sig", errors="replace")
        header = next(csv.reader(first.splitlines()[:1]), [])
        names = [h.strip() for h in header]
        name = _time_column(names)
        if name is None:
            return 0.0
        raw = header[names.index(name)]
        try:
            col = pacsv.read_csv(
                path, parse_options=pacsv.ParseOptions(invalid_row_handler=lambda _: "skip"),
                convert_options=pacsv.ConvertOptions(
                    include_columns=[raw], column_types={raw: pa.string()},
                    strings_can_be_null=True, check_utf8=False)).column(0)
        except pa.ArrowInvalid:
            return 0.0  # read_table says what is wrong with it
    if name == "timestamp":
        ns = timestamp_ns(col, lambda *_: None)
        col = pa.array(np.where(ns == NO_TIME, np.nan, ns / 1e9), pa.float64())
    elif not pa.types.is_floating(col.type) and not pa.types.is_integer(col.type):
        text = pc.utf8_trim_whitespace(col.cast(pa.string()))
        numeric = pc.match_substring_regex(text, r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
        col = pc.if_else(numeric, text, pa.scalar(None, pa.string())).cast(pa.float64())
    t = np.asarray(col.cast(pa.float64()).to_numpy(zero_copy_only=False), dtype=float)
    t = t[np.isfinite(t)]
    if name == "time_of_day_s":
        t = unwrap_time_of_day(t)
    return float(np.max(np.maximum.accumulate(t) - t)) if t.size else 0.0


def _time_column(names: list[str]) -> str | None:
    """The column a table is timed by, as :func:`rows_from_arrow` takes it."""
    return next((n for n in ("timestamp", "t", "time_of_day_s") if n in names), None)


def _is_utf8(value: bytes) -> bool:
    try:
        value.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def read_table(path: str | Path, *, strict: bool = False, problems: Problems | None = None
               ) -> tuple[PlotRows, Problems]:
    """Read a plot table (``.parquet`` / ``.pq`` as Parquet, anything else as CSV).

    Returns the good rows and the problems (bad rows named and counted). Raises
    :class:`InputError` at ``(column,)`` for a missing required column, or (``strict``) at
    ``("rows", N, column)`` for the first bad value.
    """
    path = Path(path)
    if path.suffix.lower() in (".parquet", ".pq"):
        try:
            table = pq.read_table(path)
        except (pa.ArrowException, OSError) as e:
            raise InputError(("file",), f"{path.name} is not a readable Parquet file: {e}"
                             ) from None
        return rows_from_arrow(table, strict=strict, problems=problems, csv_lines=False)
    return read_csv(path.read_bytes(), strict=strict, problems=problems)


def read_csv(data: bytes, *, strict: bool = False, problems: Problems | None = None
             ) -> tuple[PlotRows, Problems]:
    """Read a CSV plot table from bytes (every column read as text, then converted here so a
    bad value is named by its row)."""
    first = _header_line(data.split(b"\n", 1)[0])
    header = next(csv.reader(first.splitlines()[:1]), [])
    if not header or not any(h.strip() for h in header):
        raise InputError(("file",), "has no header line")
    odd = _OddRows()
    try:
        table = pacsv.read_csv(io.BytesIO(data), parse_options=odd.parse_options(),
                               convert_options=_csv_convert_options(header))
    except pa.ArrowInvalid as e:
        raise InputError(("file",), f"is not a readable CSV table: {e}") from None
    problems = problems if problems is not None else Problems()

    def numbered() -> tuple[np.ndarray, np.ndarray]:
        records = _CsvRecords(io.TextIOWrapper(io.BytesIO(data), encoding="utf-8-sig",
                                               errors="replace", newline=""), len(header))
        out = records.take(table.num_rows, problems, strict)
        records.take(0, problems, strict, to_end=True)
        return out

    # rows skipped: numbered now; else only when a problem needs its line (a quoted newline
    # or a blank line before it moves the lines: the rows' numbers are Arrow's)
    return rows_from_arrow(table, strict=strict, problems=problems, csv_lines=True,
                           numbers=numbered() if odd.skipped else numbered)


def _header_line(line: bytes) -> str:
    """A CSV's first line as text; :class:`InputError` when it is not UTF-8 (the column names
    cannot be read: a Latin-1 header made a traceback; a review helper)."""
    try:
        return line.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(("file",), f"has a header line that is not UTF-8 text (byte {e.start}):"
                         " save the table as UTF-8") from None


def _csv_convert_options(header: list[str]) -> pacsv.ConvertOptions:
    """Every column as text (converted, and a bad value named by its row, here); UTF-8 is
    checked here too, per row (:func:`rows_from_arrow`): Arrow's check refused the whole
    table for one Latin-1 byte (a fuzz helper)."""
    return pacsv.ConvertOptions(column_types={h: pa.string() for h in header},
                                strings_can_be_null=True, null_values=[""],
                                quoted_strings_can_be_null=True, check_utf8=False)


class _OddRows:
    """Arrow's CSV parser told to skip a row whose field count is not the header's (one such
    row, a line cut short or a stray comma, refused the whole table; a fuzz helper), noting
    that it did: Arrow does not say where the row was, :class:`_CsvRecords` finds it."""

    def __init__(self) -> None:
        self.skipped = 0

    def parse_options(self) -> pacsv.ParseOptions:
        def skip(_row: Any) -> str:
            self.skipped += 1
            return "skip"
        return pacsv.ParseOptions(invalid_row_handler=skip)


class _CsvRecords:
    """The row and line numbers of a CSV's records by Python's csv reader (RFC 4180 quoting
    as Arrow reads it; blank lines skipped and not numbered, as Arrow does), for the rows
    Arrow kept once it skipped one: each skipped row is reported (``bad_row``, with its row
    and line) and the later rows keep their numbers. About 1 s per 10^6 rows, only for a
    table that has such a row."""

    def __init__(self, lines: Any, fields: int):
        # Arrow reads fields of any length; the csv module stops at 128 KiB by default (a
        # traceback on a long field before a short row; a review helper)
        csv.field_size_limit(max(csv.field_size_limit(), 1 << 30))
        self.reader = csv.reader(lines)
        next(self.reader, None)  # the header
        self.fields = fields
        self.row = 0

    def take(self, kept: int, problems: Problems, strict: bool, *, to_end: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
        """Row and line numbers of the next ``kept`` rows of the header's field count (or,
        ``to_end``, of every row left); the others met on the way reported."""
        rows: list[int] = []
        lines: list[int] = []
        while to_end or len(rows) < kept:
            rec = next(self.reader, None)
            if rec is None:
                break
            if not rec:
                continue
            self.row += 1
            if len(rec) == self.fields:
                rows.append(self.row)
                lines.append(self.reader.line_num)
                continue
            where = f"row {self.row} (line {self.reader.line_num})"
            message = (f"has {len(rec)} field(s), the header {self.fields}: the row is "
                       "skipped")
            if strict:
                raise InputError(("rows", self.row), message)
            problems.add("bad_row", where, message, dropped=1)
        return np.array(rows, dtype=np.int64), np.array(lines, dtype=np.int64)




def iter_table(path: str | Path, *, batch_rows: int = 1 << 17, strict: bool = False,
               problems: Problems | None = None) -> Iterator[PlotRows]:
    """:func:`read_table` in batches of about ``batch_rows`` rows, in order (rows numbered
    and times of day unwrapped across the batches; problems into ``problems``), for
    :func:`solver.io.split.split_stream`: a table of any length in bounded memory."""
    path = Path(path)
    problems = problems if problems is not None else Problems()
    batches: Iterator[pa.RecordBatch]
    if path.suffix.lower() in (".parquet", ".pq"):
        try:
            batches = pq.ParquetFile(path).iter_batches(batch_size=batch_rows)
        except (pa.ArrowException, OSError) as e:
            raise InputError(("file",), f"{path.name} is not a readable Parquet file: {e}"
                             ) from None
        csv_lines = False
    else:
        with open(path, "rb") as f:
            first = _header_line(f.readline())
        header = next(csv.reader(first.splitlines()[:1]), [])
        if not header or not any(h.strip() for h in header):
            raise InputError(("file",), "has no header line")
        odd = _OddRows()
        try:
            batches = pacsv.open_csv(
                path, read_options=pacsv.ReadOptions(block_size=max(batch_rows * 64, 4096)),
                parse_options=odd.parse_options(), convert_options=_csv_convert_options(header))
        except pa.ArrowInvalid as e:
            raise InputError(("file",), f"is not a readable CSV table: {e}") from None
        csv_lines = True
    first_row, previous = 1, np.nan
    date: str | None = None  # a timestamp column's, from the first batch on
    records: _CsvRecords | None = None  # once Arrow skipped a row: the rows' numbers
    text = None
    try:
        while True:
            try:
                batch = next(batches)
            except StopIteration:
                if records is not None:
                    records.take(0, problems, strict, to_end=True)
                return
            except pa.ArrowInvalid as e:
                raise InputError(("file",), f"is not a readable table after row "
                                 f"{first_row - 1}: {e}") from None
            def start(first: int = first_row) -> _CsvRecords:
                """The csv reader, past the rows before this batch (as Arrow read them)."""
                nonlocal records, text
                text = open(path, encoding="utf-8-sig", errors="replace", newline="")
                records = _CsvRecords(text, len(header))
                records.take(first - 1, problems, strict)
                return records

            def numbered(n: int = batch.num_rows) -> tuple[np.ndarray, np.ndarray]:
                return (records or start()).take(n, problems, strict)

            numbers: Any = None
            if csv_lines and records is None and odd.skipped:
                # Arrow has skipped a row in this batch or one it read ahead: number the
                # rows from here on by the csv reader (the rows before: as they came)
                start()
            if records is not None:
                numbers = numbered()
            elif csv_lines:  # numbered only if a problem needs its line (then from here on)
                numbers = numbered
            rows, _ = rows_from_arrow(pa.Table.from_batches([batch]), strict=strict,
                                      problems=problems, csv_lines=csv_lines,
                                      first_row=first_row, previous_t=previous,
                                      date=date, numbers=numbers)
            date = date or rows.date
            first_row += batch.num_rows
            finite = rows.t[np.isfinite(rows.t)]
            if finite.size:
                previous = float(finite[-1])
            yield rows
    finally:
        if text is not None:
            text.close()


def rows_from_arrow(table: pa.Table, *, strict: bool = False, problems: Problems | None = None,
                    csv_lines: bool = False, first_row: int = 1, previous_t: float = np.nan,
                    date: str | None = None,
                    numbers: tuple[np.ndarray, np.ndarray]
                    | Callable[[], tuple[np.ndarray, np.ndarray]] | None = None
                    ) -> tuple[PlotRows, Problems]:
    """Convert and check an Arrow table of the documented columns (see the module docstring).
    ``first_row``: the number of its first row in the file; ``previous_t``: the unwrapped time
    before it (a table read in batches); ``date``: the date a ``timestamp`` column's ``t``
    counts from (of an earlier batch; None: the first row's); ``numbers``: each row's number
    and line in the file
    when they are not ``first_row`` on (a CSV with rows skipped), or a function giving them,
    called when a problem first needs a row's line (the line is ``row + 1`` only when no row
    before it spans lines or is blank)."""
    problems = problems if problems is not None else Problems()
    names = [n.strip() for n in table.column_names]
    table = table.rename_columns(names)
    known = {"t", "time_of_day_s", "timestamp", *STR_COLUMNS, *FLOAT_COLUMNS, *INT_COLUMNS,
             "on_ground"}
    unknown = [n for n in names if n not in known]
    if unknown and strict:
        raise InputError((unknown[0],), f"is not a column of the plot table (columns: "
                         f"{', '.join(sorted(known))})")
    if unknown:  # a user's own columns (a callsign, a comment): read past, said once
        if first_row == 1:
            for name in dict.fromkeys(unknown):
                problems.add("unknown_column", "header", f"`{name}` is not a column of the "
                             f"plot table: ignored (columns: {', '.join(sorted(known))})")
        table = table.select([i for i, name in enumerate(names) if name in known])
    header = ", ".join(names)  # as the file has it, for the messages below
    names = [n for n in names if n in known]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise InputError((dup,), "appears twice in the header")
    for group in (("t", "time_of_day_s", "timestamp"),):
        if not any(g in names for g in group):
            raise InputError(("t",), "is missing: the table needs a `t`, a `time_of_day_s` or "
                             f"a `timestamp` column (columns: {header})")
    if "sensor" not in names:
        raise InputError(("sensor",), f"is missing (columns: {header})")
    radar_cols = [c for c in ("range_m", "azimuth_deg") if c in names]
    pos_cols = [c for c in ("lat_deg", "lon_deg") if c in names]
    if len(radar_cols) == 1 or len(pos_cols) == 1:
        have = (radar_cols or pos_cols)[0]
        other = {"range_m": "azimuth_deg", "azimuth_deg": "range_m", "lat_deg": "lon_deg",
                 "lon_deg": "lat_deg"}[have]
        raise InputError((other,), f"is missing (it goes with `{have}`)")
    if not radar_cols and not pos_cols:
        raise InputError(("range_m",), "is missing: the table needs `range_m` + `azimuth_deg` "
                         "(radar plots) or `lat_deg` + `lon_deg` (position plots)")

    n = table.num_rows
    bad = np.zeros(n, dtype=bool)
    lazy = numbers if callable(numbers) else None
    row_of, line_of = numbers if numbers is not None and lazy is None else (
        np.arange(first_row, first_row + n), np.arange(first_row + 1, first_row + n + 1))

    def check(found: np.ndarray) -> None:
        if len(found) != n:  # the csv reader and Arrow read the records differently
            raise InputError(("file",), f"is not a readable CSV table: {n} rows read after "
                             f"row {first_row - 1} where the csv reader finds {len(found)}")

    check(row_of)

    def where(i: int) -> str:
        """Row ``i``'s place in the file (its line too in a CSV table)."""
        nonlocal lazy, row_of, line_of
        if lazy is not None:  # the first problem: the rows' true lines
            row_of, line_of = lazy()
            lazy = None
            check(row_of)
        return f"row {int(row_of[i])}" + (f" (line {line_of[i]})" if csv_lines else "")

    def report(rows: np.ndarray, column: str, message: str) -> None:
        new = rows[~bad[rows]]
        for i in new.tolist():
            at = where(i)  # first: it numbers the rows
            row = int(row_of[i])
            if strict:
                raise InputError(("rows", row, column), message)
            problems.add("bad_value", at, f"{column}: {message}", dropped=1)
        bad[new] = True

    for name in names:  # text not UTF-8 (read unchecked): a bad value of its row
        col = table.column(name)
        if not (pa.types.is_string(col.type) or pa.types.is_large_string(col.type)):
            continue
        try:
            col.validate(full=True)
            continue
        except pa.ArrowInvalid:
            pass
        raw = col.cast(pa.binary()).to_pylist()
        odd = np.array([v is not None and not _is_utf8(v) for v in raw], dtype=bool)
        report(np.flatnonzero(odd), name, "is not UTF-8 text")
        table = table.set_column(names.index(name), name, pa.array(
            [None if v is None or o else v.decode() for o, v in zip(odd.tolist(), raw,
                                                                     strict=True)], col.type))

    def floats(name: str) -> FloatArray:
        if name not in names:
            return np.full(n, np.nan)
        col = table.column(name)
        if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            col = pc.utf8_trim_whitespace(col)
            try:  # fast path: Arrow's parser; on a bad value, find it row by row
                cast = pc.cast(col, pa.float64())
                values = np.asarray(cast.to_numpy(zero_copy_only=False), dtype=float)
                values = np.where(np.asarray(cast.is_null().to_numpy(zero_copy_only=False)),
                                  np.nan, values)
            except pa.ArrowInvalid:
                values = np.full(n, np.nan)
                for i, s in enumerate(col.to_pylist()):
                    if s is None or s == "":
                        continue
                    try:
                        values[i] = float(s)
                    except ValueError:
                        report(np.array([i]), name, f"{s!r} is not a number")
        elif pa.types.is_integer(col.type) or pa.types.is_floating(col.type):
            values = np.asarray(pc.cast(col, pa.float64()).to_numpy(zero_copy_only=False),
                                dtype=float)
            values = np.where(np.asarray(col.is_null().to_numpy(zero_copy_only=False)),
                              np.nan, values)
        else:
            raise InputError((name,), f"has type {col.type}, expected numbers")
        inf = np.flatnonzero(np.isinf(values))
        if inf.size:
            report(inf, name, "must be finite")
            values[inf] = np.nan
        return values

    def strings(name: str) -> list[str | None]:
        if name not in names:
            return [None] * n
        col = table.column(name)
        if not (pa.types.is_string(col.type) or pa.types.is_large_string(col.type)):
            try:  # a list or binary column that is no text: the file's error, not a traceback
                col = pc.cast(col, pa.string())
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as e:
                raise InputError((name,), f"has type {col.type}, expected text: {e}") from None
        return [None if v is None else str(v).strip() or None for v in col.to_pylist()]

    time_name = "timestamp" if "timestamp" in names else "t" if "t" in names else "time_of_day_s"
    stamps = None
    if time_name == "timestamp":
        stamps = timestamp_ns(table.column("timestamp"), report)
        time = np.where(stamps == NO_TIME, np.nan, 0.0)
    else:
        time = floats(time_name)
    tod = floats("time_of_day_s") if time_name != "time_of_day_s" else time
    missing = np.flatnonzero(np.isnan(time) & ~bad)
    if missing.size:
        report(missing, time_name, "is missing")
    if time_name == "time_of_day_s":
        out_of_day = np.flatnonzero((time < 0) | (time >= DAY_S))
        if out_of_day.size:
            report(out_of_day, time_name, "must be in [0, 86400) s")
    if stamps is not None:  # t and the time of day from it, a t or time of day beside checked
        time, tod, date = _from_timestamps(stamps, ~bad, date, floats("t") if "t" in names
                                           else None, tod, report)

    sensor = strings("sensor")
    no_sensor = np.array([i for i, s in enumerate(sensor) if s is None], dtype=int)
    if no_sensor.size:
        report(no_sensor, "sensor", "is missing")

    cols = {c: floats(c) for c in FLOAT_COLUMNS}
    has_r = np.isfinite(cols["range_m"])
    has_a = np.isfinite(cols["azimuth_deg"])
    has_lat = np.isfinite(cols["lat_deg"])
    has_lon = np.isfinite(cols["lon_deg"])
    for a, b, an, bn in ((has_r, has_a, "range_m", "azimuth_deg"),
                         (has_lat, has_lon, "lat_deg", "lon_deg")):
        half = np.flatnonzero(a & ~b)
        if half.size:
            report(half, bn, f"is missing (the row has `{an}`)")
        half = np.flatnonzero(b & ~a)
        if half.size:
            report(half, an, f"is missing (the row has `{bn}`)")
    both = np.flatnonzero((has_r | has_a) & (has_lat | has_lon))
    if both.size:
        report(both, "lat_deg", "a row is either a radar plot (range_m, azimuth_deg) or a "
               "position plot (lat_deg, lon_deg), not both")
    neither = np.flatnonzero(~(has_r | has_a | has_lat | has_lon))
    if neither.size:
        report(neither, "range_m", "the row has no measurement (range_m + azimuth_deg or "
               "lat_deg + lon_deg)")
    for name, lo, hi in (("range_m", 0.0, 1e7), ("azimuth_deg", -MAX_AZIMUTH_DEG, MAX_AZIMUTH_DEG),
                         ("lat_deg", -90.0, 90.0),
                         ("lon_deg", -MAX_LON_DEG, MAX_LON_DEG), ("altitude_m", -1000.0, 100_000.0),
                         ("flight_level", -20.0, 1000.0)):
        v = cols[name]
        out = np.flatnonzero(np.isfinite(v) & ((v < lo) | (v > hi) | (v == 0.0 if
                                                                        name == "range_m"
                                                                        else False)))
        if out.size:
            report(out, name, f"must be in {'(' if name == 'range_m' else '['}{lo:g}, {hi:g}]")

    ints: dict[str, np.ndarray] = {}
    for name, base, top, what in (("mode_s", 16, 0xFFFFFF, "a 24-bit hex address (4CA2D1)"),
                                  ("mode_3a", 8, 0o7777, "4 octal digits (7000)"),
                                  ("track_number", 10, 2**31 - 1, "an integer >= 0")):
        values = np.full(n, NO_INT, dtype=np.int64)
        if name in names and pa.types.is_floating(table.column(name).type):
            # pandas writes an integer column with missing values as float, NaN where missing
            # (every row of such a Parquet mode_s was refused; a fuzz helper): whole numbers
            # are read as the integers they are
            arr = np.array(table.column(name).to_numpy(zero_copy_only=False), dtype=float)
            odd = np.flatnonzero(~np.isnan(arr) & ((np.abs(arr) > 2.0**53)
                                                   | (arr != np.round(arr))))
            if odd.size:
                report(odd, name, f"must be {what}")
                arr[odd] = np.nan
            whole = pa.array(np.nan_to_num(arr).astype(np.int64), mask=np.isnan(arr))
            table = table.set_column(names.index(name), name, whole)
        if name in names and pa.types.is_integer(table.column(name).type) and base != 8:
            col = table.column(name)
            arr = col.to_numpy(zero_copy_only=False)
            null = np.asarray(col.is_null().to_numpy(zero_copy_only=False))
            values = np.where(null, NO_INT, np.nan_to_num(arr, nan=NO_INT)).astype(np.int64)
            out = np.flatnonzero(~null & ((values < 0) | (values > top)))
            if out.size:
                report(out, name, f"must be {what}")
                values[out] = NO_INT
        else:
            for i, s in enumerate(strings(name)):
                if s is None:
                    continue
                try:
                    v = int(s.removeprefix("0x").removeprefix("0X"), base)
                    if not 0 <= v <= top or (base == 8 and len(s) > 4):
                        raise ValueError
                    values[i] = v
                except ValueError:
                    report(np.array([i]), name, f"{s!r} is not {what}")
        ints[name] = values
    aircraft = np.array(["" if a is None else a for a in strings("aircraft")], dtype=object)
    # `KEY#2` names a key's piece after a gap (solver.io.split): a user's key of that form was
    # merged with another aircraft's piece, or made a traceback (a fuzz helper)
    piece_like = np.flatnonzero([bool(PIECE_NAME.search(a) or APART_NAME.search(a))
                                 for a in aircraft])
    if piece_like.size:
        report(piece_like, "aircraft", "ends in #<number> or ~<number>, the names of a key's "
               "piece after a time gap and of another aircraft found under a key: rename the "
               "key")

    ground = on_ground_column(table, names, report)  # left out by the split, counted

    altitude = cols["altitude_m"]
    fl = cols["flight_level"]
    altitude = np.where(np.isnan(altitude), fl * FL_M, altitude)
    keep = ~bad
    t = time if time_name != "time_of_day_s" else unwrap_time_of_day(
        np.where(keep, time, np.nan), previous_t)
    rows = PlotRows.from_columns(
        n, "row", date if time_name == "timestamp" else None, t=t, time_of_day_s=tod,
        sensor=np.array(["" if s is None else s for s in sensor], dtype=object),
        range_m=cols["range_m"], azimuth_deg=cols["azimuth_deg"], lat_deg=cols["lat_deg"],
        lon_deg=wrap_lon(cols["lon_deg"]), altitude_m=altitude, flight_level=fl, aircraft=aircraft,
        origin=row_of.copy(), on_ground=ground, **ints)
    return rows.take(keep), problems


NO_TIME = np.iinfo(np.int64).min
"""A missing or bad ``timestamp`` (:func:`timestamp_ns`)."""
EPOCH_S_RANGE = (86_400.0, 4_102_444_800.0)
"""``timestamp`` epoch seconds read: 1970-01-02 to 2100-01-01 (a number outside is no
time: a time of day or a millisecond count put in the column)."""
_NUMBER = r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$"
_ZONED = r"(Z|z|[+-]\d\d(:?\d\d)?)$"
ISO_CHUNK_ROWS = 1 << 14
"""ISO 8601 text is cast in chunks of this many rows, one by one only in a chunk holding a bad
one (about 1.7 us a row): a 200,000-row CSV with one bad time read in 0.51-0.57 s, 0.71 s one by
one over all rows, 0.29 s without it (the rest: numbering the CSV's lines for the report)."""
TIME_AGREEMENT_S = 1e-3
"""A ``t`` or ``time_of_day_s`` beside a ``timestamp`` must agree with it this closely (s)."""


def timestamp_ns(col: pa.ChunkedArray | pa.Array,
                 report: Callable[[np.ndarray, str, str], None]) -> np.ndarray:
    """A ``timestamp`` column as epoch nanoseconds (int64; :data:`NO_TIME` where missing or
    bad, the bad ones reported): an Arrow timestamp (naive: UTC), epoch seconds (numbers, or
    text of them), or ISO 8601 text (``2024-03-09T10:00:00.5Z``, ``+01:00``, RFC 3339's lower
    case ``t`` and ``z`` too; without a zone: UTC, as surveillance data are timed)."""
    n = len(col)
    out = np.full(n, NO_TIME, dtype=np.int64)
    if pa.types.is_null(col.type):
        return out
    if pa.types.is_timestamp(col.type):
        try:
            vals = pc.cast(col, pa.timestamp("ns", tz=col.type.tz)).cast(pa.int64())
        except pa.ArrowInvalid as e:
            raise InputError(("timestamp",), f"holds a time beyond 1677-2262: {e}") from None
        null = np.asarray(vals.is_null().to_numpy(zero_copy_only=False), dtype=bool)
        ints = np.asarray(pc.fill_null(vals, 0).to_numpy(zero_copy_only=False), dtype=np.int64)
        out[~null] = ints[~null]
        return out
    if pa.types.is_integer(col.type) or pa.types.is_floating(col.type):
        secs = np.asarray(pc.cast(col, pa.float64()).to_numpy(zero_copy_only=False), float)
        secs = np.where(np.asarray(col.is_null().to_numpy(zero_copy_only=False)), np.nan, secs)
        return _epoch_seconds(secs, out, report)
    if not (pa.types.is_string(col.type) or pa.types.is_large_string(col.type)):
        raise InputError(("timestamp",), f"has type {col.type}, expected a time (ISO 8601 "
                         "text, epoch seconds, or a Parquet timestamp)")
    text = pc.utf8_trim_whitespace(col)
    if isinstance(text, pa.ChunkedArray):
        text = text.combine_chunks()
    present = np.asarray(pc.fill_null(pc.not_equal(text, ""), False)
                         .to_numpy(zero_copy_only=False), dtype=bool)
    numeric = present & np.asarray(pc.fill_null(pc.match_substring_regex(text, _NUMBER), False)
                                   .to_numpy(zero_copy_only=False), dtype=bool)
    if numeric.any():
        secs = np.full(n, np.nan)
        idx = np.flatnonzero(numeric)
        secs[idx] = np.asarray(pc.cast(text.take(pa.array(idx)), pa.float64())
                               .to_numpy(zero_copy_only=False), float)
        _epoch_seconds(secs, out, report)
    zoned = np.asarray(pc.fill_null(pc.match_substring_regex(text, _ZONED), False)
                       .to_numpy(zero_copy_only=False), dtype=bool)
    for mask, kind in ((present & ~numeric & zoned, pa.timestamp("ns", tz="UTC")),
                       (present & ~numeric & ~zoned, pa.timestamp("ns"))):
        every = np.flatnonzero(mask)
        for start in range(0, every.size, ISO_CHUNK_ROWS):
            idx = every[start:start + ISO_CHUNK_ROWS]
            part = text.take(pa.array(idx))
            try:  # upper case: RFC 3339's t and z (Arrow reads T and Z only)
                out[idx] = np.asarray(pc.cast(pc.utf8_upper(part), kind).cast(pa.int64())
                                      .to_numpy(zero_copy_only=False), dtype=np.int64)
                continue
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
                pass
            for i, v in zip(idx.tolist(), part.to_pylist(), strict=True):  # the bad ones
                try:
                    out[i] = pa.scalar(v.upper()).cast(kind).cast(pa.int64()).as_py()
                except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
                    report(np.array([i]), "timestamp", f"{v!r} is not a time (ISO 8601, e.g. "
                           "2024-03-09T10:00:00.5Z, or epoch seconds)")
    return out


def _epoch_seconds(secs: FloatArray, out: np.ndarray,
                   report: Callable[[np.ndarray, str, str], None]) -> np.ndarray:
    """Epoch seconds into ``out`` (ns) where finite and in :data:`EPOCH_S_RANGE`; others that
    are not NaN reported."""
    lo, hi = EPOCH_S_RANGE
    ok = np.isfinite(secs) & (secs >= lo) & (secs < hi)
    odd = np.flatnonzero(~np.isnan(secs) & ~ok)
    if odd.size:
        report(odd, "timestamp", "epoch seconds must be in [1970-01-02, 2100-01-01) (86400 to "
               "4102444800)")
    out[ok] = np.round(secs[ok] * 1e9).astype(np.int64)
    return out


def _from_timestamps(stamps: np.ndarray, keep: np.ndarray, date: str | None,
                     t_col: FloatArray | None, tod_col: FloatArray,
                     report: Callable[[np.ndarray, str, str], None]
                     ) -> tuple[FloatArray, FloatArray, str | None]:
    """``t`` (s from the UTC midnight of ``date``, else of the first row kept with a time),
    the time of day and the date, from epoch nanoseconds; a ``t`` or ``time_of_day_s`` column
    beside (NaN where empty) that disagrees by more than :data:`TIME_AGREEMENT_S` is a bad
    value of its row."""
    valid = (stamps != NO_TIME) & keep
    t = np.full(stamps.size, np.nan)
    tod = np.full(stamps.size, np.nan)
    if not valid.any():
        return t, tod, date
    ns = stamps[valid].astype("datetime64[ns]")
    if date is None:
        date = str(ns[0].astype("datetime64[D]"))
    midnight = np.datetime64(date, "ns")
    t[valid] = (ns - midnight).astype(np.int64) / 1e9
    tod[valid] = (ns - ns.astype("datetime64[D]").astype("datetime64[ns]")).astype(np.int64) / 1e9
    for name, given, d in (("t", t_col, None if t_col is None else t_col - t),
                           ("time_of_day_s", tod_col, None)):
        if given is None:
            continue
        if d is None:
            d = np.abs(given - tod)
            d = np.minimum(d, DAY_S - d)
        odd = np.flatnonzero(valid & np.isfinite(given) & (np.abs(d) > TIME_AGREEMENT_S))
        if odd.size:
            report(odd, name, "disagrees with `timestamp` (which makes `t` the seconds from "
                   f"the UTC midnight of {date}, and the time of day)")
    return t, tod, date


GROUND_WORDS = {"true": True, "1": True, "false": False, "0": False}
"""The values of a text ``on_ground`` cell (case-insensitive; empty: not said)."""


def on_ground_column(table: pa.Table, names: list[str],
                     report: Callable[[np.ndarray, str, str], None]) -> np.ndarray:
    """Each row's ``on_ground`` (int8: 1 true, 0 false, -1 empty or without the column); a
    value that is no boolean is reported as a bad value of its row."""
    n = table.num_rows
    out = np.full(n, -1, dtype=np.int8)
    if "on_ground" not in names:
        return out
    col = table.column("on_ground")
    if pa.types.is_null(col.type):  # every cell empty (pandas' column of None)
        return out
    if (pa.types.is_boolean(col.type) or pa.types.is_integer(col.type)
            or pa.types.is_floating(col.type)):  # floats: pandas' column with NaN
        values = np.asarray(pc.cast(col, pa.float64()).to_numpy(zero_copy_only=False),
                            dtype=float)
        values = np.where(np.asarray(col.is_null().to_numpy(zero_copy_only=False)), np.nan,
                          values)
        odd = np.flatnonzero(np.isfinite(values) & (values != 0) & (values != 1)
                             | np.isinf(values))
        if odd.size:
            report(odd, "on_ground", "must be true or false (1 or 0)")
        out[:] = np.where((values == 0) | (values == 1), values, -1)
        return out
    if not (pa.types.is_string(col.type) or pa.types.is_large_string(col.type)):
        raise InputError(("on_ground",), f"has type {col.type}, expected true/false")
    for i, v in enumerate(col.to_pylist()):
        word = None if v is None else v.strip().lower()
        if not word:
            continue
        if word not in GROUND_WORDS:
            report(np.array([i]), "on_ground", f"{v!r} is not true or false (1 or 0)")
            continue
        out[i] = GROUND_WORDS[word]
    return out


# ---------------------------------------------------------------------------- writing


def write_table(rows: PlotRows, path: str | Path) -> None:
    """Write the documented table (``.parquet`` / ``.pq``: Parquet, else CSV)."""
    path = Path(path)
    table = rows.to_arrow()
    if path.suffix.lower() in (".parquet", ".pq"):
        pq.write_table(table, path)
    else:
        if "timestamp" in table.column_names:  # ISO 8601 with T and Z
            table = table.set_column(table.column_names.index("timestamp"), "timestamp",
                                     iso_utc(table.column("timestamp")))
        pacsv.write_csv(table, path, pacsv.WriteOptions(quoting_style="needed"))
