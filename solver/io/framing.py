"""Recorders' frames around ASTERIX data blocks -> ``(byte offset, data blocks)`` pieces.

Recording systems store the data blocks they receive wrapped in frames of their own that
carry the time of reception. Read here: the **IOSS** framing, also called the **FINAL**
format (``*.ff`` files, read by SASS-C and by jASTERIX as ``--framing ioss``; layout as in
jASTERIX's ``definitions/framings/ioss.json``)::

    length (2 bytes, big-endian: the whole frame) | a byte | board number | recording day
    | time of reception (3 bytes, 1/100 s since midnight) | data blocks | 4 padding bytes

so a frame of ``length`` bytes holds ``length - 12`` bytes of data blocks from its 9th byte
(none in an empty frame); and its variant with a 4-byte sequence number after the length
(``ioss_seq.json``: a 12-byte header, ``length - 16`` bytes of data blocks). The recording
day byte is no date (no month or year; 0 in jASTERIX's samples): not read
(:mod:`solver.io.dates`).
A file is taken for IOSS when its first frames check out (:func:`frame_header_bytes`); else it is
a raw file or a capture (:mod:`solver.io.asterix`, :mod:`solver.io.pcap`). The data blocks of
each frame are decoded as a capture's datagrams are, with their offsets in the file (problems
name the file's bytes). A damaged frame header is reported (``bad_frame``) and the walk goes on
at the next place where a frame checks out: every offset is looked at once (linear time).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import asterix.generated as ast

from .problems import Problems

KNOWN_CATEGORIES = frozenset(ast.manifest["CATS"]) | {30, 31, 32, 252}
"""Categories whose data block headers are recognised: libasterix's and those of ARTAS and
other systems it does not define (CAT030, CAT031, CAT032, CAT252; skipped by the decoder as
``unknown_category``). A sound CAT020 block followed by a CAT030 one was distrusted, and the
reader resynchronised inside it (a tester's, on jASTERIX's samples)."""
FRAME_HEADERS = (8, 12)
"""Header bytes of the IOSS frames read: without and with the sequence number."""
FRAME_PADDING_BYTES = 4
FRAMES_CHECKED = 2
"""Frames holding data blocks that must be whole at the start of a file for it to be taken
for IOSS (empty frames before them passed), unless its first bytes chain as a raw recording's
blocks (:data:`RAW_BLOCKS_CHECKED`)."""
RAW_BLOCKS_CHECKED = 8
"""A file whose first this many data block headers (or all, to its end) chain is raw, not
IOSS: with the frame checks alone, 252 of 23,100 block boundaries of a raw recording read as
IOSS frames (a reviewer's)."""
DAMAGED_PIECE_BYTES = 1 << 16
"""A damaged stretch is given to the decoder in pieces of at most this many bytes (memory)."""
CHECKED_BLOCKS = 8
"""Data block headers checked per candidate when looking for the next frame after damage
(bounds the work per offset)."""


def _blocks_fill(data: Any, at: int, stop: int, most: int | None = None) -> bool:
    """Whether data blocks of known categories (:data:`KNOWN_CATEGORIES`) follow one another
    from ``at`` to exactly ``stop`` (with ``most``: or for that many blocks)."""
    k = 0
    while at != stop:
        if most is not None and k == most:
            return True
        if stop - at < 3 or data[at] not in KNOWN_CATEGORIES:
            return False
        length = (data[at + 1] << 8) | data[at + 2]
        if length < 3 or at + length > stop:
            return False
        at += length
        k += 1
    return True


def _frame_length(data: Any, pos: int, header: int) -> int | None:
    """The length the frame at ``pos`` declares, where it holds its header and padding (and a
    data block header, unless it is empty) and ends within the data; else None."""
    if len(data) - pos < header + FRAME_PADDING_BYTES:
        return None
    length = (data[pos] << 8) | data[pos + 1]
    empty = header + FRAME_PADDING_BYTES
    return length if ((length == empty or length >= empty + 3)
                      and pos + length <= len(data)) else None


def _whole(data: Any, pos: int, header: int, most: int | None = None) -> bool:
    """A frame at ``pos`` fits the data and its data blocks fill it exactly (``most``: the
    first that many of them, see :func:`_blocks_fill`)."""
    length = _frame_length(data, pos, header)
    return length is not None and _blocks_fill(data, pos + header,
                                               pos + length - FRAME_PADDING_BYTES, most)


def _sound(data: Any, pos: int, header: int) -> bool:
    """A frame starts at ``pos`` (looking for one after damage, bounded work): its first data
    blocks fill it (:data:`CHECKED_BLOCKS`) and the next frame's do too, or the data end."""
    if not _whole(data, pos, header, CHECKED_BLOCKS):
        return False
    nxt = pos + ((data[pos] << 8) | data[pos + 1])
    return nxt == len(data) or _whole(data, nxt, header, CHECKED_BLOCKS)


def frame_header_bytes(head: Any) -> int | None:
    """The header size of :data:`FRAME_HEADERS` with which a file starting with ``head`` (its
    first 64 KiB and 3 bytes, or all of it) is an IOSS (FINAL) recording: its first frames are
    whole (:data:`FRAMES_CHECKED` of them with data blocks, empty ones passed) up to the end of
    ``head`` (the last one checked may run past a ``head`` that is not the whole file), and its
    first bytes do not chain as a raw recording's; None for another file."""
    if _blocks_fill(head, 0, len(head), RAW_BLOCKS_CHECKED):
        return None
    return next((h for h in FRAME_HEADERS if _framed_with(head, h)), None)


def _framed_with(head: Any, header: int) -> bool:
    pos, full = 0, 0
    while full < FRAMES_CHECKED:
        if pos == len(head):
            return full > 0
        length = _frame_length(head, pos, header)
        if length is None and full > 0 and len(head) - pos >= header + FRAME_PADDING_BYTES + 3:
            length = (head[pos] << 8) | head[pos + 1]  # runs past the head: its first blocks
            return (length >= header + FRAME_PADDING_BYTES + 3
                    and _blocks_fill(head, pos + header, len(head), 1))
        if length is None or not _blocks_fill(head, pos + header,
                                              pos + length - FRAME_PADDING_BYTES):
            return False
        full += length > header + FRAME_PADDING_BYTES
        pos += length
    return True


def is_framed(head: Any) -> bool:
    """Whether a file starting with ``head`` is an IOSS recording (:func:`frame_header_bytes`)."""
    return frame_header_bytes(head) is not None


def iter_frames(data: Any, problems: Problems, header: int = FRAME_HEADERS[0]
                ) -> Iterator[tuple[int, bytes]]:
    """``(byte offset in the file, data blocks)`` of every frame of an IOSS recording
    (``data``: bytes or a memory map; ``header``: its frames' header bytes) but the empty
    ones. A frame is taken as declared where its data blocks fill it exactly, or it ends the
    file, or a sound frame follows it (its blocks are then damaged: the decoder says how); a
    length taken on any plausible successor's length let one damaged length misalign the rest
    of a file (82 % of its rows lost, nothing reported: a reviewer's). Elsewhere the frame is
    reported
    (``truncated_frame`` at the end of the file, else ``bad_frame``), the walk goes on at the
    next sound frame, and the bytes in between from the damaged frame's header's end on are
    still given to the decoder, which reports what it cannot read: nothing is left out
    silently."""
    pos, end = 0, len(data)
    while pos < end:
        length = _frame_length(data, pos, header)
        if length is not None and (_whole(data, pos, header) or pos + length == end
                                   or _sound(data, pos + length, header)):
            if length > header + FRAME_PADDING_BYTES:
                yield pos + header, bytes(data[pos + header:pos + length - FRAME_PADDING_BYTES])
            pos += length
            continue
        q = next((p for p in range(pos + 1, end) if _sound(data, p, header)), None)
        stop = end if q is None else q
        declared = (data[pos] << 8) | data[pos + 1] if end - pos >= 2 else 0
        if q is None and pos + declared > end:
            problems.add("truncated_frame", f"byte {pos}", f"frame declares {declared} bytes, "
                         f"only {end - pos} remain: what it holds is read")
        else:
            problems.add("bad_frame", f"byte {pos}", f"no IOSS frame checks out here "
                         f"(declared length {declared}); {stop - pos} bytes read as data "
                         "blocks up to " + (f"the next frame at byte {q}" if q is not None
                                            else "the end"))
        for a in range(pos + header, stop, DAMAGED_PIECE_BYTES):
            yield a, bytes(data[a:min(a + DAMAGED_PIECE_BYTES, stop)])
        pos = stop
