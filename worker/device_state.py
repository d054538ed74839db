"""Per-device decoding state and the hook that decodes one live frame.

Usage::

    decode = make_frame_decoder("temporal", "itoh")   # or "independent"
    state = DeviceState("cam1")                        # new owner: starts with a keyframe
    frame = decode(state, message)                     # DecodedFrame(winding, info, timings_ns)

The worker keeps one :class:`DeviceState` per device stream it owns and drops it
when it loses the lease, so a new owner always starts from a keyframe. Temporal
decoding (``worker/temporal.py``) keeps its memory in ``state.temporal``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.learned import ModelFileError
from models.decoders.registry import get_decoder
from models.errors import InvalidInputError
from models.formation import ENCODINGS
from models.scenes import synthetic_val256_frame
from worker.frame_message import FrameMessage
from worker.temporal_config import MODES

log = logging.getLogger(__name__)

#: The frame a worker warms its stream decoder on (:func:`warm_up`): SCAMP-5's size,
#: a seeded synthetic scene exposed as val-256 is.
WARM_UP_SIZE = 256
WARM_UP_SEED = 0


@dataclass
class DeviceState:
    """What the owning worker knows about one device stream.

    ``last_sequence`` / ``last_entry``: the newest frame whose result is written
    (sequence number, stream entry id); ``frames``: frames decoded by this owner;
    ``temporal``: the temporal decoder's memory (None: the next frame is a keyframe).
    """

    device: str
    last_sequence: int | None = None
    last_entry: str | None = None
    frames: int = 0
    temporal: Any = None


@dataclass
class DecodedFrame:
    """A decoded live frame: winding numbers (int64, the codes' shape), facts, ns timings."""

    winding: NDArray[np.int64]
    info: dict[str, Any] = field(default_factory=dict)
    timings_ns: dict[str, int] = field(default_factory=dict)


FrameDecoder = Callable[[DeviceState, FrameMessage], DecodedFrame]


def make_frame_decoder(mode: str, decoder: str) -> FrameDecoder:
    """The frame decoder for ``mode`` (``independent`` or ``temporal``) on top of the
    spatial decoder ``decoder``."""
    if mode not in MODES:
        raise InvalidInputError(f"unknown frame mode {mode!r}; use one of {MODES}")
    spatial = get_decoder(decoder)
    if mode == "independent":

        def independent(state: DeviceState, message: FrameMessage) -> DecodedFrame:
            result = spatial.decode(message.codes, message.params)
            return DecodedFrame(result.winding, result.info, {"decode": result.timings_ns["total"]})

        return independent

    from worker.stream_state import StreamState
    from worker.temporal import StreamDecoder

    stream_decoder = StreamDecoder("temporal", spatial)

    def temporal(state: DeviceState, message: FrameMessage) -> DecodedFrame:
        if state.temporal is None:
            state.temporal = StreamState()
        frame = stream_decoder.decode(
            message.codes,
            message.params,
            state.temporal,
            sequence=message.sequence,
            discont=message.discont,
        )
        info = {"decoder": spatial.name, "version": spatial.version, "mode": "temporal"}
        return DecodedFrame(
            frame.winding, {**info, **frame.summary()}, {"decode": frame.timings_ns["total"]}
        )

    return temporal


def warm_up(decoder: str) -> dict[str, float]:
    """Decode one seeded synthetic frame (:data:`WARM_UP_SIZE` px) per wrapping encoding
    that spatial decoder ``decoder`` supports, so that a stream's first frame pays
    neither the ONNX sessions' creation nor a latency budget's cost calibration
    (seconds); returns the ms each took. A clear error for an unknown decoder. Each
    encoding is warmed on its own: one whose model file is not its card's
    (:class:`models.decoders.learned.ModelFileError`) is logged and left cold, and the
    others are still warmed (a frame of it fails as ``model_unavailable``)."""
    spatial = get_decoder(decoder)
    took = {}
    for encoding in (e for e in ENCODINGS if e != "clip"):
        frame = synthetic_val256_frame(encoding, WARM_UP_SIZE, WARM_UP_SEED)
        if not spatial.supports(frame.params):
            continue
        start = time.perf_counter_ns()
        try:
            spatial.decode(frame.codes, frame.params)
        except ModelFileError as exc:
            log.error("decoder %s was not warmed up for %s frames, its model install is "
                      "broken: %s", decoder, encoding, exc)  # fmt: skip
            continue
        took[encoding] = (time.perf_counter_ns() - start) / 1e6
    return took
