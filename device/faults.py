"""Fault injection for the virtual SCAMP-5: damage packets the way a bad link does.

Each switch is a probability per packet or a fraction of bytes; everything is
drawn from one seeded generator, so a run is reproducible. :meth:`Faults.apply`
says whether the packet left the device intact, which is what tests compare
the host's drop counters against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from numbers import Integral

import numpy as np

from device.link_protocol import pack_header
from models.errors import InvalidInputError

#: Longest stall or disconnect (s): an hour. ``time.sleep`` could not wait 1e12 s
#: (OverflowError: the camera's thread died with a traceback and sent nothing more).
MAX_FAULT_S = 3600.0


@dataclass
class Faults:
    """Link faults.

    ``corrupt_bytes``: fraction of bytes overwritten with random values, in bursts
    of ``burst_len`` bytes (line noise is bursty); ``drop_packets``: probability a
    packet is never sent; ``truncate_packets``: probability only its first half is
    sent; ``oversize_packets``: probability a bogus header claiming a 16 MiB
    payload (with a valid header checksum) precedes it; ``stall_every`` /
    ``stall_s``: every N-th packet pauses ``stall_s`` seconds halfway through;
    ``disconnect_every`` / ``disconnect_s``: every N-th packet the link goes away
    for ``disconnect_s`` seconds and comes back. N = 0 means never; durations are
    0 to :data:`MAX_FAULT_S` seconds.
    """

    corrupt_bytes: float = 0.0
    burst_len: int = 256
    drop_packets: float = 0.0
    truncate_packets: float = 0.0
    oversize_packets: float = 0.0
    stall_every: int = 0
    stall_s: float = 0.0
    disconnect_every: int = 0
    disconnect_s: float = 0.5
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("corrupt_bytes", "drop_packets", "truncate_packets", "oversize_packets"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InvalidInputError(f"{name} must be a fraction in [0, 1], got {value}")
        if self.burst_len < 1:
            raise InvalidInputError(f"burst_len must be >= 1, got {self.burst_len}")
        for name in ("stall_every", "disconnect_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Integral) or value < 0:
                raise InvalidInputError(
                    f"{name} must be a whole number of packets, 0 (never) or more, got {value!r}"
                )
        for name in ("stall_s", "disconnect_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= MAX_FAULT_S):
                raise InvalidInputError(
                    f"{name} must be a finite number of seconds, 0 to {MAX_FAULT_S:g}, "
                    f"got {value:g}"
                )
        self._rng = np.random.default_rng(self.seed)

    def apply(self, packet: bytes) -> tuple[bytes, bool]:
        """``(bytes to send, intact)`` for one encoded packet."""
        rng = self._rng
        if self.drop_packets and rng.random() < self.drop_packets:
            return b"", False
        data = bytearray(packet)
        if self.corrupt_bytes:
            self._corrupt(data)
        intact = bytes(data) == packet
        if self.truncate_packets and rng.random() < self.truncate_packets:
            data = data[: len(data) // 2]
            intact = False
        if self.oversize_packets and rng.random() < self.oversize_packets:
            junk = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
            data = bytearray(pack_header(0x01, (1 << 24) - 1) + junk) + data
        return bytes(data), intact

    def _corrupt(self, data: bytearray) -> None:
        rng = self._rng
        bursts = rng.poisson(self.corrupt_bytes * len(data) / self.burst_len)
        for _ in range(int(bursts)):
            start = int(rng.integers(0, len(data)))
            stop = min(len(data), start + self.burst_len)
            data[start:stop] = rng.integers(0, 256, stop - start, dtype=np.uint8).tobytes()

    def stall_now(self, count: int) -> bool:
        """Whether packet number ``count`` should stall halfway."""
        return bool(self.stall_every) and count % self.stall_every == self.stall_every - 1

    def disconnect_now(self, count: int) -> bool:
        """Whether the link should drop before packet number ``count``."""
        return bool(self.disconnect_every) and count % self.disconnect_every == (
            self.disconnect_every - 1
        )
