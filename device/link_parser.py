"""Incremental mcam-link v1 parser: bytes in, verified packets out.

The parser never trusts a length beyond ``max_payload``, resynchronises on the
next signature after garbage, holds at most one maximal packet plus one read
chunk, and counts every packet it throws away by cause:

- ``bad_header``: a signature followed by a header whose checksum is wrong;
- ``oversize``: a header claiming a payload larger than ``max_payload``;
- ``bad_crc``: a complete packet whose CRC-32 does not match;
- ``truncated``: a packet cut short (the next packet's header starts inside it,
  the link closed, or it waited longer than the partial-packet timeout);
- ``unknown_type``: CRC ok but the type byte is not a v1 packet type;
- ``malformed``: CRC ok but the payload contradicts its header (why the last one was
  dropped is kept in ``last_malformed``).

Bytes skipped while hunting for a signature are counted in ``garbage_bytes``.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator

from device.link_protocol import (
    CRC_SIZE,
    DEFAULT_MAX_PAYLOAD,
    HEADER_SIZE,
    SIGNATURE,
    Packet,
    ProtocolError,
    decode_payload,
    is_known_type,
    packet_crc_ok,
    unpack_header,
)

DROP_CAUSES: tuple[str, ...] = (
    "bad_header", "oversize", "bad_crc", "truncated", "unknown_type", "malformed",
)
#: Feed input in slices of at most this many bytes so the buffer stays bounded.
_SLICE = 64 * 1024


class LinkParser:
    """Feed it bytes as they arrive; it returns the complete, verified packets.

    ``partial_timeout_s``: a partial packet older than this is dropped as
    truncated by :meth:`expire` (the reader calls it after every read), so a
    short read or a corrupt length never blocks the stream for long.
    """

    def __init__(self, max_payload: int = DEFAULT_MAX_PAYLOAD,
                 partial_timeout_s: float = 1.0) -> None:
        if max_payload <= 0:
            raise ValueError(f"max_payload must be positive, got {max_payload}")
        self.max_payload = max_payload
        self.partial_timeout_s = partial_timeout_s
        self.drops: Counter[str] = Counter({cause: 0 for cause in DROP_CAUSES})
        self.garbage_bytes = 0
        self.packets_ok = 0
        #: Why the newest malformed packet was dropped ('' until one is).
        self.last_malformed = ""
        self._buf = bytearray()
        self._partial_since: float | None = None

    @property
    def max_packet(self) -> int:
        """Largest packet accepted, in bytes."""
        return HEADER_SIZE + self.max_payload + CRC_SIZE

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a packet."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Add received bytes; return every packet completed by them, in order."""
        out: list[Packet] = []
        view = memoryview(data)
        for start in range(0, len(view), _SLICE):
            self._buf += view[start : start + _SLICE]
            out.extend(self._drain())
        self._start_wait_clock()
        return out

    def _start_wait_clock(self) -> None:
        if self._buf and self._partial_since is None:
            self._partial_since = time.monotonic()

    def expire(self, now: float | None = None, *, quiet: bool = True) -> list[Packet]:
        """Give up on a partial packet that has waited longer than the timeout.

        ``quiet``: the link has gone quiet (the read timed out). While bytes keep coming
        (``quiet=False``) the partial packet is given up only when a complete, verified
        packet has arrived behind it: then its length was corrupt and the sender has
        moved on, whereas a long packet on a slow link is still arriving.

        It is counted as truncated and the hunt resumes one byte later, so
        complete packets buffered behind it are returned, not lost.
        """
        if self._partial_since is None:
            return []
        now = time.monotonic() if now is None else now
        if now - self._partial_since < self.partial_timeout_s:
            return []
        if not quiet and not self._overtaken():
            return []
        if self._buf.startswith(SIGNATURE) and len(self._buf) >= HEADER_SIZE:
            self._drop("truncated")
        else:
            self.garbage_bytes += len(self._buf)
            self._skip(len(self._buf))
        out = self._drain()
        self._start_wait_clock()
        return out

    def reset(self) -> None:
        """Forget buffered bytes (the link closed); a started packet counts as truncated."""
        if self._buf.startswith(SIGNATURE) and len(self._buf) >= HEADER_SIZE:
            self.drops["truncated"] += 1
        else:
            self.garbage_bytes += len(self._buf)
        self._buf.clear()
        self._partial_since = None

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self._partial_since = None

    def _drain(self) -> list[Packet]:
        out: list[Packet] = []
        while True:
            at = self._buf.find(SIGNATURE)
            if at < 0:
                keep = len(SIGNATURE) - 1
                n = max(0, len(self._buf) - keep)
                self.garbage_bytes += n
                self._skip(n)
                return out
            if at:
                self.garbage_bytes += at
                self._skip(at)
            if len(self._buf) < HEADER_SIZE:
                return out
            ptype, length, header_ok = unpack_header(bytes(self._buf[:HEADER_SIZE]))
            if not header_ok:
                self._drop("bad_header")
                continue
            if length > self.max_payload:
                self._drop("oversize")
                continue
            end = HEADER_SIZE + length + CRC_SIZE
            if len(self._buf) < end:
                return out
            packet = self._verify(ptype, end)
            if packet is not None:
                out.append(packet)

    def _verify(self, ptype: int, end: int) -> Packet | None:
        """Check and decode the complete candidate packet in ``buf[:end]``."""
        if not self._crc_ok(0, end):
            self._drop("truncated" if self._next_header_before(end) else "bad_crc")
            return None
        payload = bytes(self._buf[HEADER_SIZE : end - CRC_SIZE])
        self._skip(end)
        if not is_known_type(ptype):
            self.drops["unknown_type"] += 1
            return None
        try:
            packet = decode_payload(ptype, payload)
        except ProtocolError as exc:
            self.drops["malformed"] += 1
            self.last_malformed = exc.message
            return None
        self.packets_ok += 1
        return packet

    def _crc_ok(self, start: int, end: int) -> bool:
        """Whether the candidate packet in ``buf[start:end]`` has a correct CRC."""
        raw = memoryview(self._buf)[start:end]
        try:
            return packet_crc_ok(raw)
        finally:
            raw.release()

    def _later_headers(self, end: int | None = None) -> Iterator[tuple[int, int]]:
        """``(start, payload length)`` of each signature with a valid header that starts
        inside ``buf[1:end]`` (None: to the end of the buffer), in order."""
        at = self._buf.find(SIGNATURE, 1, end)
        while 0 < at and at + HEADER_SIZE <= len(self._buf):
            _, length, header_ok = unpack_header(bytes(self._buf[at : at + HEADER_SIZE]))
            if header_ok:
                yield at, length
            at = self._buf.find(SIGNATURE, at + 1, end)

    def _overtaken(self) -> bool:
        """Whether a complete packet with a valid header and CRC starts after the first
        byte of the buffer (behind the partial packet at its start)."""
        for at, length in self._later_headers():
            end = at + HEADER_SIZE + length + CRC_SIZE
            if length <= self.max_payload and end <= len(self._buf) and self._crc_ok(at, end):
                return True
        return False

    def _next_header_before(self, end: int) -> bool:
        """Whether a signature with a valid header starts inside ``buf[1:end]``."""
        return any(True for _ in self._later_headers(end))

    def _drop(self, cause: str) -> None:
        """Count a rejected candidate and resume the signature hunt one byte later."""
        self.drops[cause] += 1
        self._skip(1)
