"""What temporal decoding remembers about a stream, and what it reports per frame.

The worker keeps one :class:`StreamState` per device stream (:mod:`worker.device_state`)
and :class:`worker.temporal.StreamDecoder` returns a :class:`FrameDecode` per frame,
with the share of pixels that took each path of :data:`PATHS`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.formation import SensorParams

#: The paths a pixel of a temporal step can take (see :mod:`worker.temporal`).
PATHS: tuple[str, ...] = ("temporal", "local", "spatial")


@dataclass
class StreamState:
    """What temporal decoding remembers about one stream.

    ``u``: the previous frame's unwrapped values (H x W x C, wraps); ``params``: its
    sensor parameters; ``frames``: frames decoded so far; ``last_keyframe``: index of
    the last keyframe; ``sequence``: the previous frame's device sequence number;
    ``next_whole``: the frame index from which a moving camera's frame is refined whole
    again, ``whole_interval``: the wait (frames) that set it (:mod:`worker.temporal`).
    """

    u: NDArray[np.float64] | None = None
    params: SensorParams | None = None
    frames: int = 0
    last_keyframe: int = -1
    sequence: int | None = None
    next_whole: int = 0
    whole_interval: int = 0

    def reset(self) -> None:
        """Forget the stream: the next frame is a keyframe."""
        self.u, self.params, self.sequence = None, None, None


@dataclass
class FrameDecode:
    """One decoded video frame.

    ``winding`` (int64) and ``irradiance`` (x_hat, wrap units) have the codes' shape;
    ``keyframe`` is why the frame was decoded whole (``first``, ``discont``, ``gap``,
    ``params``, ``periodic``, ``independent``) or None; ``paths`` the fraction of
    pixels per path (:data:`PATHS`); ``timings_ns`` wall time in ns.
    """

    winding: NDArray[np.int64]
    irradiance: NDArray[np.float64]
    keyframe: str | None
    paths: dict[str, float]
    timings_ns: dict[str, int] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly facts about the frame (no arrays)."""
        return {"keyframe": self.keyframe, "paths": self.paths, "timings_ns": self.timings_ns}


def path_shares(local: NDArray[np.bool_], spatial: NDArray[np.bool_]) -> dict[str, float]:
    """The fraction of pixels (and channels) that took each path of :data:`PATHS`."""
    used_local, used_spatial = float(local.mean()), float(spatial.mean())
    return {
        "temporal": 1.0 - used_local - used_spatial,
        "local": used_local,
        "spatial": used_spatial,
    }
