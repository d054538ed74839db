"""The wire format of one wrapped frame on a Redis stream (``frames:<device>``).

The device daemon produces these and workers consume them; both import this
module so the format has one definition. Codes travel as raw bytes, never JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError
from models.formation import SensorParams


@dataclass(frozen=True)
class FrameMessage:
    """One frame from a device.

    ``sequence``: the device's frame counter (numbered on past a wrap of a 32-bit one:
    :func:`device.health.unwrap_sequence`); ``timestamp_ns``: device clock in ns;
    ``discont``: true when temporal state was broken before this frame (reconnect,
    sequence gap); ``codes``: H x W (or H x W x C) uint8/uint16 in DN; ``bracketed``:
    the sequence numbers since the previous streamed frame that a bracketed capture's
    packets took (never streamed: no frames missing, and no frame periods).
    """

    device: str
    sequence: int
    timestamp_ns: int
    codes: NDArray[np.unsignedinteger]
    params: SensorParams
    discont: bool = False
    bracketed: int = 0

    def to_fields(self) -> dict[str, bytes]:
        """Stream entry fields: small text header plus the raw code bytes."""
        codes = np.ascontiguousarray(self.codes)
        return {
            "device": self.device.encode(),
            "seq": str(self.sequence).encode(),
            "ts_ns": str(self.timestamp_ns).encode(),
            "shape": ",".join(str(n) for n in codes.shape).encode(),
            "dtype": codes.dtype.str.encode(),
            "params": self.params.model_dump_json().encode(),
            "discont": b"1" if self.discont else b"0",
            "bracketed": str(self.bracketed).encode(),
            "codes": codes.tobytes(),
        }

    @classmethod
    def from_fields(cls, fields: dict[bytes | str, bytes]) -> FrameMessage:
        """Parse stream entry fields; raises :class:`InvalidInputError` if malformed."""
        get = {(k.decode() if isinstance(k, bytes) else k): v for k, v in fields.items()}
        try:
            shape = tuple(int(n) for n in get["shape"].decode().split(","))
            dtype = np.dtype(get["dtype"].decode())
            if dtype.kind != "u" or dtype.itemsize not in (1, 2):
                raise ValueError(f"dtype {dtype} is not uint8/uint16")
            codes = np.frombuffer(get["codes"], dtype=dtype).reshape(shape)
            return cls(
                device=get["device"].decode(),
                sequence=int(get["seq"]),
                timestamp_ns=int(get["ts_ns"]),
                codes=codes,
                params=SensorParams.model_validate(json.loads(get["params"])),
                discont=get.get("discont", b"0") == b"1",
                bracketed=int(get.get("bracketed", b"0")),
            )
        except KeyError as exc:
            raise InvalidInputError(
                f"malformed frame message: no field {exc}; entries carry "
                "device, seq, ts_ns, shape, dtype, params and codes"
            ) from None
        except (ValueError, TypeError) as exc:
            raise InvalidInputError(f"malformed frame message: {exc}") from None
