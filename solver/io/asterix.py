"""ASTERIX recordings (raw files, IOSS/FINAL recordings, pcap / pcapng captures) -> plot rows.

Records are parsed by libasterix (pure Python, MIT, EUROCONTROL specifications generated from
the asterix-specs definitions; it also encodes, so the tests write their recordings with it).
Nothing of the ASTERIX record structure is decoded by hand here: this module walks the
data blocks (to know byte offsets and to resynchronise after damage) and maps the decoded
items to plot rows (:class:`solver.io.tables.PlotRows`).

Containers (:func:`read_recording` tells them apart by the first bytes):

- raw: data blocks ``CAT (1 byte) | LEN (2 bytes, big-endian, including these 3) | records``
  one after the other, as recorders write them;
- IOSS, also called the FINAL format (``*.ff``; :mod:`solver.io.framing`): each frame of a
  recorder (length, board, day, time of reception, 4 padding bytes) holds data blocks;
- captures (classic pcap and pcapng; :mod:`solver.io.pcap`, decoded by dpkt): every UDP
  payload over IPv4/IPv6 is a datagram of data blocks; IP fragments are reported, not
  reassembled.

Items read (default editions CAT048 1.32, CAT021 2.7, CAT034 1.29; ``editions=`` picks others,
below):

- CAT048 target reports: I010 SAC/SIC -> sensor (sensor file), I140 time of day, I040 measured
  slant range (1/256 NM -> m; beyond 256 NM, where I020 ERR is set, the Reserved Expansion
  field's ERR) and azimuth (360/2^16 deg), I090 flight level (1/4 FL) ->
  ``flight_level`` and the pressure altitude ``altitude_m = FL * 30.48`` (used only when its
  V and G bits say validated and not garbled), I220 Mode S address, I070 Mode 3/A (validated,
  not garbled), I161 track number. Reports flagged simulated or test (I020 SIM, TST) or from a
  fixed transponder (RAB) are not aircraft: counted as ``not_aircraft`` and left out. Reports
  whose I230 flight status (STAT 1 or 3, the aircraft's Mode S downlink) says on the ground get
  ``on_ground`` (the split ends the aircraft's track there and leaves them out, counted).
- CAT021 ADS-B: I010 SAC/SIC (ground station) -> sensor, time of applicability for position
  I071 (else time of message reception I073; 0.2x: the time of day I030), position I131 (high
  resolution) or I130 (whichever is a LAT/LON group: 0.26's I131 is the signal amplitude; the
  LSB is libasterix's for the edition, 180/2^30 deg for 2.x's I131, 180/2^25 for 0.24-0.26's
  I130, 180/2^23 for 0.23's), geometric height I140 (ft -> m) for ``altitude_m``, else the
  flight level I145 as the pressure altitude (I145 always gives ``flight_level``),
  target address I080, Mode 3/A I070 (0.26's V/G flags checked), track number I161 (none in
  0.2x). I040 SIM/TST/RAB flagged reports are left out (``not_aircraft``); I040 GBS (ground
  bit set) gives ``on_ground`` (2.x: in I040's first extension; 0.2x: a fixed two octets).
- CAT034 service messages: per sensor the count of messages, north markers and sector
  crossings and the antenna rotation period I041 (:class:`ServiceStats`).

Times: the time of day (1/128 s) becomes ``t``, seconds since the UTC midnight before the
first record, monotonic across midnight (:func:`solver.io.tables.unwrap_time_of_day`, in
recording order); ``time_of_day_s`` keeps the recorded value. A capture's packet times give
the date of that midnight (``rows.date``; :class:`solver.io.dates.CaptureClock`: decided by
the first unit with packet-timed rows, disagreements reported); a raw or IOSS recording has
none.

Editions: ASTERIX data carry none, and a category's editions differ: CAT021 0.23-0.26 (older
ADS-B ground stations) have another UAP than 2.x. ``editions=`` maps a category to a libasterix
edition class (:data:`EDITIONS` lists libasterix's: CAT021 0.23-0.26 and 2.1-2.7, CAT034
1.27-1.29, CAT048 1.27-1.32; :func:`parse_edition` reads ``"21=0.26"``, :func:`editions_named`
gives the mapping for names, the command line's ``--edition 21=0.26`` and a job's
``options.editions``); the categories it does not name keep their default. Read as another
edition, records parse as garbage or not at all: CAT021 0.26 read as 2.7 gave a row per
report, its time up to 10 h and its position up to 25,000 km off, beside a ``bad_record``
per block. So where at least :data:`OTHER_EDITION_BLOCKS` data blocks of a category, and half
of its blocks in a unit, stop parsing before their end, one ``other_edition`` problem says so
(naming the edition read and the choices) and those blocks' rows are left out; a damaged block
here and there keeps the rows before its damage. A recording whose records happen to parse
to their blocks' ends as the wrong edition is not caught. CAT048 keeps its UAP from 1.27 to
1.32, and 1.27 data read as 1.32 (the default) give the same plots; libasterix's 1.27-1.31
take I090's FL unsigned (1.32 two's complement), so through them a negative FL would read
4,096 FL too high: a reading of 2,048 FL or more through an unsigned definition is a
``bad_value``, no altitude. 1.32 records with I020's later extensions (1.31 on) do not parse
as 1.27.

Damage: every problem is recorded (:class:`solver.io.problems.Problems`) with its byte offset
in the file and the rest is still read: a truncated block (its declared length runs past the
end of the file or past the start of the next valid block: the reader resynchronises on the
next block whose header, records and successor all check out), an unparsable record (the rest
of its block is skipped), unrecognised bytes between blocks, a category that is not decoded
(CAT062 ...), an unknown SAC/SIC, a record without position or time. The work spent on
damage is limited (:data:`WASTE_FACTOR`): past it, the rest of the unit is read by block headers
alone (``damaged_stretch``), so good data after a long damaged stretch are still read, in time
linear in the bytes.

Reading: :func:`read_recording` (the whole recording), :func:`iter_recording` (in order, unit
by unit, for :func:`solver.io.split.split_stream`); both decode units of ``chunk_bytes`` cut at
block or packet boundaries, in parallel on an ``executor`` when given (about 16,000 plots per
CPU-second per core, 0.06 ms a plot, with the cyclic garbage collector paused: 0.095 ms with
it; the benchmark recording's first 1.5 MB on this machine).
:func:`encode_rows` writes plot rows back as a raw
recording (tests, benchmark recordings).
"""

from __future__ import annotations

import gc
import mmap
import os
import threading
from collections import deque
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import asterix.generated as ast
import numpy as np
from asterix.base import Bits, ParsingMode, Unsigned

from ..inputs import FloatArray
from ..sensors import PositionSensor, RadarSensor
from .dates import CaptureClock
from .framing import KNOWN_CATEGORIES, frame_header_bytes, is_framed, iter_frames
from .pcap import is_capture, iter_udp_packets
from .problems import Problems
from .sensors_file import SensorSet
from .tables import DAY_S, FL_M, FT_M, NO_INT, PlotRows, unwrap_time_of_day

NM_M = 1852.0
DEFAULT_EDITIONS: dict[int, Any] = {48: ast.Cat_048_1_32, 21: ast.Cat_021_2_7,
                                    34: ast.Cat_034_1_29}


def _edition_name(spec: Any) -> str:
    """A libasterix edition class's edition, e.g. ``"0.26"``."""
    major, minor = spec.cv_edition
    return f"{major}.{minor}"


EDITIONS: dict[int, dict[str, Any]] = {
    cat: {_edition_name(spec): spec for spec in sorted(ast.manifest["CATS"][cat],
                                                        key=lambda spec: spec.cv_edition)}
    for cat in sorted(DEFAULT_EDITIONS)}
"""The editions libasterix has of each decoded category, by name (``EDITIONS[21]["0.26"]``:
``ast.Cat_021_0_26``), oldest first: what ``editions=`` may choose."""


def edition_choices() -> str:
    """The editions that can be chosen, for messages: ``CAT021 0.23, ..., 2.7 (default
    2.7); ...``."""
    return "; ".join(f"CAT{cat:03d} {', '.join(names)} (default "
                     f"{_edition_name(DEFAULT_EDITIONS[cat])})" for cat, names in EDITIONS.items())


