"""Uploaded files and their parameters, named like the CLI flags.

A request carries either ``multipart/form-data`` (the file in the field ``file``,
parameters as form fields) or a raw ``application/octet-stream`` body
(parameters as query parameters). Query parameters also apply to multipart
requests; form fields win. The body size limit is enforced while streaming
(:mod:`service.api.body_limit`). Decoding an upload (or simulating a frame from it)
takes up to gigabytes of the API's memory, so at most ``MCAM_MAX_CONCURRENT_DECODES`` run
at once (:func:`service.api.in_turn.decode_in_turn`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from models.decoders.adaptive_policy import QUALITIES
from models.errors import InvalidInputError, MissingParameterError, UnsupportedFormatError
from models.file_magic import (
    FRAME_MAGICS,
    Judged,
    content_first,
    format_by_content,
    named_format,
    refuse_empty,
)
from models.formation import SensorParams
from models.frames import FRAME_ALIASES, FRAME_FORMATS, not_a_frame
from models.hdr_io import DEFAULT_EXR_COMPRESSION, EXR_COMPRESSIONS
from service.api.errors import ApiError
from service.api.media_types import media_type
from service.api.single_values import refuse_repeated

Model = TypeVar("Model", bound=BaseModel)
_MAX_FORM_FIELDS = 64
#: The start of a multipart/form-data body: a boundary line (RFC 2046: at most 70
#: characters) and a part's Content-Disposition.
_MULTIPART_START = re.compile(rb"--([^\r\n]{1,70})\r\nContent-Disposition:\s*form-data",
                              re.IGNORECASE)
#: The frame format each file-name suffix names: the readers' (:mod:`models.frames`)
#: and raw codes.
_NAMED = {**FRAME_ALIASES, "raw": "raw", "bin": "raw"}


class SensorFields(BaseModel):
    """Sensor parameters (see ``models.formation.SensorParams``); given ones override any
    parameters stored in the file. Ranges are checked when the parameters are merged."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    encoding: Literal["modulo", "mantissa", "clip"] | None = None
    alpha: float | None = Field(None, description="mantissa base: one wrap per factor alpha")
    bits: int | None = Field(None, description="bits per code (1..16)")
    gain: float | None = Field(None, description="scene irradiance to wrap units")
    max_wraps: float | None = Field(
        None, description="clip x at this many wrap units (at least 1, the first wrap)"
    )
    read_noise: float | None = Field(None, description="Gaussian sigma in wraps")
    full_well: float | None = Field(
        None, description="electrons at x = 1 (shot noise; at least 1)"
    )
    seed: int | None = Field(None, description="noise seed")

    def sensor_overrides(self) -> dict[str, Any]:
        """The sensor parameters that were given (None = not given)."""
        return {name: getattr(self, name) for name in SensorParams.model_fields}


class ReconstructionFields(SensorFields):
    """Parameters of ``POST /v1/reconstructions``."""

    decoder: str | None = Field(None, description="decoder name (GET /v1/decoders)")
    quality: Literal[QUALITIES] | None = Field(  # type: ignore[valid-type]
        None, description="instead of decoder: the adaptive decoder at this quality"
    )
    latency_ms: float | None = Field(
        None, ge=0.1, le=600_000,
        description="instead of decoder or quality: the most accurate adaptive routing "
        "predicted to find W within this many ms (decoder auto-<N>ms)",
    )  # fmt: skip
    format: Literal["png", "tiff", "npy", "raw"] | None = Field(
        None, description="frame file format; default: from the file name or its first bytes. "
        "A PNG, TIFF or npy is read as what its first bytes show, whatever this or the name "
        "says",
    )
    width: int | None = Field(None, ge=1, le=1 << 16, description="raw frames: pixels per row")
    height: int | None = Field(None, ge=1, le=1 << 16, description="raw frames: rows")
    channels: int | None = Field(None, ge=1, le=4, description="raw frames: codes per pixel")
    scene_referred: bool = Field(
        True, description="divide the result by the gain when known (false: wrap units)"
    )
    half: bool = Field(
        False,
        description="write a half-float EXR (default float32; values under 6.1e-5 are kept "
        "to 3e-8 only, so dark scene-referred pixels lose precision)",
    )
    exr_compression: Literal[tuple(EXR_COMPRESSIONS)] = Field(  # type: ignore[valid-type]
        DEFAULT_EXR_COMPRESSION,
        description="lossless EXR compression: zip (smaller) or none (faster)",
    )


class SimulateFields(SensorFields):
    """Parameters of ``POST /v1/simulate``."""

    overexposed: float | None = Field(
        None, description="instead of gain: the fraction of pixels at x >= 1, strictly "
        "between 0 and 1"
    )
    gray: bool = Field(False, description="encode Rec.709 luminance instead of RGB")
    clip_negative: bool = Field(False, description="set negative irradiance to 0")
    seed: int | None = Field(
        0, description="noise seed (0 by default, as mcam simulate: a request gives the same "
        "frame every time)",
    )
    format: Literal["png", "npy", "tiff"] | None = Field(
        None, description="output file format (default: png for one channel, tiff for colour)"
    )
    part: Literal["codes", "winding"] = Field(
        "codes", description="the wrapped frame, or the true winding numbers W"
    )


