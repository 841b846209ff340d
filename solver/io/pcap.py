"""Network captures of ASTERIX (pcap and pcapng) -> UDP payloads with their byte offsets.

dpkt (BSD, pure Python; it reads and writes both capture formats and the link, IP and UDP
layers) decodes every header: the file and packet headers of classic pcap, the section,
interface and packet blocks of pcapng, and each frame's link layer, IPv4/IPv6 header (with
IPv6 extension headers) and UDP header. This module walks the file itself only to know each
payload's byte offset (problems name it) and to report, packet by packet, what cannot be
used instead of dropping it silently.

- pcap: classic libpcap, micro- or nanosecond, either byte order.
- pcapng: several sections (either byte order) and interfaces (each with its link type);
  enhanced, simple and (obsolete) packet blocks; other blocks (statistics, name resolution,
  ...) are skipped.
- Link types: Ethernet (802.1Q / QinQ tags), raw IP (101, 228, 229), Linux cooked v1 / v2,
  BSD loopback.
- IP fragments are reported, not reassembled; packets cut by the capture's snap length and a
  file cut inside a packet are reported (``truncated_packet``).
- Each packet's capture time (epoch seconds; :func:`iter_udp_packets`) gives the recording's
  date (:mod:`solver.io.dates`).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from typing import Any

import dpkt
from dpkt import ethernet, ip, ip6, loopback, pcap, pcapng, sll, sll2, udp

from ..inputs import InputError
from .problems import Problems

# classic pcap: the magic number as it lies in the file -> (file header, packet header)
_PCAP: dict[bytes, tuple[type, type]] = {
    struct.pack(">I", pcap.TCPDUMP_MAGIC): (pcap.FileHdr, pcap.PktHdr),
    struct.pack(">I", pcap.TCPDUMP_MAGIC_NANO): (pcap.FileHdr, pcap.PktHdr),
    struct.pack("<I", pcap.TCPDUMP_MAGIC): (pcap.LEFileHdr, pcap.LEPktHdr),
    struct.pack("<I", pcap.TCPDUMP_MAGIC_NANO): (pcap.LEFileHdr, pcap.LEPktHdr),
}
_NANO = {struct.pack(">I", pcap.TCPDUMP_MAGIC_NANO), struct.pack("<I", pcap.TCPDUMP_MAGIC_NANO)}
_PCAPNG = struct.pack(">I", pcapng.PCAPNG_BT_SHB)  # the same bytes in either byte order
_PCAPNG_ORDER = {struct.pack("<I", pcapng.BYTE_ORDER_MAGIC): "<",
                 struct.pack(">I", pcapng.BYTE_ORDER_MAGIC): ">"}
_BLOCKS = {  # pcapng block classes by byte order
    "<": {"shb": pcapng.SectionHeaderBlockLE, "idb": pcapng.InterfaceDescriptionBlockLE,
          pcapng.PCAPNG_BT_EPB: pcapng.EnhancedPacketBlockLE,
          pcapng.PCAPNG_BT_PB: pcapng.PacketBlockLE},
    ">": {"shb": pcapng.SectionHeaderBlock, "idb": pcapng.InterfaceDescriptionBlock,
          pcapng.PCAPNG_BT_EPB: pcapng.EnhancedPacketBlock,
          pcapng.PCAPNG_BT_PB: pcapng.PacketBlock},
}
_LINKS: dict[int, type] = {1: ethernet.Ethernet, 113: sll.SLL, 276: sll2.SLL2,
                           0: loopback.Loopback}
_RAW_IP = frozenset({101, 228, 229})
_SHORT = {ethernet.ETH_TYPE_IP: "short IPv4 header", ethernet.ETH_TYPE_IP6: "short IPv6 header"}
LINK_TYPES = frozenset(_LINKS) | _RAW_IP
"""Link types whose frames are read (others are refused for a pcap file, reported per packet
for a pcapng interface)."""


def is_capture(head: bytes) -> bool:
    """Whether a file starting with ``head`` is a pcap or pcapng capture."""
    return bytes(head[:4]) in _PCAP or bytes(head[:4]) == _PCAPNG


def iter_udp_payloads(data: Any, problems: Problems) -> Iterator[tuple[int, bytes]]:
    """``(byte offset in the file, payload)`` of every UDP datagram of a capture (``data``:
    bytes or a memory map); what is not one (other protocols, fragments, packets cut short)
    is added to ``problems`` with its packet number and byte offset."""
    for offset, payload, _ in iter_udp_packets(data, problems):
        yield offset, payload


def iter_udp_packets(data: Any, problems: Problems) -> Iterator[tuple[int, bytes, float]]:
    """:func:`iter_udp_payloads` with each packet's capture time (epoch seconds, UTC; NaN for
    a pcapng simple packet block, which has none): classic pcap's seconds and micro- or
    nanoseconds, pcapng's 64-bit count in its interface's ``if_tsresol`` units (default
    microseconds) plus its ``if_tsoffset`` seconds."""
    if bytes(data[:4]) == _PCAPNG:
        yield from _pcapng(data, problems)
    else:
        yield from _pcap(data, problems)


def _pcap(data: Any, problems: Problems) -> Iterator[tuple[int, bytes, float]]:
    if len(data) < 24 or bytes(data[:4]) not in _PCAP:
        raise InputError(("recording",), "is not a pcap capture (no pcap magic number)")
    file_hdr, pkt_hdr = _PCAP[bytes(data[:4])]
    fraction = 1e9 if bytes(data[:4]) in _NANO else 1e6
    linktype = file_hdr(data[:24]).linktype & 0x0FFFFFFF  # the upper bits: FCS information
    if linktype not in LINK_TYPES:
        raise InputError(("recording",), f"pcap link type {linktype} is not read (Ethernet, "
                         "raw IP, Linux cooked capture and loopback are)")
    pos, number = 24, 0
    while pos < len(data):
        number += 1
        if len(data) - pos < 16:
            problems.add("truncated_packet", f"byte {pos}", f"pcap packet {number}: "
                         f"{len(data) - pos} bytes left, a packet header has 16")
            return
        hdr = pkt_hdr(data[pos:pos + 16])
        start = pos + 16
        pos = start + hdr.caplen
        if pos > len(data):
            problems.add("truncated_packet", f"byte {start - 16}", f"pcap packet {number} "
                         f"declares {hdr.caplen} bytes, only {len(data) - start} remain")
            return
        found = _packet(data, start - 16, start, hdr.caplen, hdr.len, linktype,
                        f"pcap packet {number}", problems)
        if found is not None:
            yield (*found, hdr.tv_sec + hdr.tv_usec / fraction)


def _time_units(idb: Any, order: str) -> tuple[float, float]:
    """A pcapng interface's (timestamp units per second, offset in seconds): its
    ``if_tsresol`` (a power of 10, or of 2 with the top bit set; default 10^6) and
    ``if_tsoffset`` options."""
    per_s, offset = 1e6, 0.0
    for opt in getattr(idb, "opts", ()):
        if opt.code == pcapng.PCAPNG_OPT_IF_TSRESOL and len(opt.data) >= 1:
            v = opt.data[0]
            per_s = float(2 ** (v & 0x7F) if v & 0x80 else 10 ** (v & 0x7F))
        elif opt.code == pcapng.PCAPNG_OPT_IF_TSOFFSET and len(opt.data) >= 8:
            offset = float(struct.unpack(order + "q", opt.data[:8])[0])
    return per_s, offset


def _pcapng(data: Any, problems: Problems) -> Iterator[tuple[int, bytes, float]]:
    pos, number = 0, 0
    order = "<"
    # (link type, snap length, time units per second, time offset) of the section's interfaces
    links: list[tuple[int, int, float, float]] = []
    while pos < len(data):
        if len(data) - pos < 12:
            problems.add("truncated_packet", f"byte {pos}", f"pcapng: {len(data) - pos} bytes "
                         "left, a block has at least 12")
            return
        if bytes(data[pos:pos + 4]) == _PCAPNG:  # a section header: its own byte order
            found = _PCAPNG_ORDER.get(bytes(data[pos + 8:pos + 12]))
            if found is None and pos == 0:
                raise InputError(("recording",), "pcapng section header at byte 0 has no "
                                 "byte-order magic")
            if found is None:
                problems.add("truncated_packet", f"byte {pos}", "pcapng section header "
                             "without byte-order magic; the rest of the capture "
                             f"({len(data) - pos} bytes) is not read")
                return
            order, links = found, []
        btype, length = struct.unpack_from(order + "II", data, pos)
        if length < 12 or length % 4:
            problems.add("truncated_packet", f"byte {pos}", f"pcapng block of type {btype} "
                         f"declares a length of {length}; the rest of the capture "
                         f"({len(data) - pos} bytes) is not read")
            return
        if pos + length > len(data):
            problems.add("truncated_packet", f"byte {pos}", f"pcapng block of type {btype} "
                         f"declares {length} bytes, only {len(data) - pos} remain")
            return
        block, at = data[pos:pos + length], pos
        pos += length
        blocks = _BLOCKS[order]
        try:
            if btype == pcapng.PCAPNG_BT_SHB:
                blocks["shb"](block)
            elif btype == pcapng.PCAPNG_BT_IDB:
                idb = blocks["idb"](block)
                links.append((idb.linktype, idb.snaplen, *_time_units(idb, order)))
            elif btype in (pcapng.PCAPNG_BT_EPB, pcapng.PCAPNG_BT_PB):
                number += 1
                pkt = blocks[btype](block)
                where = f"pcapng packet {number}"
                if pkt.iface_id >= len(links):
                    problems.add("not_asterix_packet", f"byte {at}", f"{where}: interface "
                                 f"{pkt.iface_id} is not described", key="no interface")
                    continue
                if pkt.caplen > length - blocks[btype].__hdr_len__:
                    problems.add("truncated_packet", f"byte {at}", f"{where} declares "
                                 f"{pkt.caplen} captured bytes, more than its block holds; "
                                 "skipped", key="bad block")
                    continue
                # the packet data follow the block's fixed header (dpkt's pkt_data)
                link = links[pkt.iface_id]
                found = _packet(data, at, at + blocks[btype].__hdr_len__ - 4, pkt.caplen,
                                pkt.pkt_len, link[0], where, problems)
                if found is not None:
                    yield (*found, ((pkt.ts_high << 32) | pkt.ts_low) / link[2] + link[3])
            elif btype == pcapng.PCAPNG_BT_SPB:  # dpkt has no class for it: 2 fields
                number += 1
                where = f"pcapng packet {number}"
                if not links:
                    problems.add("not_asterix_packet", f"byte {at}", f"{where}: a simple "
                                 "packet block before any interface", key="no interface")
                    continue
                (origlen,) = struct.unpack_from(order + "I", data, at + 8)
                linktype, snaplen = links[0][:2]
                caplen = min(origlen, length - 16, snaplen or origlen)
                found = _packet(data, at, at + 12, caplen, origlen, linktype, where, problems)
                if found is not None:
                    yield (*found, float("nan"))  # a simple packet block has no time
        except dpkt.UnpackError as e:
            problems.add("truncated_packet", f"byte {at}", f"pcapng block of type {btype} "
                         f"does not parse ({e!r}); skipped", key="bad block")


def _packet(data: Any, at: int, start: int, caplen: int, origlen: int, linktype: int,
            where: str, problems: Problems) -> tuple[int, bytes] | None:
    """The UDP payload of the captured frame ``data[start:start + caplen]`` with its offset, or
    None with the reason in ``problems`` (at ``at``, the packet's header or block)."""
    if caplen < origlen:
        problems.add("truncated_packet", f"byte {at}", f"{where} was captured with "
                     f"{caplen} of its {origlen} bytes (snap length); skipped", key="snaplen")
        return None
    found = _udp_payload(bytes(data[start:start + caplen]), linktype)
    if isinstance(found, str):
        problems.add("not_asterix_packet", f"byte {at}", f"{where}: {found}", key=found)
        return None
    offset, payload = found
    return start + offset, payload


def _udp_payload(frame: bytes, linktype: int) -> tuple[int, bytes] | str:
    """(offset in the frame, UDP payload) of one link-layer frame (dpkt decodes the layers),
    or why there is none."""
    if linktype not in LINK_TYPES:
        return f"link type {linktype} is not read"
    try:
        if linktype in _RAW_IP:
            link: Any = None
            net = (ip.IP if frame[:1] and frame[0] >> 4 == 4 else ip6.IP6)(frame)
        else:
            link = _LINKS[linktype](frame)
            net = link.data
    except dpkt.UnpackError:
        return f"frame of {len(frame)} bytes too short for its headers"
    if isinstance(net, ip.IP):
        if net.mf or net.offset:
            return "IPv4 fragment (not reassembled)"
        if net.p != 17:
            return f"IP protocol {net.p}, not UDP"
    elif isinstance(net, ip6.IP6):
        if 44 in net.extension_hdrs:
            return "IPv6 fragment (not reassembled)"
        if net.p != 17:
            return f"IPv6 next header {net.p}, not UDP"
    else:
        kind = getattr(link, "_next_type", None) or getattr(link, "ethtype", None)
        if kind in _SHORT:
            return _SHORT[kind]
        return f"ethertype 0x{kind:04x}, not IP" if kind else "not IP"
    datagram = net.data
    if not isinstance(datagram, udp.UDP):
        return "short UDP header"
    # each layer's header is its length less its payload's (Ethernet counts its tags)
    offset = (len(link) - len(net) if link is not None else 0) + len(net) - len(datagram) + 8
    payload = datagram.data
    if datagram.ulen >= 8:
        payload = payload[:datagram.ulen - 8]
    return offset, bytes(payload)