def parse_edition(text: str) -> tuple[int, str]:
    """``"21=0.26"`` (also ``021=0.26``, ``CAT021=0.26``) -> ``(21, "0.26")``, checked against
    :data:`EDITIONS`; ``ValueError`` listing the choices."""
    cat_text, sep, name = text.partition("=")
    cat_text = cat_text.strip().upper().removeprefix("CAT")
    cat = int(cat_text) if sep and cat_text.isdigit() else None
    name = name.strip()
    if cat not in EDITIONS or name not in EDITIONS[cat]:
        what = (f"{text!r}: give CATEGORY=EDITION (e.g. 21=0.26)" if cat is None else
                f"{text!r}: CAT{cat:03d} is not decoded" if cat not in EDITIONS else
                f"{text!r}: libasterix has no CAT{cat:03d} edition {name!r}")
        raise ValueError(f"{what}; the choices: {edition_choices()}")
    return cat, name


def _with_defaults(editions: Mapping[int, Any] | None) -> dict[int, Any]:
    """``editions=`` over :data:`DEFAULT_EDITIONS`: the categories not named keep their
    default (``editions={21: ast.Cat_021_0_26}`` once left CAT048 and CAT034 undecoded, every
    block an ``unknown_category``)."""
    return {**DEFAULT_EDITIONS, **(editions or {})}


def editions_named(names: Mapping[int, str]) -> dict[int, Any]:
    """The decoder's ``editions=`` for the editions named per category (e.g. ``{21: "0.26"}``),
    the other categories at :data:`DEFAULT_EDITIONS`; ``ValueError`` listing the choices."""
    out = dict(DEFAULT_EDITIONS)
    for cat, name in names.items():
        out[cat] = EDITIONS[parse_edition(f"{cat}={name}")[0]][name]
    return out


REF_048 = ast.Ref_048_1_13
"""CAT048's Reserved Expansion field (read for the extended range, ERR)."""


@dataclass
class ServiceStats:
    """What a sensor's CAT034 service messages say: counts, and the antenna rotation period
    (I034/041, s) last reported (None when never)."""

    messages: int = 0
    north_markers: int = 0
    sector_crossings: int = 0
    rotation_period_s: float | None = None


@dataclass
class Recording:
    """A decoded recording: the plot rows (``origin``: byte offset of each row's record in the
    file), the problems, CAT034 statistics per sensor id, and counts (data blocks per
    category, records, bytes, captured packets)."""

    rows: PlotRows
    problems: Problems
    service: dict[str, ServiceStats] = field(default_factory=dict)
    blocks: dict[int, int] = field(default_factory=dict)
    records: int = 0
    bytes: int = 0
    packets: int = 0


RESYNC_CHECK_BYTES = 1
"""Resynchronising after damage, a candidate block's records must parse up to this many bytes
(1: its first record; with a plausible header and successor)."""
WASTE_FACTOR = 2
"""Work the reader may spend on damage before it reads on by block headers alone: parsing that
finds no block (resynchronisation checks, blocks whose records fail) of at most this many times
the unit's bytes (64 KiB at least) and a record per :data:`WASTE_RECORD_BYTES` of them. Beyond
it the rest of the unit is still read, linearly: a candidate block needs a header and a
successor that check out, and one whose records fail is skipped to its declared end (which may
hide good data up to that length). Before, reaching a limit ended the unit's reading: 200 KB of
random bytes before 300 KB of sound data lost all 14,146 of its rows."""
WASTE_RECORD_BYTES = 64
"""See :data:`WASTE_FACTOR` (libasterix's cost goes by records, about 0.1 ms each)."""
MIN_RECORD_BYTES = 4
"""A block whose records average fewer bytes than this (beyond :data:`DENSE_SLACK` records) is
no data: sound recordings hold a record per 7 bytes (a CAT034 north marker) to 30 (CAT048
with Mode S). Bytes that parse as records of 2-3 bytes over and over (0x30: every offset a
12,336-byte CAT048 block) were read as sound blocks: 1 MiB of them took 42 s."""
DENSE_SLACK = 8
NO_DATA_SKIP = 256
"""Past the work limit, bytes skipped (at least) after records that are no data before looking
for the next block header (1 MiB of 0x30: 2.5 s; looking on from the record, 29 s): good data
right after such damage lose at most this many bytes. A block whose records do not parse is
skipped to its declared end (from the failed record, 15 ff ff ... took 650 s a MiB)."""
UNDECODED_CHAIN = 3
"""A block of a category not decoded here (CAT062, ...) is trusted with its declared length
only where the block headers from its end on chain for this many blocks (each plausible and
within the data) or reach the end: its records cannot be checked. Trusting one plausible
successor, a flipped length bit in a CAT062 block (landing on bytes that look like a header,
about one place in ten) lost up to 3,230 of 9,417 rows (a tester's sweep). Nor is it trusted
where blocks of a decoded category chain from within it to exactly its declared end: the flip
landed on a later block's start (``_Decoder._swallows_blocks``)."""
MAX_CHECKED_RECORD_BYTES = 1024
"""Bytes given to that check beyond its budget (a record longer than this fails it)."""
CHUNK_BYTES = 1 << 20
"""Size of the units a recording is decoded in (in parallel with ``executor=``)."""
OTHER_EDITION_BLOCKS = 4
"""Data blocks of a category that stop parsing before their end (and half its blocks, in a
unit) taken for data of another edition (:meth:`_Decoder._other_edition`)."""


def read_recording(source: str | Path | bytes, sensors: SensorSet, *,
                   editions: Mapping[int, Any] | None = None, executor: Any = None,
                   chunk_bytes: int = CHUNK_BYTES) -> Recording:
    """Decode a raw ASTERIX file or a capture of it (see the module docstring).

    The recording is cut into units of about ``chunk_bytes`` at data block (or packet)
    boundaries; with ``executor`` (a Dask ``Client`` or any ``concurrent.futures``-style
    executor) the units are decoded in parallel, else one after the other: the result is the
    same (rows in recording order, times unwrapped over the whole recording)."""
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    parts = list(iter_recording(data, sensors, editions=editions, executor=executor,
                                chunk_bytes=chunk_bytes))
    return _merge(parts, Problems(), len(data), sum(p.packets for p in parts))


