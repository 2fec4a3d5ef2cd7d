"""The delay line's cut of a TCP segmentation offload run into its segments (sitl.network.delay_line), for a run
the medium delivered in part: each segment as the sender's NIC would have cut it, the lost ones left out."""

import struct

from sitl.network.delay_line import VNET_HDR, surviving_segments

SRC, DST = bytes([10, 0, 0, 1]), bytes([10, 0, 0, 2])


def _ip_header_sums_to_ones(header: bytes) -> bool:
    total = sum(struct.unpack("!10H", header))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return total == 0xFFFF


def tso_run(payload: bytes, mss: int, seq: int, flags: int, ip_id: int = 100) -> bytes:
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 40 + len(payload), ip_id, 0x4000, 64, 6, 0, SRC, DST)
    tcp = struct.pack("!HHIIBBHHH", 40000, 5201, seq, 77, 5 << 4, flags, 512, 0xABCD, 0)
    return VNET_HDR.pack(1, 1, 40, mss, 20, 16) + ip + tcp + payload


def test_a_run_with_its_middle_segment_lost_gives_the_first_and_last_as_the_nic_would_cut_them():
    """2,500 bytes at an MSS of 1,000 with FIN, PSH, ACK and CWR: segment 1 lost. Segment 0 keeps ACK and CWR
    (FIN and PSH belong to the last), segment 2 keeps FIN, PSH and ACK (CWR belongs to the first); each has its
    own IP length, ID and a valid IP checksum, its sequence number, its bytes, and a header that says: one packet,
    checksum partial at the TCP header's checksum field."""
    payload = bytes(range(256)) * 9 + bytes(196)
    run = tso_run(payload, 1000, 5000, 0x99)
    first, last = surviving_segments(run, (1,))
    for packet, k, size in ((first, 0, 1000), (last, 2, 500)):
        flags, gso_type, hdr_len, gso_size, csum_start, csum_offset = VNET_HDR.unpack_from(packet)
        assert (flags, gso_type, hdr_len, gso_size, csum_start, csum_offset) == (1, 0, 40, 0, 20, 16)
        ip = packet[VNET_HDR.size:]
        assert len(ip) == 40 + size and struct.unpack_from("!HH", ip, 2) == (40 + size, 100 + k)
        assert _ip_header_sums_to_ones(ip[:20])
        assert struct.unpack_from("!I", ip, 24)[0] == 5000 + 1000 * k
        assert ip[40:] == payload[1000 * k:1000 * k + size]
    assert first[VNET_HDR.size + 33] == 0x90 and last[VNET_HDR.size + 33] == 0x19


def test_nothing_lost_gives_every_segment_and_the_sequence_wraps():
    run = tso_run(bytes(3000), 1000, 2**32 - 1024, 0x10)
    packets = surviving_segments(run, ())
    assert [struct.unpack_from("!I", p, VNET_HDR.size + 24)[0] for p in packets] == [2**32 - 1024, 2**32 - 24, 976]
