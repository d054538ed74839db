"""mcam-link v1: the byte-level packet format between a camera and its host.

Documented byte by byte in ``docs/mcam-link-v1.md``; every size, offset and
struct format lives here. All multi-byte integers and floats are little-endian.

A packet on the wire::

    +-----------+------+----------------+----------+-----------------+--------+
    | signature | type | payload length | hdr csum | payload         | CRC-32 |
    |  3 bytes  |  u8  |  u24           |   u8     | length bytes    |  u32   |
    +-----------+------+----------------+----------+-----------------+--------+

The header checksum is ``(~sum(header[0:7])) & 0xFF``; the CRC-32 (zlib /
IEEE 802.3) covers everything after the signature up to the CRC itself: type,
length, header checksum and payload. A data packet's payload is a 48-byte data
header followed by the codes, row-major, 8-bit or 16-bit little-endian.
"""

from __future__ import annotations

import enum
import math
import struct
import sys
import zlib
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError

SIGNATURE = b"\xa5MC"
VERSION = 1

# ---- struct formats (the single place they are written) ----
HEADER_FORMAT = "<3sB3sB"  # signature, type, u24 payload length (as 3 bytes), checksum
DATA_HEADER_FORMAT = "<QQBBHHBBddHBBI"
CRC_FORMAT = "<I"
EXPOSURE_FORMAT = "<dQ"  # gain, integration time ns
ENCODING_FORMAT = "<BBd"  # encoding id, bits, alpha
FRAME_RATE_FORMAT = "<d"  # frames per second
BRACKET_FORMAT = "<Bdd"  # count, base gain (0 = device's choice), ratio

HEADER_SIZE = struct.calcsize(HEADER_FORMAT)
DATA_HEADER_SIZE = struct.calcsize(DATA_HEADER_FORMAT)
CRC_SIZE = struct.calcsize(CRC_FORMAT)
#: Byte offsets inside the 8-byte header.
TYPE_OFFSET = 3
LENGTH_OFFSET = 4
CHECKSUM_OFFSET = 7
#: The largest payload length a u24 can carry.
MAX_PAYLOAD_FIELD = (1 << 24) - 1
#: Default parser limit: a 256 x 256 16-bit frame plus its data header, with headroom.
DEFAULT_MAX_PAYLOAD = DATA_HEADER_SIZE + 512 * 512 * 2

#: Integration time at which a frame's gain is the analog gain (ns): a frame reports
#: ``analog gain * integration / REFERENCE_INTEGRATION_NS``.
REFERENCE_INTEGRATION_NS = 1_000_000
#: Smallest nonzero gain a data header may carry: the smallest normal f64.
MIN_GAIN = sys.float_info.min
#: Largest alpha a data header may carry (as :class:`models.formation.SensorParams`).
MAX_ALPHA = 1e6
#: Data header ``data_type`` of an image of sensor codes (the SCAMP-5 analog-register image).
DATA_TYPE_CODES = 3
#: Data header flag bits.
FLAG_BRACKET = 0x0001  # part of a bracketed reference capture
FLAG_SATURATED_RANGE = 0x0002  # the device clipped x at max_wraps


class PacketType(enum.IntEnum):
    """Packet type byte. Device -> host: DATA; host -> device: the rest."""

    DATA = 0x01
    START = 0x10
    STOP = 0x11
    SET_EXPOSURE = 0x12
    SET_ENCODING = 0x13
    SET_FRAME_RATE = 0x14
    REQUEST_BRACKET = 0x15


#: Encoding ids in the data header and SET_ENCODING, in :data:`models.formation.ENCODINGS` order.
ENCODING_IDS: dict[str, int] = {"modulo": 0, "mantissa": 1, "clip": 2}
ENCODING_NAMES: dict[int, str] = {v: k for k, v in ENCODING_IDS.items()}


class ProtocolError(InvalidInputError):
    """A packet is well framed (CRC ok) but its content is inconsistent."""

    code = "protocol_error"


@dataclass(frozen=True)
class DataPacket:
    """One image from the device.

    ``sequence``: device loop counter; ``timestamp_ns``: device clock (ns);
    ``gain``: wrap units per scene unit (0 = unknown); ``codes``: H x W in DN.
    """

    sequence: int
    timestamp_ns: int
    encoding: str
    alpha: float
    bits: int
    gain: float
    codes: NDArray[np.unsignedinteger]
    flags: int = 0
    bracket_index: int = 0
    bracket_count: int = 0
    channel: int = 0
    data_type: int = DATA_TYPE_CODES
    version: int = VERSION
    type: PacketType = field(default=PacketType.DATA, init=False)


@dataclass(frozen=True)
class StartPacket:
    """Start streaming frames."""

    type: PacketType = field(default=PacketType.START, init=False)


@dataclass(frozen=True)
class StopPacket:
    """Stop streaming frames."""

    type: PacketType = field(default=PacketType.STOP, init=False)