def iter_recording(source: str | Path | bytes, sensors: SensorSet, *,
                   editions: Mapping[int, Any] | None = None, executor: Any = None,
                   chunk_bytes: int = CHUNK_BYTES, ahead: int = 8) -> Iterator[Recording]:
    """:func:`read_recording` unit by unit, in recording order, for a reader that wants to
    start before the end (e.g. :func:`solver.io.split.split_stream` over the parts' rows):
    each part holds its rows (times unwrapped continuously across the parts), its problems
    (the container's too) and counts. With ``executor`` at most ``ahead`` units are
    decoded at once. A file is memory-mapped and read unit by unit (what is held does not
    grow with its length)."""
    if isinstance(source, bytes):
        yield from _iter_data(source, sensors, editions, executor, chunk_bytes, ahead)
        return
    with open(source, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            yield from _iter_data(b"", sensors, editions, executor, chunk_bytes, ahead)
            return
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
            yield from _iter_data(mapped, sensors, editions, executor, chunk_bytes, ahead)


def _iter_data(data: bytes | mmap.mmap, sensors: SensorSet, editions: Mapping[int, Any] | None,
               executor: Any, chunk_bytes: int, ahead: int) -> Iterator[Recording]:
    """:func:`iter_recording` of the recording's bytes, or of the file memory-mapped (its
    pages released behind the reading: the memory does not grow with the file)."""
    eds = _with_defaults(editions)
    previous = np.nan
    clock = CaptureClock()  # a capture's date, from its packet times

    def finish(part: Recording, walk: Problems, unit: list[tuple[int, bytes]],
               times: list[float], packed: bool) -> Recording:
        nonlocal previous
        walk.extend(part.problems)
        t = unwrap_time_of_day(part.rows.time_of_day_s, previous)
        if np.isfinite(t).any():
            previous = float(t[np.isfinite(t)][-1])
        rows = replace(part.rows, t=t)
        clock.add(t, _received(rows, unit, times), rows.where, walk)
        return Recording(replace(rows, date=clock.date), walk, part.service, part.blocks,
                         part.records, part.bytes, len(unit) if packed else 0)

    units = _units(data, chunk_bytes)
    packed = _pieces(data, Problems()) is not None  # a capture's packets or frames are counted
    if executor is None:
        for unit, walk, times in units:
            yield finish(decode_datagrams(unit, sensors, editions=eds), walk, unit, times,
                         packed)
        return
    pending: deque[tuple[Any, Problems, list[tuple[int, bytes]], list[float]]] = deque()
    for unit, walk, times in units:
        pending.append((executor.submit(decode_datagrams, unit, sensors, editions=eds), walk,
                        unit, times))
        if len(pending) >= ahead:
            fut, w, u, k = pending.popleft()
            yield finish(fut.result(), w, u, k, packed)
    while pending:
        fut, w, u, k = pending.popleft()
        yield finish(fut.result(), w, u, k, packed)


def _pieces(data: bytes | mmap.mmap, problems: Problems
            ) -> Iterator[tuple[int, bytes, float]] | None:
    """A capture's UDP payloads or an IOSS recording's frames' data blocks, as ``(file offset,
    data blocks, capture time)`` (epoch s, a capture's packet time; NaN for a frame: its day
    byte is no date, :mod:`solver.io.dates`); what cannot be read of the container goes to
    ``problems``; None for a raw recording."""
    if is_capture(data):
        return iter_udp_packets(data, problems)
    header = frame_header_bytes(data)
    return None if header is None else ((a, b, np.nan) for a, b in
                                        iter_frames(data, problems, header))


def _units(data: bytes | mmap.mmap, chunk_bytes: int
           ) -> Iterator[tuple[list[tuple[int, bytes]], Problems, list[float]]]:
    """The decoding units of a recording (copies of its bytes) with the container's problems
    met on the way and each piece's capture time (:func:`_pieces`; none for a raw file); a
    memory-mapped file's pages are released behind the units."""
    release = _Release(data)
    walk = Problems()  # filled by a container's walk, drained into each unit
    pieces = _pieces(data, walk)
    if pieces is None:
        for a, b in _block_cuts(data, chunk_bytes):
            unit = data[a:b]
            release.upto(b)
            yield [(a, unit)], Problems(), []
        return
    units: list[tuple[int, bytes]] = []
    times: list[float] = []
    size = 0
    for offset, payload, when in pieces:
        units.append((offset, payload))
        times.append(when)
        size += len(payload)
        if size >= chunk_bytes:
            release.upto(offset)
            yield units, walk.drain(), times
            units, times, size = [], [], 0
    if units or walk:
        yield units, walk.drain(), times


def _received(rows: PlotRows, unit: list[tuple[int, bytes]], times: list[float]) -> FloatArray:
    """Each row's capture time: its record's packet's (the last piece starting at or before
    the record's byte offset); NaN without one."""
    if not times or not len(rows):
        return np.full(len(rows), np.nan)
    starts = np.array([a for a, _ in unit], dtype=np.int64)
    k = np.searchsorted(starts, rows.origin, side="right") - 1
    return np.where(k >= 0, np.asarray(times, dtype=float)[np.maximum(k, 0)], np.nan)


RELEASE_STEP = 1 << 20
"""A memory-mapped recording's pages are given back in steps of at least this many bytes."""


class _Release:
    """Gives a memory-mapped file's pages before a position back (``madvise DONTNEED``: they
    stay in the page cache, out of the process's resident memory); nothing for bytes."""

    def __init__(self, data: bytes | mmap.mmap):
        self.mapped = data if isinstance(data, mmap.mmap) and hasattr(data, "madvise") else None
        self.done = 0

    def upto(self, pos: int) -> None:
        if self.mapped is None:
            return
        end = pos - pos % mmap.PAGESIZE
        if end - self.done >= RELEASE_STEP:
            self.mapped.madvise(mmap.MADV_DONTNEED, self.done, end - self.done)
            self.done = end


def decode_blocks(data: bytes, sensors: SensorSet, *,
                  editions: Mapping[int, Any] | None = None) -> Recording:
    """Decode data blocks one after the other (a raw file's bytes or one datagram)."""
    return decode_datagrams([(0, data)], sensors, editions=editions)


def decode_datagrams(datagrams: list[tuple[int, bytes]], sensors: SensorSet, *,
                     editions: Mapping[int, Any] | None = None) -> Recording:
    """Decode ``(file offset, bytes)`` pieces, each a sequence of whole data blocks (a UDP
    payload, or a stretch of a raw file); byte offsets are the file's. The cyclic garbage
    collector is paused meanwhile (:func:`cyclic_gc_paused`)."""
    decoder = _Decoder(sensors, _with_defaults(editions))
    with cyclic_gc_paused():
        for offset, payload in datagrams:
            decoder.feed(payload, offset)
    return decoder.finish(sum(len(p) for _, p in datagrams))


_GC_LOCK = threading.Lock()
_GC_PAUSES = [0, False]  # pauses running, and whether the collector was on before the first


@contextmanager
def cyclic_gc_paused() -> Iterator[None]:
    """Pause Python's cyclic garbage collector (reference counting goes on) while a unit is
    decoded: libasterix builds some ten objects per byte, and each collection walked the
    records held so far: sound data 95 us a plot with it, 57-60 without (the benchmark
    recording's first 1.5 MB, 70,775 plots); valid 64-KB blocks of 7-byte records 101 s a MiB
    against 24 (a tester's). Counted across threads (two jobs decoding at once): the collector
    is on again when the last pause ends, if it was on before the first; it then collects what
    the unit left (memory bounded by a unit)."""
    with _GC_LOCK:
        if _GC_PAUSES[0] == 0:
            _GC_PAUSES[1] = gc.isenabled()
            gc.disable()
        _GC_PAUSES[0] += 1
    try:
        yield
    finally:
        with _GC_LOCK:
            _GC_PAUSES[0] -= 1
            if _GC_PAUSES[0] == 0 and _GC_PAUSES[1]:
                gc.enable()


DISORDER_SAMPLE_BYTES = 1 << 14
""":func:`time_disorder_s` reads the first record of a data block every this many bytes
(a 25-MB recording: 1,600 records, about 0.2 s)."""


def time_disorder_s(source: str | Path | bytes, sensors: SensorSet, *,
                    editions: Mapping[int, Any] | None = None,
                    every_bytes: int = DISORDER_SAMPLE_BYTES) -> float:
    """How far (s) a report of a recording comes after a later-timed one, at most (0: in time
    order), from the time of day of the first report of a data block every ``every_bytes``
    (unwrapped in recording order): whether it can be split as it is read in units
    (:func:`solver.io.split.split_stream`) or must be read whole and sorted first. Two
    recordings concatenated (``cat r1.ast r2.ast``) split every aircraft into overlapping
    tracks when streamed (found by a fuzz helper); a backward jump between two samples shows
    them. A raw file is walked by its block headers up to its first damage, a capture by its
    datagrams (the first block of each)."""
    if isinstance(source, bytes):
        return _time_disorder_s(source, sensors, editions, every_bytes)
    with open(source, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            return 0.0
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
            return _time_disorder_s(mapped, sensors, editions, every_bytes)


def _time_disorder_s(data: bytes | mmap.mmap, sensors: SensorSet,
                     editions: Mapping[int, Any] | None, every_bytes: int) -> float:
    decoder = _Decoder(sensors, _with_defaults(editions))
    due = 0
    for offset, buf, a, b in _sampled_blocks(data):
        if offset < due or buf[a] not in decoder.editions:
            continue
        block = bytes(buf[a:b])
        records, _ = decoder._parse(block[0], block, 3, len(block), RESYNC_CHECK_BYTES)
        before = len(decoder.rows)
        decoder._handle(block[0], records[:1], 0, offset, len(block))
        if len(decoder.rows) > before:
            due = offset + every_bytes
    t = unwrap_time_of_day(np.array([row[0] for row in decoder.rows], dtype=float))
    return float(np.max(np.maximum.accumulate(t) - t)) if t.size else 0.0


def _sampled_blocks(data: bytes | mmap.mmap) -> Iterator[tuple[int, Any, int, int]]:
    """The data blocks :func:`time_disorder_s` may sample, as ``(file offset, buffer, start,
    stop)``: a raw file's blocks up to its first damage, a capture's first block of each
    datagram (an IOSS recording's of each frame)."""
    pieces = _pieces(data, Problems())
    if pieces is not None:
        for offset, payload, _ in pieces:
            if _fits(payload, 0):
                yield offset, payload, 0, (payload[1] << 8) | payload[2]
        return
    pos, end = 0, len(data)
    while pos < end and _fits(data, pos):
        nxt = pos + ((data[pos + 1] << 8) | data[pos + 2])
        yield pos, data, pos, nxt
        pos = nxt


def block_chunks(data: bytes, chunk_bytes: int = CHUNK_BYTES) -> list[tuple[int, int]]:
    """``(start, stop)`` stretches of a raw recording of about ``chunk_bytes``, cut at data
    block boundaries found by walking the headers. A cut is placed only where the walk is
    sure of the boundary (every header so far plausible and within the data); from the first
    damage on, the rest is one stretch (the decoder resynchronises inside it)."""
    return list(_block_cuts(data, chunk_bytes))


def _block_cuts(data: bytes | mmap.mmap, chunk_bytes: int) -> Iterator[tuple[int, int]]:
    """:func:`block_chunks` one stretch after the other (the walk goes no further than the
    stretch it gives)."""
    start, pos, end = 0, 0, len(data)
    while pos < end and _plausible(data, pos):
        pos += (data[pos + 1] << 8) | data[pos + 2]
        if pos >= end:
            break
        if pos - start >= chunk_bytes and _plausible(data, pos):
            yield start, pos
            start = pos
    yield start, end


def _plausible(data: bytes, p: int) -> bool:
    """A block header could start at ``p``: a category libasterix knows and a length of at
    least 3 (the block may still run past the end: that is reported when it is read)."""
    return (len(data) - p >= 3 and data[p] in KNOWN_CATEGORIES
            and ((data[p + 1] << 8) | data[p + 2]) >= 3)


def looks_like_recording(head: bytes) -> bool:
    """Whether a file starting with ``head`` (its first 64 KiB and 3 bytes, or all of it) is a
    capture or starts with a data block: a category libasterix knows, a length within the
    file, followed by another such header or the end. Text, JSON, gzip or a script do not (a
    Python file's ``\"\"\"`` reads as a CAT034 header, whose successor does not)."""
    if is_capture(head) or is_framed(head) or not head:
        return True
    if not _fits(head, 0):
        return False
    nxt = (head[1] << 8) | head[2]
    return nxt == len(head) or _plausible(head, nxt)


def _fits(data: bytes, p: int) -> bool:
    """A whole block could start at ``p``: plausible and within the data."""
    return _plausible(data, p) and p + ((data[p + 1] << 8) | data[p + 2]) <= len(data)


def _chain_holds(data: bytes | mmap.mmap, q: int) -> bool:
    """Whether :data:`UNDECODED_CHAIN` whole blocks follow one another from ``q`` by their
    headers alone (or the data ends on the way)."""
    for _ in range(UNDECODED_CHAIN):
        if q == len(data):
            return True
        if not _fits(data, q):
            return False
        q += (data[q + 1] << 8) | data[q + 2]
    return True


def _merge(parts: list[Recording], problems: Problems, size: int, packets: int) -> Recording:
    """One recording from its decoded units in order: rows concatenated and their times
    unwrapped over the whole, problems and counts added up."""
    rows = PlotRows.concat([p.rows for p in parts]) if parts else PlotRows.from_columns(
        0, "byte")
    rows = replace(rows, t=unwrap_time_of_day(rows.time_of_day_s))
    service: dict[str, ServiceStats] = {}
    blocks: dict[int, int] = {}
    for p in parts:
        problems.extend(p.problems)
        for k, v in p.blocks.items():
            blocks[k] = blocks.get(k, 0) + v
        for sid, st in p.service.items():
            acc = service.setdefault(sid, ServiceStats())
            acc.messages += st.messages
            acc.north_markers += st.north_markers
            acc.sector_crossings += st.sector_crossings
            if st.rotation_period_s is not None:
                acc.rotation_period_s = st.rotation_period_s
    return Recording(rows, problems, service, blocks, sum(p.records for p in parts), size,
                     packets)


# ---------------------------------------------------------------------------------- blocks


class _Decoder:
    """Data blocks -> row columns; one instance per recording."""

    def __init__(self, sensors: SensorSet, editions: Mapping[int, Any]):
        self.sensors = sensors
        self.editions = dict(editions)
        if not set(self.editions) <= {21, 34, 48}:
            raise ValueError(f"editions: categories {sorted(self.editions)}; only 21, 34 and "
                             "48 are decoded")
        self.problems = Problems()
        self.rows: list[tuple] = []  # one tuple per row, in the order of _COLUMNS
        self._memo: dict[tuple, Any] = {}
        # the last search: (data, headers only, from, found)
        self._resync_memo: tuple[Any, bool, int, int | None] | None = None
        self._fed = 0  # bytes fed so far, for the work limit of feed()
        self._wasted = 0  # bytes parsed for no block (checks, failed blocks): the limit's
        self._wasted_records = 0  # records parsed (or failed on) for no block, the same
        self._headers_only = False  # past the limit: resynchronising by block headers alone
        self._lsbs: dict[type, float | None] = {}
        self.service: dict[str, ServiceStats] = {}
        self.blocks: dict[int, int] = {}
        self.records = 0
        # whole blocks whose records stopped parsing early: (category, file offset, rows)
        self._failed_blocks: list[tuple[int, int, int, int]] = []

    # ------------------------------------------------------------------ block walking

    def _parse(self, cat: int, data: bytes, start: int, stop: int, budget: int | None = None
               ) -> tuple[list[tuple[Any, int]], tuple[int, str, bool, int] | None]:
        """Records of ``data[start:stop]`` with their byte offsets, and where and why parsing
        stopped early, whether for records that are no data, and where the bytes it read end
        (None: every byte was read, or ``budget`` bytes of records were). No data: records
        averaging fewer than :data:`MIN_RECORD_BYTES` bytes (not returned) and, past the work
        limit, a record without I010 (the data source every category decoded here requires).
        A check (``budget``) and a parse that stops early count as waste."""
        spec = self.editions.get(cat)
        if spec is None:
            return [], None
        if budget is not None:  # Bits.from_bytes works through every byte it is given
            stop = min(stop, start + budget + MAX_CHECKED_RECORD_BYTES)
        # The records' bits over a copy of this block's bytes only: libasterix's Bits copies
        # its buffer from the read position to the buffer's end for every integer it reads,
        # so over the whole unit (1 MiB) the cost per record grew with the unit's size.
        bits = Bits.from_bytes(data[start:stop])
        out: list[tuple[Any, int]] = []
        err: tuple[int, str, bool, int] | None = None
        source = self._headers_only and budget is None
        at = start
        while len(bits):
            at = start + bits.bit_offset1 // 8
            if budget is not None and at - start >= budget:
                break
            if len(out) > (at - start) // MIN_RECORD_BYTES + DENSE_SLACK:
                err = (at, f"{len(out)} records in {at - start} bytes: no data", True, at)
                out = []
                break
            r = spec.cv_uap.cv_record.parse(ParsingMode.StrictParsing, bits)
            if isinstance(r, ValueError):
                err = (at, str(r), False, at)
                break
            if source and r[0].get_item("010") is None:
                err = (at, "a record without I010 (data source): no data", True,
                       start + r[1].bit_offset1 // 8)
                break
            out.append((r[0], at))
            bits = r[1]
        if budget is not None or err is not None:
            self._wasted += (at if err is not None else stop) - start
            self._wasted_records += len(out) + 1
        return out, err

    def _valid_start(self, data: bytes, q: int) -> bool:
        """Whether a block that checks out starts at ``q``: a decoded category, a length of at
        least 4 within the data, records that parse and a plausible successor (or the end).
        Blocks of other categories are not resynchronised on (their records cannot be checked,
        and bytes inside records often look like their headers)."""
        if data[q] not in self.editions or not _plausible(data, q):
            return False
        nxt = q + ((data[q + 1] << 8) | data[q + 2])
        if nxt - q < 4 or nxt > len(data):
            return False
        if nxt != len(data) and not _plausible(data, nxt):
            return False
        # the first records only: checking every candidate's whole block made the search
        # quadratic (20 KB of 0x30 bytes, each offset a 12 KB CAT048 block whose records
        # parse: minutes); the block found is then read whole, its damage reported
        return self._parse(data[q], data, q + 3, nxt, RESYNC_CHECK_BYTES)[1] is None

    def _header_start(self, data: bytes, q: int) -> bool:
        """Whether a block could start at ``q`` by its header alone (past the work limit): a
        decoded category, a length of at least 4 within the data and a plausible successor (or
        the end)."""
        if data[q] not in self.editions or len(data) - q < 3:
            return False
        nxt = q + ((data[q + 1] << 8) | data[q + 2])
        return nxt - q >= 4 and nxt <= len(data) and (nxt == len(data) or _plausible(data, nxt))

    def _swallows_blocks(self, data: bytes | mmap.mmap, start: int, stop: int) -> bool:
        """Whether whole blocks, the first of a decoded category, follow one another from
        within ``data[start:stop]`` to exactly ``stop``: an undecoded block's declared length
        then runs over blocks that follow it (a flipped length bit landing on a later block's
        start; inside a sound block a header chain landing exactly on its end is rare). Each
        offset is followed once (``ends``: whether the chain from it ends at ``stop``). The
        bytes looked through count toward the work limit (past it the check is not made):
        nested blocks declaring one end had every one look through the same tail again
        (a reviewer's: 420 s a MiB)."""
        self._wasted += stop - start
        ends: dict[int, bool] = {}
        for cat in self.editions:
            mark = bytes([cat])
            p = data.find(mark, start, stop)
            while p != -1:
                path, q = [], p
                while q < stop and q not in ends and _fits(data, q):
                    path.append(q)
                    q += (data[q + 1] << 8) | data[q + 2]
                hit = ends[q] if q in ends else q == stop
                ends.update(dict.fromkeys(path, hit))
                if hit:
                    return True
                ends.setdefault(p, False)
                p = data.find(mark, p + 1, stop)
        return False

    def _over_limit(self) -> bool:
        """Whether the damage read so far took the work limit (:data:`WASTE_FACTOR`)."""
        room = max(self._fed, 1 << 16)
        return (self._wasted > WASTE_FACTOR * room
                or self._wasted_records > room // WASTE_RECORD_BYTES)

    def _resync(self, data: bytes, start: int) -> int | None:
        """The first valid block start at or after ``start`` (past the work limit: by its
        header alone). The last search is remembered: every offset it passed was no start, so
        a search from within it has the same answer (without this, each byte of a damaged tail
        searched to the end again: quadratic)."""
        memo = self._resync_memo
        if memo is not None and memo[0] is data and memo[1] == self._headers_only and (
                memo[2] <= start and (memo[3] is None or start <= memo[3])):
            return memo[3]
        found = None
        for q in range(start, len(data)):
            if self._headers_only:
                if self._header_start(data, q):
                    found = q
                    break
            elif self._valid_start(data, q):
                found = q
                break
            elif self._over_limit():
                self._headers_only = True
        self._resync_memo = (data, self._headers_only, start, found)
        return found

    def feed(self, data: bytes, base: int) -> None:
        """Decode the data blocks of ``data``, whose first byte is at file offset ``base``."""
        pos, end = 0, len(data)
        problems = self.problems
        self._fed += end
        told = self._headers_only
        while pos < end:
            if not self._headers_only and self._over_limit():
                self._headers_only = True
            if self._headers_only and not told:
                told = True
                problems.add("damaged_stretch", f"byte {base + pos}", "the damage before took "
                             f"the reader's work limit ({WASTE_FACTOR} times the bytes read, or "
                             f"a record per {WASTE_RECORD_BYTES} bytes, parsed for no block): "
                             "the rest of this part of the recording is read by block headers "
                             "alone, a block whose records do not parse skipped to its declared "
                             "end")
            if end - pos < 3:
                problems.add("truncated_block", f"byte {base + pos}", f"{end - pos} byte(s) "
                             "left at the end, a block header has 3: skipped")
                return
            cat, length = data[pos], (data[pos + 1] << 8) | data[pos + 2]
            if length < 3:
                q = self._resync(data, pos + 1)
                problems.add("corrupt_block", f"byte {base + pos}", f"block header declares a "
                             f"length of {length} (< 3); {(q or end) - pos} bytes skipped up "
                             "to " + (f"the next block at byte {base + q}" if q is not None
                                      else "the end"))
                if q is None:
                    return
                pos = q
                continue
            nxt = pos + length
            stop = min(nxt, end)
            # parsed whole only once its header and successor check out: parsing every
            # candidate's declared block first made damaged stretches quadratic
            fits = nxt <= end and (nxt == end or _fits(data, nxt))
            if fits and cat not in self.editions:  # its records cannot be checked
                fits = _chain_holds(data, nxt) and (
                    self._headers_only or self._over_limit()
                    or not self._swallows_blocks(data, pos + 3, nxt))
            records, err = self._parse(cat, data, pos + 3, stop) if fits else ([], None)
            if fits and err is None:
                self._handle(cat, records, pos, base, nxt - pos)  # the usual case
                pos = nxt
                continue
            if fits and self._headers_only:  # past the work limit: to the declared end, or
                assert err is not None  # past records that are no data: each byte parsed once
                # (searching from the failed record parsed 64-KB blocks 3 bytes apart: 15 ff ff
                # ... 650 s a MiB; a reviewer's)
                self._handle(cat, records, pos, base, nxt - pos)
                q = (self._resync(data, min(nxt, max(err[3], err[0] + NO_DATA_SKIP)))
                     if err[2] else nxt if nxt < end else None)
                problems.add("bad_record", f"byte {base + err[0]}", f"CAT{cat:03d} record does "
                             f"not parse ({err[1]}); {(q or end) - err[0]} bytes skipped up to "
                             + (f"the next block at byte {base + q}" if q is not None
                                else "the end"))
                if q is None:
                    return
                pos = q
                continue
            # something is wrong: find where the stream goes on
            q = self._resync(data, pos + 1)
            if q is not None and q < stop:  # this block was cut short at q
                records, _ = self._parse(cat, data, pos + 3, q)
                self._handle(cat, records, pos, base, q - pos)
                problems.add("truncated_block", f"byte {base + pos}", f"CAT{cat:03d} block "
                             f"declares {length} bytes but the next block starts at byte "
                             f"{base + q} ({q - pos} bytes on); {len(records)} whole "
                             "record(s) read from it")
                pos = q
                continue
            if not fits:
                records, err = self._parse(cat, data, pos + 3, stop)
            # a whole block whose records stop parsing before its end: damage, or the data
            # of another edition (counted, see finish)
            self._handle(cat, records, pos, base, stop - pos,
                         failed=fits and err is not None and not err[2])
            if nxt > end:
                problems.add("truncated_block", f"byte {base + pos}", f"CAT{cat:03d} block "
                             f"declares {length} bytes, only {end - pos} remain; "
                             f"{len(records)} whole record(s) read from it")
                return
            if err is not None:
                problems.add("bad_record", f"byte {base + err[0]}", f"CAT{cat:03d} record "
                             f"does not parse ({err[1]}); the rest of its block "
                             f"({nxt - err[0]} bytes) skipped")
            if nxt == end or _plausible(data, nxt):
                pos = nxt
                continue
            problems.add("unrecognised_bytes", f"byte {base + nxt}", f"{(q or end) - nxt} "
                         "bytes that are no data block skipped")
            if q is None:
                return
            pos = q

    def _handle(self, cat: int, records: list[tuple[Any, int]], pos: int, base: int,
                size: int, failed: bool = False) -> None:
        """Rows from parsed records (``pos``: the block's offset in ``data``, ``size`` its bytes
        read; ``failed``: a whole block whose records stop parsing before its end, its rows
        noted for :meth:`_other_edition`)."""
        self.blocks[cat] = self.blocks.get(cat, 0) + 1
        first = len(self.rows)
        if cat not in self.editions:
            self.problems.add("unknown_category", f"byte {base + pos}",
                              f"CAT{cat:03d} data block(s) skipped (decoded: "
                              + ", ".join(f"CAT{c:03d}" for c in sorted(self.editions)) + ")",
                              key=str(cat), skipped_bytes=size)
            return
        # the function, not a bound method kept on self: no reference cycle, so a unit's
        # decoder and its rows are freed as soon as the unit is done, not by the cyclic GC
        handler = _HANDLERS[cat]
        for rec, at in records:
            self.records += 1
            try:
                row = handler(self, rec, base + at)
            except Exception as e:  # a record libasterix parses but we cannot read
                self.problems.add("bad_record", f"byte {base + at}",
                                  f"CAT{cat:03d} record not readable: {e!r}", dropped=1)
                continue
            if row is not None:
                self.rows.append(row)
        if failed:
            self._failed_blocks.append((cat, base + pos, first, len(self.rows)))

    # ------------------------------------------------------------------ records
    #
    # What a record says is read with libasterix's item API. Items whose values repeat from
    # record to record (SAC/SIC, the I020/I040 flags, Mode 3/A, flight level, track number)
    # are read once per distinct raw value (the item's ``as_uint()`` or its bytes, a cache
    # key only) and their reading kept in ``self._memo``; the problems they cause are still
    # counted per record. Unsigned quantities (times, slant range, azimuth) are the item's
    # ``as_uint()`` times the LSB of libasterix's content class, as ``as_quantity`` computes
    # them, without building the content objects per record. A row is a tuple in the order
    # of ``_COLUMNS``; a record yields its row only once all of it has been read (a record
    # that raises leaves no partial row).

    def _sensor(self, rec: Any, cat: int, at: int, kind: type | None) -> str | None:
        i010 = rec.get_item("010")
        if i010 is None:
            self.problems.add("missing_item", f"byte {at}", f"CAT{cat:03d} record without "
                              "I010 (SAC/SIC): left out", key=f"{cat}:010", dropped=1)
            return None
        memo_key = ("010", cat, i010.as_uint())
        hit = self._memo.get(memo_key)
        if hit is None:
            hit = self._memo[memo_key] = self._read_sensor(i010, cat, kind)
        sid, problem = hit
        if problem is not None:
            what, message, key, dropped = problem
            self.problems.add(what, f"byte {at}", message, key=key, dropped=dropped)
        return sid

    def _read_sensor(self, i010: Any, cat: int, kind: type | None
                     ) -> tuple[str | None, tuple[str, str, str, int] | None]:
        sac = i010.variation.get_item("SAC").as_uint()
        sic = i010.variation.get_item("SIC").as_uint()
        sensor = self.sensors.by_code(sac, sic)
        if sensor is None:
            return None, ("unknown_sensor", f"SAC {sac} / SIC {sic} (CAT{cat:03d}) is not in "
                          "the sensor file: its records are left out", f"{sac}/{sic}",
                          int(cat != 34))
        if kind is not None and not isinstance(sensor, kind):
            return None, ("wrong_sensor_kind", f"SAC {sac} / SIC {sic} is {sensor.kind} "
                          f"sensor {sensor.id!r} in the sensor file but sends CAT{cat:03d}: "
                          "left out", f"{sac}/{sic}/{cat}", 1)
        return sensor.id, None

    def _flagged(self, item: Any, names: tuple[str, ...], sensor: str, at: int, cat: int
                 ) -> bool:
        """Whether one of the subitems ``names`` of ``item`` is set; such a report is left
        out, counted as ``not_aircraft``."""
        if item is None:
            return False
        memo_key = ("flags", cat, names, item.unparse().to_bytes())
        name = self._memo.get(memo_key, False)
        if name is False:
            name = None
            for n in names:
                sub = item.variation.get_item(n)
                if sub is not None and sub.as_uint():
                    name = n
                    break
            self._memo[memo_key] = name
        if name is None:
            return False
        self.problems.add("not_aircraft", f"byte {at}", f"CAT{cat:03d} report of "
                          f"{sensor!r} flagged {name}: left out",
                          key=f"{sensor}/{name}", dropped=1)
        return True

    def _beyond_rho(self, i020: Any) -> bool:
        """Whether CAT048 I020's ERR (extended range) is set: the slant range is beyond what
        I040's RHO holds (256 NM) and RHO stays at its largest value."""
        memo_key = ("020/ERR", i020.unparse().to_bytes())
        err = self._memo.get(memo_key)
        if err is None:
            sub = i020.variation.get_item("ERR")
            err = self._memo[memo_key] = sub is not None and bool(sub.as_uint())
        return err

    @staticmethod
    def _extended_range(re: Any) -> float | None:
        """The slant range (NM) of CAT048's Reserved Expansion field (ERR, 1/256 NM, its
        edition 1.13 as libasterix defines it), or None where it has none. A long-range radar's
        plot beyond 256 NM read at I040's RHO was up to hundreds of metres short (jASTERIX's
        CAT048 1.23 sample: 257 NM read as 255.996, 1,859 m; a tester's check)."""
        if re is None:
            return None
        parsed = REF_048.cv_expansion.parse(Bits.from_bytes(re.variation.get_bytes()))
        if isinstance(parsed, ValueError):
            return None
        err = parsed[0].get_item("ERR")
        return None if err is None else float(err.variation.content.as_quantity("NM"))

    def _on_ground(self, item: Any, what: str, read: Any) -> int:
        """What ``item`` says of the aircraft (``read(item)``: 1 on the ground, 0 airborne, -1
        not said), read once per raw value; -1 without it."""
        if item is None:
            return -1
        memo_key = (what, item.unparse().to_bytes())  # extended items have no as_uint
        ground = self._memo.get(memo_key)
        if ground is None:
            ground = self._memo[memo_key] = int(read(item))
        return ground

    def _missing(self, cat: int, item: str, sensor: str, at: int) -> None:
        self.problems.add("missing_item", f"byte {at}", f"CAT{cat:03d} report of {sensor!r} "
                          f"without I{cat:03d}/{item}: left out", key=f"{cat}:{item}:{sensor}",
                          dropped=1)

    def _code(self, item: Any, name: str, sensor: str, at: int, cat: int) -> int:
        """A Mode 3/A code, -1 when absent, not validated or garbled (counted)."""
        if item is None:
            return NO_INT
        memo_key = ("070", cat, item.as_uint())
        code = self._memo.get(memo_key)
        if code is None:
            v = item.variation
            code = None
            for flag in ("V", "G"):
                sub = v.get_item(flag) if flag in _names(v) else None
                if sub is not None and sub.as_uint():
                    code = _INVALID
                    break
            if code is None:
                code = int(v.get_item(name).as_uint())
            self._memo[memo_key] = code
        if code is _INVALID:
            self.problems.add("invalid_code", f"byte {at}", f"CAT{cat:03d} Mode 3/A of "
                              f"{sensor!r} not validated or garbled: not used",
                              key=f"{sensor}/3a")
            return NO_INT
        return code

    def _lsb(self, rule: Any) -> float | None:
        """The LSB of an unsigned quantity (``rule``: an element's rule variation, e.g. an
        item's or a group's sub-item), None when signed: read once per libasterix class."""
        lsb = self._lsbs.get(type(rule), False)
        if lsb is False:
            content = type(rule.variation.content)
            lsb = self._lsbs[type(rule)] = (content.cv_lsb if issubclass(
                content.cv_signedness, Unsigned) else None)
        return lsb

    def _unsigned(self, rule: Any, unit: str) -> float:
        """``rule.variation.content.as_quantity(unit)`` of an element (see :meth:`_lsb`)."""
        lsb = self._lsb(rule)
        if lsb is None:
            return rule.variation.content.as_quantity(unit)
        return rule.as_uint() * lsb

    def _memo_quantity(self, what: str, item: Any, unit: str) -> float:
        """``item.variation.content.as_quantity(unit)``, read once per raw value."""
        memo_key = (what, item.as_uint())
        q = self._memo.get(memo_key)
        if q is None:
            q = self._memo[memo_key] = item.variation.content.as_quantity(unit)
        return q

    def _track_number(self, item: Any, what: str, name: str) -> int:
        """The track number subitem ``name`` of I161 (``NO_INT`` without it), read once per
        raw value."""
        if item is None:
            return NO_INT
        memo_key = (what, item.as_uint())
        trn = self._memo.get(memo_key)
        if trn is None:
            trn = self._memo[memo_key] = int(item.variation.get_item(name).as_uint())
        return trn

    def _cat048(self, rec: Any, at: int) -> tuple | None:
        sensor = self._sensor(rec, 48, at, RadarSensor)
        if sensor is None:
            return None
        get = rec.get_item
        i020 = get("020")
        if self._flagged(i020, ("SIM", "TST", "RAB"), sensor, at, 48):
            return None
        i140, i040 = get("140"), get("040")
        if i140 is None:
            return self._missing(48, "140", sensor, at)
        if i040 is None:
            return self._missing(48, "040", sensor, at)
        tod = self._time_of_day(i140, 48, sensor, at)
        if tod is None:
            return None
        g040 = i040.variation
        rho = self._unsigned(g040.get_item("RHO"), "NM")
        if i020 is not None and self._beyond_rho(i020):
            rho = self._extended_range(get("RE"))
            if rho is None:
                self.problems.add("bad_value", f"byte {at}", f"CAT048 report of {sensor!r}: "
                                  "I020 ERR says its slant range is beyond I040's 256 NM, and "
                                  "no extended range (RE ERR) is readable: left out",
                                  key=f"{sensor}/err", dropped=1)
                return None
        theta = self._unsigned(g040.get_item("THETA"), "°")
        fl = np.nan
        i090 = get("090")
        if i090 is not None:
            memo_key = ("090", i090.as_uint())
            fl = self._memo.get(memo_key)
            if fl is None:
                v = i090.variation
                fl = self._memo[memo_key] = (
                    _INVALID if v.get_item("V").as_uint() or v.get_item("G").as_uint()
                    else self._flight_level(v.get_item("FL")))
            if fl is _INVALID:
                self.problems.add("invalid_code", f"byte {at}", f"CAT048 flight level of "
                                  f"{sensor!r} not validated or garbled: not used",
                                  key=f"{sensor}/fl")
                fl = np.nan
            elif isinstance(fl, tuple):
                self.problems.add("bad_value", f"byte {at}", f"CAT048 flight level of "
                                  f"{sensor!r} reads {fl[0]:g} FL through CAT048 "
                                  f"{_edition_name(self.editions[48])}, whose definition "
                                  "takes I048/090 unsigned (1.32's, two's complement, reads a "
                                  "negative FL): not used", key=f"{sensor}/fl-unsigned")
                fl = np.nan
        i220 = get("220")
        trn = self._track_number(get("161"), "161/48", "TRN")
        ground = self._on_ground(get("230"), "230", lambda i: STAT_GROUND.get(
            i.variation.get_item("STAT").as_uint(), -1))
        return (tod, sensor, rho * NM_M, theta, np.nan, np.nan,
                fl * FL_M, fl, NO_INT if i220 is None else int(i220.as_uint()),
                self._code(get("070"), "MODE3A", sensor, at, 48), trn, at, ground)

    def _flight_level(self, rule: Any) -> float | tuple[float]:
        """I048/090's FL (``rule``: its group's FL sub-item). libasterix's CAT048 1.27-1.31
        define it unsigned, 1.32 two's complement: through the former a negative FL (on the
        ground at a sea-level airport in high pressure) reads 4,096 FL too high, so a reading
        of 2,048 FL or more through an unsigned definition is returned as ``(value,)``, not
        used."""
        fl = rule.variation.content.as_quantity("FL")
        return (fl,) if fl >= 2048 and self._lsb(rule) is not None else fl

    def _cat021(self, rec: Any, at: int) -> tuple | None:
        sensor = self._sensor(rec, 21, at, PositionSensor)
        if sensor is None:
            return None
        get = rec.get_item
        i040 = get("040")
        if self._flagged(i040, ("SIM", "TST", "RAB"), sensor, at, 21):
            return None
        # 2.x: time of applicability I071, else of reception I073; 0.2x: time of day I030
        time = get("071") or get("073") or get("030")
        if time is None:
            return self._missing(21, "071" if "071" in type(rec).cv_items_dict else "030",
                                 sensor, at)
        tod = self._time_of_day(time, 21, sensor, at)
        if tod is None:
            return None
        # 2.x: I131 high resolution, else I130; 0.24-0.26: I130 (32-bit, 0.26's I131 is the
        # signal amplitude); 0.23: I130 (24-bit). The LSB is libasterix's for the edition.
        pos = self._position(get("131")) or self._position(get("130"))
        if pos is None:
            return self._missing(21, "130", sensor, at)
        lat = pos.variation.get_item("LAT").variation.content.as_quantity("°")
        lon = pos.variation.get_item("LON").variation.content.as_quantity("°")
        fl, alt = np.nan, np.nan
        i145, i140 = get("145"), get("140")
        if i145 is not None:
            fl = self._memo_quantity("145", i145, "FL")
            alt = fl * FL_M
        if i140 is not None:  # geometric (GNSS): the height the geometry needs, not the FL's
            alt = self._memo_quantity("140/21", i140, "ft") * FT_M
        i080 = get("080")
        trn = self._track_number(get("161"), "161/21", "TRNUM")
        ground = self._on_ground(i040, "040/21", _gbs)
        return (tod, sensor, np.nan, np.nan, lat, lon, alt, fl,
                NO_INT if i080 is None else int(i080.as_uint()),
                self._code(get("070"), "MODE3A", sensor, at, 21), trn, at, ground)

    def _position(self, item: Any) -> Any:
        """``item`` if it is a position (a group with LAT and LON: CAT021 0.26's I131 is the
        signal amplitude, 2.x's the high-resolution position), else None; its structure is
        looked at once per libasterix class."""
        if item is None:
            return None
        memo_key = ("latlon", type(item))
        is_position = self._memo.get(memo_key)
        if is_position is None:
            is_position = self._memo[memo_key] = {"LAT", "LON"} <= _names(item.variation)
        return item if is_position else None

    def _time_of_day(self, item: Any, cat: int, sensor: str, at: int) -> float | None:
        """The record's time of day (s), or None with a problem when it is not within a day
        (the item holds up to 131,072 s: one such record first shifted a whole recording by a
        day, and in the middle put its plot a day off; found by a fuzz helper)."""
        tod = self._unsigned(item, "s")
        if 0 <= tod < DAY_S:
            return tod
        self.problems.add("bad_value", f"byte {at}", f"CAT{cat:03d} report of {sensor!r}: "
                          f"time of day {tod:g} s is not within a day: left out",
                          key=f"{sensor}/tod", dropped=1)
        return None

    def _cat034(self, rec: Any, at: int) -> None:
        sensor = self._sensor(rec, 34, at, None)
        if sensor is None:
            return
        stats = self.service.setdefault(sensor, ServiceStats())
        stats.messages += 1
        i000, i041 = rec.get_item("000"), rec.get_item("041")
        kind = None if i000 is None else i000.as_uint()
        stats.north_markers += int(kind == 1)
        stats.sector_crossings += int(kind == 2)
        if i041 is not None:
            stats.rotation_period_s = float(i041.variation.content.as_quantity("s"))

    # ------------------------------------------------------------------ result

    def _other_edition(self) -> None:
        """Where at least :data:`OTHER_EDITION_BLOCKS` data blocks of a category and half of
        its blocks stop parsing before their end, the data are of another edition than the
        one read (damage spoils a block here and there): the rows read from those blocks are
        garbage, left out (``other_edition``, naming the choices). Read as 2.7, CAT021 0.26
        reports gave a row each, times up to 10 h and positions up to 25,000 km off, beside
        a ``bad_record`` problem per block."""
        drop: list[tuple[int, int]] = []
        for cat in sorted({b[0] for b in self._failed_blocks}):
            failed = [b for b in self._failed_blocks if b[0] == cat]
            if len(failed) < OTHER_EDITION_BLOCKS or 2 * len(failed) < self.blocks[cat]:
                continue
            rows = sum(b[3] - b[2] for b in failed)
            drop += [(b[2], b[3]) for b in failed]
            name = _edition_name(self.editions[cat])
            self.problems.add(
                "other_edition", f"byte {failed[0][1]}", f"{len(failed)} of "
                f"{self.blocks[cat]} CAT{cat:03d} data blocks do not parse to their end as "
                f"CAT{cat:03d} {name}: the recording's CAT{cat:03d} is likely of another "
                f"edition (libasterix has {', '.join(EDITIONS[cat])}; choose with the command "
                f"line's --edition {cat}=EDITION or a job's options.editions); the {rows} "
                "plots read from those blocks are left out", key=str(cat), dropped=rows)
        if drop:
            gone = np.zeros(len(self.rows), dtype=bool)
            for a, b in drop:
                gone[a:b] = True
            self.rows = [row for row, g in zip(self.rows, gone.tolist(), strict=True) if not g]

    def finish(self, size: int) -> Recording:
        self._other_edition()
        n = len(self.rows)
        cols = list(zip(*self.rows, strict=True)) if n else [()] * len(_COLUMNS)
        c = dict(zip(_COLUMNS, cols, strict=True))
        tod = np.array(c["time_of_day_s"], dtype=float)
        rows = PlotRows.from_columns(
            n, "byte", t=unwrap_time_of_day(tod), time_of_day_s=tod,
            sensor=np.array(c["sensor"], dtype=object).reshape(n),
            **{k: np.array(c[k], dtype=float) for k in (
                "range_m", "azimuth_deg", "lat_deg", "lon_deg", "altitude_m", "flight_level")},
            **{k: np.array(c[k], dtype=np.int64) for k in (
                "mode_s", "mode_3a", "track_number", "origin")},
            on_ground=np.array(c["on_ground"], dtype=np.int8))
        return Recording(rows, self.problems, self.service, self.blocks, self.records, size)


_HANDLERS = {48: _Decoder._cat048, 21: _Decoder._cat021, 34: _Decoder._cat034}
"""The record reader of each decoded category."""

_COLUMNS = ("time_of_day_s", "sensor", "range_m", "azimuth_deg", "lat_deg", "lon_deg",
            "altitude_m", "flight_level", "mode_s", "mode_3a", "track_number", "origin",
            "on_ground")
"""The order of a decoded row's values."""

STAT_GROUND = {0: 0, 1: 1, 2: 0, 3: 1}
"""CAT048 I230 STAT (the aircraft's Mode S flight status) -> on the ground (1) or airborne (0);
the other values (4, 5: either; 6, 7: unknown) say neither."""

_INVALID = object()
"""A memoised reading that is not validated or garbled."""


def _gbs(i040: Any) -> int:
    """CAT021 I040's ground bit (in its first extension): 1 set, 0 clear, -1 not sent."""
    sub = i040.variation.get_item("GBS")
    return -1 if sub is None else int(sub.as_uint())


def _names(variation: Any) -> set[str]:
    items = getattr(type(variation), "cv_items_list", [])
    out = set()
    for it in items:
        ns = getattr(it[0], "cv_non_spare", None) if it else None
        if ns is not None:
            out.add(ns.cv_name)
    return out


# ---------------------------------------------------------------------------------- encoding


def encode_rows(rows: PlotRows, sensors: SensorSet, *, max_block_records: int = 16) -> bytes:
    """Plot rows -> a raw ASTERIX recording (libasterix encodes): radar rows as CAT048
    (I010, I140, I040, I090 from ``flight_level``, I220, I070, I161, I230 from ``on_ground``),
    position rows as CAT021 2.7 (I010, I071, I131, I145 from ``flight_level``, I140 from an
    ``altitude_m`` that is not the flight level's pressure altitude, I080, I070, I161, I040
    from ``on_ground``); consecutive rows of one sensor
    share a data block of at most ``max_block_records`` records. The time of day is
    ``time_of_day_s``, else ``t`` modulo a day. For test and benchmark recordings;
    :func:`read_recording` reads them back to the encoding resolution. Raises ``ValueError``
    naming the row for what cannot be encoded (a sensor without SAC/SIC, a slant range beyond
    256 NM)."""
    c048, c021 = DEFAULT_EDITIONS[48], DEFAULT_EDITIONS[21]
    code_of = {sensors.sensors[j].id: code for code, j in sensors.codes.items()}
    out: list[bytes] = []
    block: list[Any] = []
    block_key: tuple[str, int] | None = None

    def flush() -> None:
        if block:
            spec = c048 if block_key is not None and block_key[1] == 48 else c021
            out.append(spec.create(list(block)).unparse().to_bytes())
            block.clear()

    for i in range(len(rows)):
        sid = str(rows.sensor[i])
        if sid not in code_of:
            raise ValueError(f"row {i}: sensor {sid!r} has no sac/sic in the sensor file")
        sac, sic = code_of[sid]
        tod = rows.time_of_day_s[i] if np.isfinite(rows.time_of_day_s[i]) else rows.t[i]
        tod = float(np.mod(tod, 86_400.0))
        fl, alt = float(rows.flight_level[i]), float(rows.altitude_m[i])
        items: dict[str, Any] = {"010": (("SAC", sac), ("SIC", sic))}
        radar = bool(np.isfinite(rows.range_m[i]))
        if radar:
            rho = float(rows.range_m[i]) / NM_M
            if not 0 < rho < 256:
                raise ValueError(f"row {i}: range_m {rows.range_m[i]} is beyond I048/040's "
                                 "256 NM")
            items["140"] = (tod, "s")
            items["040"] = (("RHO", (rho, "NM")),
                            ("THETA", (float(np.mod(rows.azimuth_deg[i], 360.0)), "°")))
            if np.isfinite(fl):
                items["090"] = (0, 0, ("FL", (fl, "FL")))
            if rows.mode_s[i] >= 0:
                items["220"] = int(rows.mode_s[i])
            if rows.mode_3a[i] >= 0:
                items["070"] = (0, 0, 0, 0, ("MODE3A", int(rows.mode_3a[i])))
            if rows.track_number[i] >= 0:
                items["161"] = (0, ("TRN", int(rows.track_number[i])))
            if rows.on_ground[i] >= 0:  # the Mode S flight status: on the ground or airborne
                items["230"] = (("COM", 1), ("STAT", int(rows.on_ground[i])), ("SI", 0), 0,
                                ("MSSC", 1), ("ARC", 1), ("AIC", 1), ("B1A", 0), ("B1B", 0))
            record = c048.cv_record.create(items)
        else:
            items["071"] = (tod, "s")
            items["131"] = (("LAT", (float(rows.lat_deg[i]), "°")),
                            ("LON", (float(rows.lon_deg[i]), "°")))
            if np.isfinite(fl):
                items["145"] = (fl, "FL")
            if np.isfinite(alt) and not (np.isfinite(fl) and alt == fl * FL_M):
                items["140"] = (alt / FT_M, "ft")  # a geometric height beside the FL
            if rows.mode_s[i] >= 0:
                items["080"] = int(rows.mode_s[i])
            if rows.mode_3a[i] >= 0:
                items["070"] = (0, ("MODE3A", int(rows.mode_3a[i])))
            if rows.track_number[i] >= 0:
                items["161"] = (0, ("TRNUM", int(rows.track_number[i])))
            if rows.on_ground[i] >= 0:  # the ground bit, in I040's first extension
                items["040"] = ((("ATP", 1), ("ARC", 1), ("RC", 0), ("RAB", 0), None),
                                (("DCR", 0), ("GBS", int(rows.on_ground[i])), ("SIM", 0),
                                 ("TST", 0), ("SAA", 0), ("CL", 0), None))
            record = c021.cv_record.create(items)
        key = (sid, 48 if radar else 21)
        if key != block_key or len(block) >= max_block_records:
            flush()
            block_key = key
        block.append(record)
    flush()
    return b"".join(out)
