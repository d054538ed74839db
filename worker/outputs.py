"""Result files of one decoded frame: the HDR EXR, the winding-number map and the codes.

Usage::

    files = encode_outputs(codes, result.winding, params, result.info, options)
    # {"exr": EXR bytes, "winding": .npy bytes (int64), "codes": .npy bytes}

Options (from the job): ``scene_referred`` (default true: x / gain when the gain
is known, else wrap units x), ``half`` (default false: float32 EXR) and
``exr_compression`` (default :data:`models.hdr_io.DEFAULT_EXR_COMPRESSION`, ``zip``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decodable import check_decodable
from models.errors import OutputOverflowError, OutputUnderflowError
from models.exr_header import reconstruction_attributes
from models.formation import SensorParams, reconstruct
from models.frames import encode_frame
from models.hdr_io import DEFAULT_EXR_COMPRESSION, encode_exr
from models.winding_files import encode_winding_file

#: Result-store key suffixes of a job's outputs.
OUTPUT_NAMES = {"exr": "result.exr", "winding": "winding.npy", "codes": "codes.npy"}
#: EXR compression of live device frames (``MCAM_STREAM_EXR_COMPRESSION``). A stream's
#: frames are written at frame rate into the result store, where ZIP cost the worker a
#: third of its time (bench.stream, itoh) to save 14% of the disk; uploads and video jobs,
#: whose files travel to clients, default to ``zip``.
STREAM_EXR_COMPRESSION = "none"


def _exr_form(options: dict[str, Any]) -> tuple[type[np.floating], bool]:
    """The job ``options``' EXR pixel type (half or float32) and whether it is
    scene-referred."""
    half = bool(options.get("half", False))
    return np.float16 if half else np.float32, bool(options.get("scene_referred", True))


def check_result_storable(
    codes: NDArray[Any], params: SensorParams, options: dict[str, Any]
) -> None:
    """Refuse, before a job is queued, a frame whose EXR cannot be stored whatever the
    decoder finds (:func:`models.decodable.check_decodable` with the job's ``options``):
    the worker would fail it with output_overflow or output_underflow."""
    dtype, scene_referred = _exr_form(options)
    check_decodable(codes, params, dtype, scene_referred=scene_referred)


def check_video_storable(
    codes: NDArray[Any], params: SensorParams, options: dict[str, Any]
) -> None:
    """Refuse, before a video job is queued, a clip (T x H x W[x C] codes) whose EXR
    frames cannot be stored whatever the decoder finds: :func:`check_result_storable`
    on each frame, the first frame refused named in the error. A value's fate depends on
    its code alone, so the clip's distinct codes are checked first; a clip that passes
    (the usual case) is not reconstructed frame by frame."""
    try:
        check_result_storable(np.unique(codes), params, options)
    except (OutputOverflowError, OutputUnderflowError) as clip_error:
        for index, frame in enumerate(codes):
            try:
                check_result_storable(frame, params, options)
            except (OutputOverflowError, OutputUnderflowError) as exc:
                raise type(exc)(f"video frame {index}: {exc.message}") from None
        raise clip_error


def encode_exr_result(
    codes: NDArray[Any],
    winding: NDArray[np.integer],
    params: SensorParams,
    info: dict[str, Any],
    options: dict[str, Any],
    source: str = "an uploaded frame",
) -> bytes:
    """The reconstruction as EXR bytes, its units stated in ``comments`` (raises
    OutputOverflowError if it does not fit); ``source`` names the frame there."""
    dtype, scene_referred = _exr_form(options)
    x_hat = reconstruct(codes, winding, params, dtype, scene_referred=scene_referred)
    return encode_exr(
        x_hat,
        reconstruction_attributes(params, info, source, scene_referred),
        half=dtype is np.float16,
        compression=str(options.get("exr_compression", DEFAULT_EXR_COMPRESSION)),
    )


def encode_outputs(
    codes: NDArray[Any],
    winding: NDArray[np.integer],
    params: SensorParams,
    info: dict[str, Any],
    options: dict[str, Any],
) -> dict[str, bytes]:
    """The outputs of a frame, by output name: ``exr``, ``winding`` and ``codes`` (.npy,
    DN). The codes are kept as uploaded: no EXR carries them back for every frame (16-bit
    codes re-encoded from a half-float EXR were off by up to 45 DN, and from a float32
    one, at a thousand wraps, by up to 3 DN: 24 bits hold W and 16 bits of fraction only
    while W < 256)."""
    return {
        "exr": encode_exr_result(codes, winding, params, info, options),
        "winding": encode_winding_file(winding, "npy"),
        "codes": encode_frame(codes, None, "npy"),
    }