@dataclass(frozen=True)
class ExposurePacket:
    """Set the analog gain (dimensionless) and integration time (ns)."""

    gain: float
    integration_ns: int
    type: PacketType = field(default=PacketType.SET_EXPOSURE, init=False)


@dataclass(frozen=True)
class EncodingPacket:
    """Set the in-pixel encoding (modulo / mantissa / clip), its alpha and the code bits."""

    encoding: str
    bits: int
    alpha: float
    type: PacketType = field(default=PacketType.SET_ENCODING, init=False)


@dataclass(frozen=True)
class FrameRatePacket:
    """Set the frame rate in frames per second."""

    fps: float
    type: PacketType = field(default=PacketType.SET_FRAME_RATE, init=False)


@dataclass(frozen=True)
class BracketPacket:
    """Request a bracketed capture: ``count`` clipped images, gain multiplied by ``ratio``."""

    count: int = 5
    base_gain: float = 0.0
    ratio: float = 2.0
    type: PacketType = field(default=PacketType.REQUEST_BRACKET, init=False)


ControlPacket = (
    StartPacket | StopPacket | ExposurePacket | EncodingPacket | FrameRatePacket | BracketPacket
)
Packet = DataPacket | ControlPacket


def header_checksum(first_seven: bytes) -> int:
    """The header's 8th byte: ones' complement of the byte sum of bytes 0..6, mod 256."""
    return (~sum(first_seven)) & 0xFF


def pack_header(ptype: int, length: int) -> bytes:
    """The 8-byte packet header for a payload of ``length`` bytes."""
    if not 0 <= length <= MAX_PAYLOAD_FIELD:
        raise ProtocolError(f"payload of {length} bytes does not fit the u24 length field")
    head = SIGNATURE + bytes([ptype]) + length.to_bytes(3, "little")
    return head + bytes([header_checksum(head)])


def unpack_header(header: bytes) -> tuple[int, int, bool]:
    """``(type, payload length, checksum ok)`` of an 8-byte header starting with the signature."""
    _, ptype, raw_length, checksum = struct.unpack(HEADER_FORMAT, header)
    return ptype, int.from_bytes(raw_length, "little"), checksum == header_checksum(header[:7])


def frame_packet(ptype: int, payload: bytes) -> bytes:
    """Header + payload + CRC-32 of everything after the signature."""
    body = pack_header(ptype, len(payload))[len(SIGNATURE) :] + payload
    return SIGNATURE + body + struct.pack(CRC_FORMAT, zlib.crc32(body))


def packet_crc_ok(packet: bytes | memoryview) -> bool:
    """Whether the trailing CRC-32 matches the bytes between the signature and the CRC."""
    (expected,) = struct.unpack(CRC_FORMAT, packet[-CRC_SIZE:])
    return zlib.crc32(packet[len(SIGNATURE) : -CRC_SIZE]) == expected


def _check_codes(codes: NDArray[np.unsignedinteger], bits: int) -> NDArray[np.unsignedinteger]:
    arr = np.asarray(codes)
    if arr.ndim != 2 or arr.dtype.kind != "u" or arr.dtype.itemsize != (1 if bits <= 8 else 2):
        raise ProtocolError(
            f"codes must be H x W uint{8 if bits <= 8 else 16} for {bits} bits, "
            f"got {arr.dtype} with shape {arr.shape}"
        )
    return np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))


def encode_data(packet: DataPacket) -> bytes:
    """The wire bytes of a data packet."""
    codes = _check_codes(packet.codes, packet.bits)
    if packet.encoding not in ENCODING_IDS:
        raise ProtocolError(f"unknown encoding {packet.encoding!r}; use one of {ENCODING_IDS}")
    height, width = codes.shape
    data_header = struct.pack(
        DATA_HEADER_FORMAT,
        packet.sequence,
        packet.timestamp_ns,
        packet.data_type,
        packet.version,
        width,
        height,
        packet.bits,
        ENCODING_IDS[packet.encoding],
        packet.alpha,
        packet.gain,
        packet.flags,
        packet.bracket_index,
        packet.bracket_count,
        packet.channel,
    )
    return frame_packet(PacketType.DATA, data_header + codes.tobytes())


