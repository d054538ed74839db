"""The incremental parser: fuzzed with hypothesis (and atheris when installed), plus one test
per drop cause. The fuzz knows every valid packet it wrote and checks the parser emits exactly
the intact ones, in order, and nothing else."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from device import link_protocol as lp
from device.link_parser import LinkParser

MAX_PAYLOAD = 4096


def small_data(seq: int, h: int, w: int, bits: int) -> lp.DataPacket:
    codes = np.random.default_rng(seq).integers(0, 1 << bits, (h, w))
    return lp.DataPacket(seq, seq * 1000, "mantissa", 2.0, bits, 1.0,
                         codes.astype(np.uint8 if bits <= 8 else np.uint16))


PACKETS = st.one_of(
    st.builds(small_data, st.integers(0, 10_000), st.integers(1, 8), st.integers(1, 8),
              st.integers(1, 16)),
    st.sampled_from([lp.StartPacket(), lp.StopPacket(), lp.FrameRatePacket(25.0),
                     lp.EncodingPacket("modulo", 8, 2.0), lp.BracketPacket()]),
)


@st.composite
def damaged(draw: st.DrawFn) -> tuple[bytes, bool, bytes]:
    """A segment of the stream, whether it is an intact packet, and the bytes a cut
    packet misses (empty for the other kinds)."""
    kind = draw(st.sampled_from(["intact", "intact", "garbage", "flip", "cut", "fake"]))
    if kind == "garbage":
        return draw(st.binary(min_size=1, max_size=300)), False, b""
    if kind == "fake":
        length = draw(st.integers(0, (1 << 24) - 1))
        return lp.pack_header(draw(st.integers(0, 255)), length) + draw(st.binary(max_size=64)), \
            False, b""
    wire = lp.encode_packet(draw(PACKETS))
    if kind == "intact":
        return wire, True, b""
    if kind == "cut":
        cut = draw(st.integers(1, len(wire) - 1))
        return wire[:cut], False, wire[cut:]
    data = bytearray(wire)
    # Distinct positions: flipping one byte twice by the same value would restore it.
    for i in draw(st.sets(st.integers(0, len(data) - 1), min_size=1, max_size=4)):
        data[i] ^= draw(st.integers(1, 255))
    return bytes(data), False, b""


def run_parser(stream: bytes, chunks: list[int]) -> tuple[list[lp.Packet], LinkParser]:
    parser = LinkParser(max_payload=MAX_PAYLOAD)
    out: list[lp.Packet] = []
    pos = 0
    for size in chunks:
        out += parser.feed(stream[pos : pos + size])
        pos += size
    out += parser.feed(stream[pos:])
    while parser.buffered:
        out += parser.expire(now=math.inf)
    return out, parser


def same(a: lp.Packet, b: lp.Packet) -> bool:
    return lp.encode_packet(a) == lp.encode_packet(b)


@given(segments=st.lists(damaged(), max_size=25),
       chunks=st.lists(st.integers(1, 700), max_size=40))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_fuzz_emits_exactly_the_intact_packets(segments: list[tuple[bytes, bool, bytes]],
                                               chunks: list[int]) -> None:
    # A cut packet followed by the very bytes it misses is a whole packet, not damage.
    stream = b"".join(data for data, _, _ in segments)
    ends = np.cumsum([len(data) for data, _, _ in segments], dtype=int)
    assume(not any(missing and stream.startswith(missing, int(end))
                   for (_, _, missing), end in zip(segments, ends, strict=True)))
    intact = [data for data, ok, _ in segments if ok]
    out, parser = run_parser(stream, chunks)
    assert [lp.encode_packet(p) for p in out] == intact
    assert parser.buffered == 0
    assert parser.packets_ok == len(intact)


#: A payload limit above every packet of PACKETS (48 + 8 x 8 x 2 bytes) and below most
#: fake lengths, so a parser that trusted a length would hold more than a packet.
SMALL_MAX_PAYLOAD = 512


#: A header whose length is near the limit of SMALL_MAX_PAYLOAD (either side of it).
NEAR_LIMIT_HEADERS = st.builds(lp.pack_header, st.integers(0, 255),
                               st.integers(0, 2 * SMALL_MAX_PAYLOAD))


#: Random bytes, up to three packets' worth (hypothesis draws short binaries).
FILLER = st.builds(lambda size, seed: np.random.default_rng(seed).bytes(size),
                   st.integers(0, 3 * (SMALL_MAX_PAYLOAD + 12)), st.integers(0, 2**32 - 1))


@given(pieces=st.lists(st.one_of(FILLER, NEAR_LIMIT_HEADERS, damaged().map(lambda s: s[0])),
                       max_size=25),
       chunk=st.integers(1, 600))
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_fuzz_emits_only_crc_valid_slices_of_its_input_and_stays_bounded(
    pieces: list[bytes], chunk: int
) -> None:
    """Random bytes mixed with intact, damaged and fake packets: each packet emitted is,
    byte for byte, a slice of the bytes fed so far after the previous one's (its encoding
    carries a valid CRC, so the slice does), and the parser never holds a whole packet's
    worth of bytes."""
    stream = b"".join(pieces)
    parser = LinkParser(max_payload=SMALL_MAX_PAYLOAD)
    after = 0  # where the last emitted packet ended in the stream
    for start in range(0, len(stream), chunk):
        fed = start + chunk
        for packet in parser.feed(stream[start:fed]):
            wire = lp.encode_packet(packet)
            at = stream.find(wire, after, fed)
            assert at >= 0, f"emitted {packet!r}, which is not in the bytes fed after {after}"
            after = at + len(wire)
        assert parser.buffered < parser.max_packet


def test_resynchronises_after_garbage_and_counts_it() -> None:
    good = lp.encode_packet(small_data(1, 4, 4, 8))
    out, parser = run_parser(b"\x00\xa5M" + b"junk" * 10 + good + b"\xa5" + good, [7, 1, 100])
    assert len(out) == 2 and all(same(p, small_data(1, 4, 4, 8)) for p in out)
    assert parser.garbage_bytes == 3 + 40 + 1
    assert sum(parser.drops.values()) == 0


@pytest.mark.parametrize(("mangle", "cause"), [
    (lambda w: w[:5] + bytes([w[5] ^ 1]) + w[6:], "bad_header"),
    (lambda w: w[:20] + bytes([w[20] ^ 1]) + w[21:], "bad_crc"),
    (lambda w: w[:-1] + bytes([w[-1] ^ 1]), "bad_crc"),
    (lambda w: lp.pack_header(lp.PacketType.DATA, MAX_PAYLOAD + 1) + w[8:], "oversize"),
    (lambda w: w[: len(w) // 2], "truncated"),
    (lambda w: lp.frame_packet(0x42, w[8:-4]), "unknown_type"),
    (lambda w: lp.frame_packet(lp.PacketType.DATA, w[8:-5]), "malformed"),
])
def test_each_drop_cause_is_counted_and_the_next_packet_survives(mangle, cause: str) -> None:
    wire = lp.encode_packet(small_data(3, 5, 5, 8))
    out, parser = run_parser(mangle(wire) + wire, [])
    assert [lp.encode_packet(p) for p in out] == [wire]
    assert parser.drops[cause] == 1
    assert sum(parser.drops.values()) == 1


def test_byte_by_byte_feeding_equals_one_feed() -> None:
    wires = [lp.encode_packet(small_data(i, 3, 7, 12)) for i in range(3)]
    stream = b"xx".join(wires)
    parser = LinkParser(MAX_PAYLOAD)
    out = [p for byte in stream for p in parser.feed(bytes([byte]))]
    assert [lp.encode_packet(p) for p in out] == wires


#: Long enough that no pause of the test's own between two lines expires a partial
#: packet ("not yet timed out"); the tests expire it by asking at ``now=math.inf``.
PARTIAL_TIMEOUT_S = 60.0


def test_partial_packet_waits_then_expires_as_truncated() -> None:
    wire = lp.encode_packet(small_data(4, 6, 6, 8))
    parser = LinkParser(MAX_PAYLOAD, partial_timeout_s=PARTIAL_TIMEOUT_S)
    assert parser.feed(wire[:30]) == []
    assert parser.expire() == []  # not yet timed out
    assert parser.buffered == 30
    assert parser.expire(now=math.inf) == []
    assert parser.drops["truncated"] == 1
    assert parser.buffered < len(lp.SIGNATURE)  # only a possible signature start is kept


def test_while_bytes_keep_coming_a_partial_packet_expires_only_once_overtaken() -> None:
    """A long packet still arriving on a slow link (bytes keep coming, nothing complete
    behind it) is kept past the timeout; a header whose corrupt length swallows the
    packets behind it is given up once one of them is complete, and they survive."""
    wire = lp.encode_packet(small_data(4, 6, 6, 8))
    parser = LinkParser(MAX_PAYLOAD, partial_timeout_s=PARTIAL_TIMEOUT_S)
    assert parser.feed(wire[:30]) == []
    assert parser.expire(now=math.inf, quiet=False) == []
    assert parser.feed(wire[30:]) != []
    bogus = lp.pack_header(lp.PacketType.DATA, MAX_PAYLOAD)
    assert parser.feed(bogus + wire) == []
    assert parser.expire(quiet=False) == []  # not yet timed out
    (packet,) = parser.expire(now=math.inf, quiet=False)
    assert lp.encode_packet(packet) == wire and parser.drops["truncated"] == 1


def test_reset_counts_a_started_packet_as_truncated() -> None:
    parser = LinkParser(MAX_PAYLOAD)
    parser.feed(lp.encode_packet(lp.StartPacket())[:-2])
    parser.reset()
    assert parser.drops["truncated"] == 1 and parser.buffered == 0


def test_bad_max_payload_is_rejected() -> None:
    with pytest.raises(ValueError, match="positive"):
        LinkParser(max_payload=0)


@pytest.mark.skipif(importlib.util.find_spec("atheris") is None, reason="atheris not installed")
def test_atheris_fuzz_bounded_run() -> None:
    harness = Path(__file__).with_name("atheris_link_parser.py")
    result = subprocess.run([sys.executable, str(harness), "-runs=2000", "-seed=1"],
                            capture_output=True, text=True, timeout=120,
                            cwd=Path(__file__).parents[2])
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Done 2000 runs" in result.stderr
