"""The one decoder interface: codes + sensor parameters in, W and x_hat out.

Every decoder (classical, learned, adaptive) subclasses :class:`Decoder` and
implements :meth:`Decoder.predict_winding` on a single-channel map of ``m``.
Validation, per-channel dispatch, inversion and timing live here once.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError
from models.formation import SensorParams, clip_winding, dequantize, from_unwrapped

#: Lower-tail percentile of the relative winding map used as the W = 0 anchor. The
#: exposure leaves most pixels unwrapped (overexposed <= 0.35 in practice), so the 5th
#: percentile lies deep in the W = 0 population yet ignores up to 5% of wrong pixels.
ANCHOR_PERCENTILE = 5.0
#: Channels a frame's last axis may hold: grey or RGB.
FRAME_CHANNELS = (1, 3)


@dataclass
class DecodeResult:
    """Output of a decoder.

    ``winding``: int64 winding numbers, same shape as the codes.
    ``irradiance``: x_hat in wrap units (float64), same shape.
    ``timings_ns``: wall time per stage in ns (``predict``, ``invert``, ``total``).
    ``info``: decoder-specific facts (model version, routing decisions, ...).
    """

    winding: NDArray[np.int64]
    irradiance: NDArray[np.float64]
    timings_ns: dict[str, int]
    info: dict[str, Any] = field(default_factory=dict)


def check_frame_shape(codes: NDArray[Any], params: SensorParams | None = None) -> None:
    """Reject frames a decoder cannot unwrap: not 2-D/3-D, or smaller than 2 x 2. A
    frame of ``params`` that never wraps (:func:`never_wraps`) needs no neighbours: any
    size with a pixel is decoded (W = 0)."""
    if codes.ndim == 3 and codes.shape[2] not in FRAME_CHANNELS:
        raise InvalidInputError(_channels_refused(codes.shape))
    if codes.ndim not in (2, 3):
        raise InvalidInputError(f"a frame is H x W or H x W x 3, got shape {codes.shape}")
    if params is not None and never_wraps(params):
        refuse_empty(codes)
    elif codes.shape[0] < 2 or codes.shape[1] < 2:
        raise InvalidInputError(_too_narrow(codes.shape[0], codes.shape[1]))


def _channels_refused(shape: tuple[int, ...]) -> str:
    """Why an H x W x C frame whose C is not 1 or 3 is refused, and what to send instead:
    an RGBA frame without its alpha, a frame stored channels first (C x H x W with C of
    1, 3 or 4 and fewer than its rows and columns, as a tensor is) with its channels last."""
    if shape[2] == 4:
        fix = "H x W or H x W x 3 (RGB without its alpha channel)"
    elif shape[0] in (*FRAME_CHANNELS, 4) and shape[0] < min(shape[1:]):
        fix = (
            f"H x W or H x W x 3: this looks stored channels first ({shape[0]} x H x W); "
            "store each frame with its channels last (H x W x C)"
        )
    else:
        fix = "H x W or H x W x 3"
    return f"a frame has 1 or 3 channels (grey or RGB), got shape {shape}; give {fix}"


def _too_narrow(height: int, width: int) -> str:
    """Why a ``height x width`` frame (pixels) one pixel high or wide is refused, and
    what to send instead (a classical decoder gives each copy of a row sent twice the
    row's W)."""
    lacks = f"a {height} x {width} frame has no neighbours to unwrap against"
    need = "spatial decoders need at least 2 x 2 pixels: send the whole frame"
    if height == 1 and width > 1:
        return f"{lacks} above or below; {need}, or this row twice (a 2 x {width} frame)"
    if width == 1 and height > 1:
        return f"{lacks} left or right; {need}, or this column twice (a {height} x 2 frame)"
    return f"{lacks}; {need}"


def refuse_empty(m: NDArray[Any]) -> None:
    """Reject a frame or channel (H x W, or H x W x C) that holds no pixel: there is
    nothing to unwrap, and a decoder's per-pixel figures (route shares, fractions
    changed) would divide by zero."""
    if m.size == 0:
        raise InvalidInputError(
            f"a {' x '.join(map(str, m.shape))} frame holds no pixels; decoders need at "
            "least 2 x 2 pixels"
        )


def integer_percentile(values: NDArray[np.integer], percentile: float) -> int:
    """``np.percentile(values, percentile, method="higher")`` of integers, by counting:
    the value at sorted index ``ceil((n - 1) * (percentile / 100))`` (in numpy's order of
    operations, so a tiny percentile rounds as it does there). Winding numbers span
    few values, so a histogram is 5-10x cheaper than numpy's partition."""
    flat = np.asarray(values).ravel()
    lowest = int(flat.min())
    counts = np.bincount(flat - lowest)
    index = int(np.ceil((percentile / 100.0) * (flat.size - 1)))
    return lowest + int(np.searchsorted(np.cumsum(counts), index, side="right"))


def anchor_winding(relative: NDArray[np.int64], params: SensorParams) -> NDArray[np.int64]:
    """Fix the unknown constant of an unwrapping: the darkest pixels get W = 0.

    Unwrapping recovers W only up to a global offset. The exposure is set for the
    dark detail, so the darkest pixels never wrap: we shift W so that its
    lower-tail value (the ``ANCHOR_PERCENTILE`` percentile, robust to a few
    isolated errors) is 0, then clamp to [0, max_winding] (W >= 0 since x >= 0).
    """
    return clip_winding(relative - anchor_offset(relative), params)


def anchor_offset(relative: NDArray[np.int64]) -> int:
    """The constant :func:`anchor_winding` takes off ``relative``: its
    ``ANCHOR_PERCENTILE`` percentile."""
    return integer_percentile(relative, ANCHOR_PERCENTILE)


def never_wraps(params: SensorParams) -> bool:
    """Whether frames with ``params`` have W = 0 at every pixel whatever the decoder: a
    clipped sensor (``clip``) never wraps, so it needs no model and no unwrapping. Every
    decoder decodes such a frame (:meth:`Decoder.decode`, :meth:`Decoder.supports`)."""
    return params.encoding == "clip"


class Decoder(ABC):
    """Base class of all decoders. Subclasses set ``name`` and ``predict_winding``."""

    name: ClassVar[str]
    version: str = "1"
    #: Whether the decoder sets clipped blobs to the sensor's clip
    #: (:mod:`models.decoders.saturation`). A stream decoding along time wraps one that
    #: does not (:mod:`models.decoders.filling`), and fills them again after refining
    #: an anchoring keyframe (:mod:`worker.temporal`).
    fills_saturation: ClassVar[bool] = False

    def decode(self, codes: NDArray[Any], params: SensorParams) -> DecodeResult:
        """Decode a frame of codes (H x W or H x W x C, DN) into W and x_hat."""
        start = time.perf_counter_ns()
        codes = np.asarray(codes)
        check_frame_shape(codes, params)
        m = dequantize(codes, params.bits)
        squeeze = m.ndim == 2
        planes = m[:, :, None] if squeeze else m
        info: dict[str, Any] = {"decoder": self.name, "version": self.version}
        if never_wraps(params):
            winding = np.zeros(planes.shape, np.int64)
        else:
            winding, facts = self.explain_planes(planes, params)
            info.update(facts)
        predicted = time.perf_counter_ns()
        if squeeze:
            winding = winding[:, :, 0]
        x_hat = from_unwrapped(winding + m, params)
        done = time.perf_counter_ns()
        return DecodeResult(
            winding=winding,
            irradiance=x_hat,
            timings_ns={
                "predict": predicted - start,
                "invert": done - predicted,
                "total": done - start,
            },
            info=info,
        )

    def supports(self, params: SensorParams) -> bool:
        """Whether this decoder can decode frames with these parameters: one that never
        wraps (:func:`never_wraps`) always, else where it :meth:`unwraps` them."""
        return never_wraps(params) or self.unwraps(params)

    def unwraps(self, params: SensorParams) -> bool:
        """Whether this decoder can find W in frames with these parameters (all, by
        default; a learned decoder only those of the encodings it has a model for)."""
        return True

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """Winding numbers plus facts about how they were found (shown per job).

        Decoders that make per-frame choices (the adaptive router) override this.
        """
        return self.predict_winding(m, params), {}

    def explain_planes(
        self, planes: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """Winding numbers (int64, H x W x C) of every channel of ``planes`` (H x W x C
        wrapped values), and the facts of :meth:`explain_winding`: under ``details`` for
        one channel, a list under ``channels`` for several. Each channel is decoded on its
        own, then a colour frame's channels go through :meth:`join_channels`.
        """
        channels = [self.explain_winding(planes[:, :, c], params) for c in range(planes.shape[2])]
        winding = np.stack([w for w, _ in channels], axis=2).astype(np.int64)
        details = [facts for _, facts in channels if facts]
        info: dict[str, Any] = {}
        if details:
            info = {"channels": details} if len(channels) > 1 else {"details": details[0]}
        if len(channels) > 1:
            winding, joined = self.join_channels(planes, winding, params)
            if joined:
                info["colour"] = joined
        return winding, info

    def join_channels(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """What this decoder does with a colour frame's W (H x W x C) once each channel is
        decoded, and its facts (reported under ``colour``): nothing by default; the
        channels made consistent by :mod:`models.decoders.colour` for decoders that
        decode them jointly."""
        return winding, {}

    def run_pixels(self, shape: tuple[int, int], params: SensorParams) -> list[int]:
        """Pixels of each run :meth:`predict_winding` makes on a channel of ``shape``: the
        unit of work whose fixed and per-pixel cost a latency budget predicts
        (:mod:`models.decoders.budget`). One run of the channel, unless the decoder
        splits it."""
        return [shape[0] * shape[1]]

    @abstractmethod
    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        """Winding numbers (int64, H x W) for one channel of wrapped values m in [0, 1)."""