def decode_data(payload: bytes | memoryview) -> DataPacket:
    """Parse a data packet's payload; :class:`ProtocolError` if inconsistent."""
    if len(payload) < DATA_HEADER_SIZE:
        raise ProtocolError(f"data payload of {len(payload)} bytes is shorter than its header")
    (seq, ts, dtype_id, version, width, height, bits, enc, alpha, gain, flags, b_index, b_count,
     channel) = struct.unpack_from(DATA_HEADER_FORMAT, payload)
    if version != VERSION or dtype_id != DATA_TYPE_CODES:
        raise ProtocolError(f"unsupported data version {version} / data type {dtype_id}")
    if enc not in ENCODING_NAMES or not 1 <= bits <= 16 or width == 0 or height == 0:
        raise ProtocolError(
            f"bad data header: encoding id {enc} (must be one of {ENCODING_NAMES}), bits {bits} "
            f"(must be 1..16), {width}x{height} pixels (neither may be 0)"
        )
    if not (1.0 < alpha <= MAX_ALPHA and (gain == 0.0 or MIN_GAIN <= gain < math.inf)):
        raise ProtocolError(f"bad data header: alpha {alpha} (must be in (1, {MAX_ALPHA}]), "
                            f"gain {gain} (must be 0 for unknown, or a normal positive number)")
    itemsize = 1 if bits <= 8 else 2
    if len(payload) - DATA_HEADER_SIZE != width * height * itemsize:
        raise ProtocolError(
            f"payload holds {len(payload) - DATA_HEADER_SIZE} code bytes, "
            f"header says {width}x{height}x{itemsize}"
        )
    codes = np.frombuffer(payload, dtype="<u1" if itemsize == 1 else "<u2",
                          offset=DATA_HEADER_SIZE).reshape(height, width)
    if int(codes.max()) >= 1 << bits:
        raise ProtocolError(f"codes exceed {bits} bits")
    return DataPacket(seq, ts, ENCODING_NAMES[enc], alpha, bits, gain,
                      codes.astype(codes.dtype.newbyteorder("=")), flags, b_index, b_count,
                      channel, dtype_id, version)


def encode_control(packet: ControlPacket) -> bytes:
    """The wire bytes of a host -> device control packet."""
    match packet:
        case StartPacket() | StopPacket():
            payload = b""
        case ExposurePacket(gain=gain, integration_ns=integration):
            payload = struct.pack(EXPOSURE_FORMAT, gain, integration)
        case EncodingPacket(encoding=encoding, bits=bits, alpha=alpha):
            payload = struct.pack(ENCODING_FORMAT, ENCODING_IDS[encoding], bits, alpha)
        case FrameRatePacket(fps=fps):
            payload = struct.pack(FRAME_RATE_FORMAT, fps)
        case BracketPacket(count=count, base_gain=base_gain, ratio=ratio):
            payload = struct.pack(BRACKET_FORMAT, count, base_gain, ratio)
        case _:
            raise ProtocolError(f"not a control packet: {packet!r}")
    return frame_packet(packet.type, payload)


def _unpack_exact(fmt: str, payload: bytes | memoryview, what: str) -> tuple:
    if len(payload) != struct.calcsize(fmt):
        raise ProtocolError(f"{what} payload is {len(payload)} bytes, expected "
                            f"{struct.calcsize(fmt)}")
    return struct.unpack(fmt, payload)


def decode_control(ptype: int, payload: bytes | memoryview) -> ControlPacket:
    """Parse a control packet's payload; :class:`ProtocolError` if inconsistent."""
    if ptype in (PacketType.START, PacketType.STOP):
        _unpack_exact("<", payload, PacketType(ptype).name)
        return StartPacket() if ptype == PacketType.START else StopPacket()
    if ptype == PacketType.SET_EXPOSURE:
        gain, integration = _unpack_exact(EXPOSURE_FORMAT, payload, "SET_EXPOSURE")
        return ExposurePacket(gain, integration)
    if ptype == PacketType.SET_ENCODING:
        enc, bits, alpha = _unpack_exact(ENCODING_FORMAT, payload, "SET_ENCODING")
        if enc not in ENCODING_NAMES:
            raise ProtocolError(f"unknown encoding id {enc}")
        return EncodingPacket(ENCODING_NAMES[enc], bits, alpha)
    if ptype == PacketType.SET_FRAME_RATE:
        (fps,) = _unpack_exact(FRAME_RATE_FORMAT, payload, "SET_FRAME_RATE")
        return FrameRatePacket(fps)
    if ptype == PacketType.REQUEST_BRACKET:
        count, base_gain, ratio = _unpack_exact(BRACKET_FORMAT, payload, "REQUEST_BRACKET")
        return BracketPacket(count, base_gain, ratio)
    raise ProtocolError(f"unknown packet type 0x{ptype:02x}")


def encode_packet(packet: Packet) -> bytes:
    """The wire bytes of any packet."""
    return encode_data(packet) if isinstance(packet, DataPacket) else encode_control(packet)


def decode_payload(ptype: int, payload: bytes | memoryview) -> Packet:
    """Parse the payload of a packet of type ``ptype`` (CRC already checked)."""
    if ptype == PacketType.DATA:
        return decode_data(payload)
    return decode_control(ptype, payload)


def is_known_type(ptype: int) -> bool:
    """Whether ``ptype`` is a packet type of mcam-link v1."""
    return ptype in PacketType._value2member_map_
