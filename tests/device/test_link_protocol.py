"""mcam-link v1 encoders/decoders: round trips, sizes, checksums and clear errors."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device import link_protocol as lp

FLOATS = st.floats(min_value=1.0001, max_value=1e6, allow_nan=False)


def data_packet(seq: int = 5, bits: int = 8, shape: tuple[int, int] = (4, 6),
                encoding: str = "modulo") -> lp.DataPacket:
    rng = np.random.default_rng(seq)
    dtype = np.uint8 if bits <= 8 else np.uint16
    codes = rng.integers(0, 1 << bits, shape).astype(dtype)
    return lp.DataPacket(seq, 123_456_789, encoding, 2.0, bits, 1.5, codes, lp.FLAG_BRACKET, 1, 6)


def test_sizes_and_offsets_match_the_document() -> None:
    assert (lp.HEADER_SIZE, lp.DATA_HEADER_SIZE, lp.CRC_SIZE) == (8, 48, 4)
    assert lp.SIGNATURE == b"\xa5MC"
    assert (lp.TYPE_OFFSET, lp.LENGTH_OFFSET, lp.CHECKSUM_OFFSET) == (3, 4, 7)


def test_data_packet_layout_byte_by_byte() -> None:
    packet = data_packet()
    wire = lp.encode_data(packet)
    assert wire[:3] == lp.SIGNATURE and wire[3] == lp.PacketType.DATA
    length = int.from_bytes(wire[4:7], "little")
    assert length == 48 + 24 and len(wire) == 8 + length + 4
    assert wire[7] == (~sum(wire[:7])) & 0xFF
    assert struct.unpack("<I", wire[-4:])[0] == zlib.crc32(wire[3:-4])
    assert struct.unpack_from("<Q", wire, 8)[0] == 5
    assert struct.unpack_from("<Q", wire, 16)[0] == 123_456_789
    assert struct.unpack_from("<HH", wire, 26) == (6, 4)  # width, height
    assert wire[30:32] == bytes([8, 0])  # bits, encoding id (modulo)
    assert struct.unpack_from("<dd", wire, 32) == (2.0, 1.5)
    assert wire[56 : 56 + 24] == packet.codes.tobytes()


@given(seq=st.integers(0, 2**64 - 1), bits=st.integers(1, 16),
       h=st.integers(1, 9), w=st.integers(1, 9),
       encoding=st.sampled_from(["modulo", "mantissa", "clip"]))
@settings(max_examples=60, deadline=None)
def test_data_round_trip(seq: int, bits: int, h: int, w: int, encoding: str) -> None:
    packet = data_packet(seq % 1000, bits, (h, w), encoding)
    packet = lp.DataPacket(seq, packet.timestamp_ns, encoding, 3.0, bits, 0.25, packet.codes)
    wire = lp.encode_packet(packet)
    assert lp.packet_crc_ok(wire)
    back = lp.decode_payload(wire[3], wire[8:-4])
    assert isinstance(back, lp.DataPacket)
    np.testing.assert_array_equal(back.codes, packet.codes)
    assert back.codes.dtype == packet.codes.dtype
    assert (back.sequence, back.encoding, back.bits, back.alpha, back.gain) == (
        seq, encoding, bits, 3.0, 0.25)


CONTROLS = [
    lp.StartPacket(), lp.StopPacket(), lp.ExposurePacket(2.5, 4_000_000),
    lp.EncodingPacket("mantissa", 10, 1.5), lp.FrameRatePacket(60.0),
    lp.BracketPacket(5, 0.125, 2.0),
]


@pytest.mark.parametrize("packet", CONTROLS, ids=lambda p: type(p).__name__)
def test_control_round_trip(packet: lp.ControlPacket) -> None:
    wire = lp.encode_control(packet)
    assert lp.packet_crc_ok(wire)
    assert lp.decode_payload(wire[3], wire[8:-4]) == packet


@given(gain=FLOATS, integration=st.integers(0, 2**64 - 1))
@settings(max_examples=30, deadline=None)
def test_exposure_round_trip(gain: float, integration: int) -> None:
    wire = lp.encode_control(lp.ExposurePacket(gain, integration))
    assert lp.decode_payload(wire[3], wire[8:-4]) == lp.ExposurePacket(gain, integration)


def test_inconsistent_payloads_raise_protocol_errors() -> None:
    wire = lp.encode_data(data_packet())
    with pytest.raises(lp.ProtocolError, match="code bytes"):
        lp.decode_data(wire[8:-5])
    with pytest.raises(lp.ProtocolError, match="shorter than its header"):
        lp.decode_data(b"\x00" * 10)
    with pytest.raises(lp.ProtocolError, match="expected 8"):
        lp.decode_control(lp.PacketType.SET_FRAME_RATE, b"\x00" * 3)
    with pytest.raises(lp.ProtocolError, match="unknown packet type"):
        lp.decode_control(0x7F, b"")
    too_big = data_packet(bits=3)
    codes = too_big.codes.copy()
    codes[0, 0] = 200
    payload = lp.encode_data(lp.DataPacket(1, 0, "modulo", 2.0, 8, 1.0, codes))[8:-4]
    patched = payload[:22] + bytes([3]) + payload[23:]
    with pytest.raises(lp.ProtocolError, match="exceed 3 bits"):
        lp.decode_data(patched)
    for alpha, gain in ((0.0, 1.0), (float("nan"), 1.0), (2.0, -1.0), (2.0, float("inf")),
                        (2.0, 5e-324)):
        payload = lp.encode_data(lp.DataPacket(1, 0, "modulo", alpha, 8, gain, codes))[8:-4]
        with pytest.raises(lp.ProtocolError, match="alpha"):
            lp.decode_data(payload)


def test_encoder_rejects_bad_codes_and_lengths() -> None:
    with pytest.raises(lp.ProtocolError, match="uint16"):
        lp.encode_data(lp.DataPacket(0, 0, "modulo", 2.0, 12, 1.0, np.zeros((2, 2), np.uint8)))
    with pytest.raises(lp.ProtocolError, match="unknown encoding"):
        lp.encode_data(lp.DataPacket(0, 0, "log", 2.0, 8, 1.0, np.zeros((2, 2), np.uint8)))
    with pytest.raises(lp.ProtocolError, match="u24"):
        lp.pack_header(lp.PacketType.DATA, 1 << 24)


def test_header_checksum_detects_any_single_byte_change() -> None:
    header = lp.pack_header(lp.PacketType.DATA, 1000)
    assert lp.unpack_header(header) == (lp.PacketType.DATA, 1000, True)
    for i in range(3, 8):
        damaged = bytearray(header)
        damaged[i] ^= 0x10
        assert not lp.unpack_header(bytes(damaged))[2]
