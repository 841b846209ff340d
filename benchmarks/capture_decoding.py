"""Decoding a recording as raw ASTERIX and as a pcapng capture of it: CPU per plot.

    python -m benchmarks.capture_decoding --work /work/recfull      # the 200-aircraft recording

The recording is the benchmark's (``benchmarks/recording.py``, built into ``WORK/rec-small``
or reused from there); the capture holds each of its data blocks as one UDP datagram in an
Ethernet frame (the most packets a recording can make), written with dpkt. Each file is read
with :func:`solver.io.asterix.iter_recording` in the command line's units, the two alternated
``--reps`` times; the least CPU time of each counts (``time.process_time``), so bursts of
other work on a shared machine drop out. Writes ``benchmarks/results/capture_decoding.md``.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from pathlib import Path

import dpkt
from dpkt import pcapng

from solver.io.asterix import block_chunks, iter_recording
from solver.io.reading import STREAM_CHUNK_BYTES
from solver.io.sensors_file import load_sensors

from .recording import RecordingSpec, build
from .run import publish


def write_capture(raw: bytes, path: Path) -> int:
    """``raw``'s data blocks as one pcapng packet each; returns the number of packets."""
    blocks = [raw[a:b] for a, b in block_chunks(raw, 1)]  # units of 1 byte: each block alone
    out = [bytes(pcapng.SectionHeaderBlockLE()),
           bytes(pcapng.InterfaceDescriptionBlockLE(linktype=1, snaplen=65535))]
    for block in blocks:
        udp = dpkt.udp.UDP(sport=40000, dport=8600, ulen=8 + len(block), data=block)
        ip = dpkt.ip.IP(src=bytes([10, 0, 0, 1]), dst=bytes([239, 1, 1, 1]), p=17, data=udp)
        frame = dpkt.ethernet.Ethernet(type=dpkt.ethernet.ETH_TYPE_IP, data=ip)
        out.append(bytes(pcapng.EnhancedPacketBlockLE(pkt_data=bytes(frame))))
    path.write_bytes(b"".join(out))
    return len(blocks)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="where the recording is built")
    ap.add_argument("--aircraft", type=int, default=200)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    built = build(RecordingSpec(aircraft=args.aircraft), args.work / "rec-small")
    sensors = load_sensors(built.sensors)
    raw = built.recording.read_bytes()
    capture = built.recording.with_suffix(".pcapng")
    packets = write_capture(raw, capture)
    best = {"raw": float("inf"), "pcapng": float("inf")}
    plots = 0
    for _ in range(args.reps):
        for name, path in (("raw", built.recording), ("pcapng", capture)):
            t0 = time.process_time()
            plots = sum(len(p.rows) for p in iter_recording(path, sensors,
                                                            chunk_bytes=STREAM_CHUNK_BYTES))
            best[name] = min(best[name], time.process_time() - t0)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    md = ["# Decoding a recording as raw ASTERIX and as a pcapng capture", "",
          f"`python -m benchmarks.capture_decoding --work {args.work} --aircraft "
          f"{args.aircraft} --reps {args.reps}` (commit {commit}): {plots} plots, raw "
          f"{len(raw) / 2**20:.1f} MiB, pcapng {capture.stat().st_size / 2**20:.1f} MiB "
          f"({packets} packets, one data block each). Least CPU time of {args.reps} "
          "alternated reads each.", "",
          "| file | CPU s | ms a plot |", "|---|---:|---:|"]
    md += [f"| {k} | {v:.2f} | {1e3 * v / plots:.4f} |" for k, v in best.items()]
    md += ["", f"pcapng / raw: {best['pcapng'] / best['raw']:.3f}"]
    publish("capture_decoding.md", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
