"""IOSS (FINAL) recordings (solver.io.framing): frames written here with struct after the
layout of jASTERIX's ``ioss`` framing (length of the whole frame, a byte, board, day, time of
reception in 1/100 s, the data blocks, 4 padding bytes) around data blocks encoded with
libasterix; decoded to the same plots as the raw recording, problems at the file's byte
offsets, damaged frames reported and the walk resumed."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from test_io_asterix import SENSORS, assert_same_plots, encode_recording

from solver.io.asterix import decode_blocks, looks_like_recording, read_recording
from solver.io.framing import frame_header_bytes, is_framed, iter_frames
from solver.io.problems import Problems


def frame(blocks: bytes, time_s: float, board: int = 3, day: int = 27,
          seq: int | None = None) -> bytes:
    """One IOSS frame around ``blocks`` (with ``seq``: the variant with a sequence number)."""
    length = 8 + len(blocks) + 4 + (0 if seq is None else 4)
    cs = round(time_s * 100)
    return (struct.pack(">H", length) + (b"" if seq is None else struct.pack(">I", seq))
            + struct.pack(">BBB", 0, board, day) + cs.to_bytes(3, "big") + blocks
            + b"\xa5" * 4)


def framed(blocks: list[bytes], per_frame: int = 1) -> bytes:
    """The blocks, ``per_frame`` to a frame."""
    return b"".join(frame(b"".join(blocks[k:k + per_frame]), 36_000.0 + k)
                    for k in range(0, len(blocks), per_frame))


@pytest.mark.parametrize("per_frame", [1, 3])
def test_a_framed_recording_decodes_to_the_plots_of_the_raw_one(per_frame, tmp_path):
    enc = encode_recording()
    data = framed(enc.blocks, per_frame)
    assert is_framed(data) and looks_like_recording(data[:(1 << 16) + 3])
    assert not is_framed(enc.data)  # a raw recording is not taken for a framed one
    path = tmp_path / "day.ff"
    path.write_bytes(data)
    rec = read_recording(path, SENSORS, chunk_bytes=512)  # many units
    assert not rec.problems, rec.problems.summary()
    assert_same_plots(rec.rows, enc.plots)
    assert rec.packets == -(-len(enc.blocks) // per_frame)
    # each row's origin is its record's offset in the framed file
    raw = decode_blocks(enc.data, SENSORS)
    starts = np.cumsum([0] + [len(b) for b in enc.blocks])
    block_of = np.searchsorted(starts, raw.rows.origin, side="right") - 1
    k = block_of // per_frame
    expected = raw.rows.origin + 8 * (k + 1) + 4 * k
    np.testing.assert_array_equal(rec.rows.origin, expected)
    assert data[rec.rows.origin[0]] == enc.data[raw.rows.origin[0]]


def test_a_damaged_record_in_a_frame_is_located_in_the_file():
    enc = encode_recording()
    data = bytearray(framed(enc.blocks))
    k = 5  # the sixth block's frame; its first record's FSPEC made to promise no item
    at = sum(len(b) + 12 for b in enc.blocks[:k]) + 8
    assert data[at] == enc.blocks[k][0]
    data[at + 3] = 0x00
    rec = read_recording(bytes(data), SENSORS)
    assert "bad_record" in rec.problems.counts
    for e in rec.problems.entries:  # each named at its byte in the file, in that block
        assert at + 3 <= int(e.where.removeprefix("byte ")) < at + len(enc.blocks[k]), e
    assert data[at:at + 3] == enc.blocks[k][:3]


def test_a_damaged_frame_header_is_reported_and_the_walk_goes_on():
    enc = encode_recording()
    frames = [frame(b, 36_000.0 + k) for k, b in enumerate(enc.blocks)]
    k = 7
    bad = bytearray(frames[k])
    bad[0], bad[1] = 0xFF, 0xF0  # a length running over the next frames
    data = b"".join([*frames[:k], bytes(bad), *frames[k + 1:]])
    problems = Problems()
    pieces = list(iter_frames(data, problems))
    (entry,) = problems.entries
    at = sum(len(f) for f in frames[:k])
    assert entry.kind == "bad_frame" and entry.where == f"byte {at}"
    assert f"the next frame at byte {at + len(frames[k])}" in entry.message
    # the damaged frame's blocks are still given to the decoder (with its padding)
    assert pieces[k] == (at + 8, bytes(bad[8:]))
    rec = read_recording(data, SENSORS)
    assert_same_plots(rec.rows, enc.plots)
    kinds = set(rec.problems.counts)
    assert kinds == {"bad_frame", "unrecognised_bytes"}, rec.problems.summary()


def test_a_frame_cut_by_the_end_of_the_file_is_reported_and_its_whole_blocks_read():
    enc = encode_recording()
    data = framed(enc.blocks[:-1]) + frame(enc.blocks[-1] + enc.blocks[-2], 1.0)[:-10]
    rec = read_recording(data, SENSORS)
    assert rec.problems.counts.get("truncated_frame") == 1
    assert_same_plots(rec.rows, enc.plots)  # the cut frame's first block is whole


def test_garbage_is_not_a_framed_recording_and_reading_it_is_linear():
    rng = np.random.default_rng(3)
    junk = rng.integers(0, 256, 300_000, np.uint8).tobytes()
    assert not is_framed(junk[:(1 << 16) + 3])
    enc = encode_recording()
    data = framed(enc.blocks[:10]) + junk + framed(enc.blocks[10:])
    problems = Problems()
    pieces = list(iter_frames(data, problems))
    assert problems.counts == {"bad_frame": problems.counts["bad_frame"]}
    assert sum(len(p) for _, p in pieces) >= len(junk)  # the junk went to the decoder
    rec = read_recording(data, SENSORS)
    assert len(rec.rows) >= len(enc.plots) - 3  # a false frame in the junk may cut one block


def test_the_sequence_numbered_variant_and_empty_frames_are_read():
    """jASTERIX's ioss_seq framing (a 4-byte sequence number after the length: 12-byte
    headers) and empty frames (a recorder's frame of no data block: length 12), also at the
    start of a file; a tester found both read as raw data (0 of 3 reports)."""
    enc = encode_recording()
    seq = b"".join(frame(b, 36_000.0 + k, seq=1000 + k) for k, b in enumerate(enc.blocks))
    assert frame_header_bytes(seq) == 12 and frame_header_bytes(framed(enc.blocks)) == 8
    rec = read_recording(seq, SENSORS)
    assert not rec.problems, rec.problems.summary()
    assert_same_plots(rec.rows, enc.plots)
    empty = frame(b"", 35_999.0)
    assert len(empty) == 12
    gappy = b"".join([empty, empty, *[frame(b, 36_000.0 + k) + (empty if k % 5 == 0 else b"")
                                      for k, b in enumerate(enc.blocks)]])
    assert frame_header_bytes(gappy) == 8
    rec = read_recording(gappy, SENSORS)
    assert not rec.problems, rec.problems.summary()
    assert_same_plots(rec.rows, enc.plots)


@pytest.mark.parametrize(("k", "length"), [(10, 0xFFF0), (150, 0xFFF0), (150, 0x2000),
                                           (150, 0x0400), (150, 0x0040)])
def test_one_damaged_frame_length_in_a_long_file_loses_no_plot(k, length):
    """A frame taken as declared where any plausible length followed it let one damaged
    length misalign the rest of a 1.2-MB file (82 % of its rows lost, nothing reported: a
    reviewer's). A frame is now taken where its blocks fill it, or a sound frame follows."""
    enc = encode_recording(duration=600.0)
    frames = [bytearray(frame(b, 36_000.0 + j)) for j, b in enumerate(enc.blocks)]
    frames[k][0], frames[k][1] = length >> 8, length & 0xFF
    rec = read_recording(b"".join(bytes(f) for f in frames), SENSORS)
    assert rec.problems.counts.get("bad_frame") == 1, rec.problems.summary()
    assert_same_plots(rec.rows, enc.plots)


def test_a_raw_recording_is_not_taken_for_ioss_from_any_block():
    """A raw recording read from any of its block boundaries is raw: 252 of 23,100 were read
    as IOSS frames by the frame checks alone (a reviewer's)."""
    enc = encode_recording(duration=600.0)
    data = enc.data
    starts = np.cumsum([0] + [len(b) for b in enc.blocks[:-1]])
    assert [int(a) for a in starts if frame_header_bytes(data[a:a + (1 << 16) + 3])] == []


def test_a_file_of_many_empty_frames_first_is_ioss():
    """65 empty frames (780 bytes: a recorder idle for a minute) before the first data made
    the file raw (1 of 76 rows; a reviewer's): the head's bytes bound the look, not a count."""
    enc = encode_recording()
    data = frame(b"", 0.0) * 500 + framed(enc.blocks)
    assert frame_header_bytes(data[:(1 << 16) + 3]) == 8
    rec = read_recording(data, SENSORS)
    assert not rec.problems and len(rec.rows) == len(enc.plots)