@dataclass(frozen=True)
class Upload:
    """The uploaded bytes, the client's file name (never used as a path) and form fields."""

    data: bytes
    filename: str | None
    fields: dict[str, str]


async def _read_multipart(request: Request) -> Upload:
    try:
        form = await request.form(max_files=1, max_fields=_MAX_FORM_FIELDS)
    except HTTPException as exc:
        if isinstance(exc, ApiError) or not isinstance(exc.detail, str):
            raise  # ours (the body limit's 413), already a JSON error
        raise ApiError(
            exc.status_code, "bad_request",
            f"the multipart/form-data body could not be read ({exc.detail.rstrip('.')}); send "
            "one well-formed part per field, the file in 'file' with a short file name "
            "(curl -F file=@frame.png)",
        ) from None  # fmt: skip
    try:
        file = form.get("file")
        if isinstance(file, str):
            raise MissingParameterError(
                "the field 'file' came as text, not as a file: its part's Content-Disposition "
                "has no filename (curl -F file=<frame.png sends the file's bytes as text, "
                "and the parameter filename* alone is not read); send it as a file "
                "(curl -F file=@frame.png)"
            )
        if not isinstance(file, UploadFile):
            raise MissingParameterError(
                "no file uploaded: send it in the multipart/form-data field 'file' (a body "
                "cut short before its closing boundary loses the file too)"
            )
        fields: list[tuple[str, str]] = []
        for name, value in form.multi_items():
            if name == "file":
                continue
            if not isinstance(value, str):
                raise InvalidInputError(f"form field {name!r} must be text, not a file")
            fields.append((name, value))
        refuse_repeated(fields)
        return Upload(await file.read(), file.filename, dict(fields))
    finally:
        await form.close()


def _refuse_multipart_as_raw(body: bytes | bytearray) -> None:
    """Refuse a multipart/form-data body labelled application/octet-stream: read as the
    raw file, it was told to be converted to OpenEXR, or that its frame format could not
    be told, which sent the client to the wrong fix."""
    found = _MULTIPART_START.match(body)
    if found is not None:
        boundary = found.group(1).decode("latin-1")
        raise UnsupportedFormatError(
            "the body is a multipart/form-data body sent as application/octet-stream: send "
            f"it with the header 'Content-Type: multipart/form-data; boundary={boundary}' "
            "(curl -F file=@frame.png does), or send the raw file alone"
        )


async def read_upload(request: Request) -> Upload:
    """The request's file: multipart field ``file`` or the raw body."""
    media = media_type(request)
    if media == "multipart/form-data":
        upload = await _read_multipart(request)
    elif media == "application/octet-stream":
        body = bytearray()
        async for chunk in request.stream():
            body += chunk
        _refuse_multipart_as_raw(body)
        upload = Upload(bytes(body), None, {})
    else:
        raise UnsupportedFormatError(
            f"unsupported content type {media or '(none)'!r}: send multipart/form-data with "
            "the file in the field 'file', or the raw file as application/octet-stream"
        )
    refuse_empty(len(upload.data), "the uploaded file")
    return upload


async def read_upload_fields(
    request: Request, model: type[Model], query: BaseModel
) -> tuple[Upload, Model]:
    """The upload, and the query parameters updated by its form fields, validated as
    ``model`` (422 if bad)."""
    upload = await read_upload(request)
    values = {**query.model_dump(exclude_unset=True), **upload.fields}
    try:
        return upload, model.model_validate(values)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors()) from None


def sniff_frame_format(upload: Upload, declared: str | None, raw_size: bool) -> Judged:
    """The frame format to decode the upload as: the declared one, else the file name's
    suffix's, else the leading bytes', else ``raw`` when a raw frame size (``raw_size``)
    was given. A PNG, TIFF or npy is decoded as what its leading bytes show whatever
    its name says (:func:`models.frames.decode_frame`); raw codes have no leading bytes
    to judge by, so declared or named raw with a size given, they are raw. Declared or
    named raw without a size, a PNG, TIFF or npy is decoded as what it is, with the
    warning naming both (:func:`models.file_magic.content_first`)."""
    named = declared or named_format(upload.filename, _NAMED)
    if (named == "raw" and raw_size) or named in FRAME_FORMATS:
        return Judged(named, None)
    if named is not None:
        return content_first(upload.data, named, FRAME_MAGICS)
    fmt = format_by_content(upload.data, FRAME_MAGICS) or ("raw" if raw_size else None)
    if fmt is not None:
        return Judged(fmt, None)
    raise UnsupportedFormatError(
        "cannot tell the frame's format: send a .png, .tiff or .npy file, or raw codes with "
        f"format=raw, width, height, bits and encoding{_elsewhere(upload.data)}"
    )


def _elsewhere(data: bytes) -> str:
    """What to do with an upload that is a file another route takes ('' otherwise)."""
    other = not_a_frame(data)
    return "" if other is None else f"; this file is {other}"
