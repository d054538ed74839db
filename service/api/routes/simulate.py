"""``POST /v1/simulate``: an HDR image (EXR or .hdr) -> its wrapped frame, synchronously."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from models.exposure import check_not_black
from models.formation import SensorParams, simulate
from models.frames import encode_frame
from models.hdr_io import read_hdr
from models.winding_files import encode_winding_file
from service.api.deps import StateDep, SubmitKey
from service.api.downloads import MEDIA_TYPES, download
from service.api.in_turn import decode_in_turn
from service.api.schemas import CANNOT_HOLD, SIMULATE_ERRORS, upload_body
from service.api.uploads import SimulateFields, Upload, read_upload_fields
from service.core.config import Settings

router = APIRouter(prefix="/v1", tags=["simulate"])

PARAMS_HEADER = "X-Mcam-Params"
#: How many negative scene values ``clip_negative`` set to 0 (lossy EXR leaves some).
CLIPPED_HEADER = "X-Mcam-Clipped-Negative"


def simulate_upload(upload: Upload, fields: SimulateFields, settings: Settings) -> Response:
    """Expose and encode the uploaded image; answer with the frame (or W) file."""
    image = read_hdr(
        upload.data,
        clip_negative=fields.clip_negative,
        max_pixels=settings.max_pixels,
        name="the uploaded HDR image",
    )
    params = SensorParams.parse(
        {k: v for k, v in fields.sensor_overrides().items() if v is not None}
    )
    frame = simulate(image.pixels, params, overexposed=fields.overexposed, gray=fields.gray)
    check_not_black(frame)
    fmt = fields.format or ("tiff" if frame.codes.ndim == 3 else "png")  # PNG frames are grey
    if fields.part == "winding":
        content = encode_winding_file(frame.winding, fmt)
    else:
        content = encode_frame(frame.codes, frame.params, fmt)
    stem = "winding" if fields.part == "winding" else "frame"
    headers = {
        PARAMS_HEADER: frame.params.model_dump_json(),
        CLIPPED_HEADER: str(image.negatives_clipped),
    }
    return download(content, fmt, stem, headers)


@router.post(
    "/simulate",
    summary="Simulate a wrapping sensor: HDR image in, wrapped frame out",
    response_class=Response,
    responses={
        200: {
            "description": "the wrapped frame (codes in DN, parameters embedded in PNG/TIFF) or W; "
            f"the parameters used (with the gain) are in the {PARAMS_HEADER} header, the "
            f"count of negative scene values set to 0 in {CLIPPED_HEADER}",
            "content": {MEDIA_TYPES[fmt]: {} for fmt in ("png", "tiff", "npy")},
            "headers": {
                PARAMS_HEADER: {
                    "description": "the sensor parameters used, with the gain (JSON)",
                    "schema": {"type": "string"},
                },
                CLIPPED_HEADER: {
                    "description": "how many negative scene values (samples: pixels x "
                    "channels) clip_negative set to 0, as mcam simulate --clip-negative "
                    "prints; 0 when none were or clip_negative is false",
                    "schema": {"type": "integer", "minimum": 0},
                },
            },
        },
        **SIMULATE_ERRORS,
        422: CANNOT_HOLD,
    },
    openapi_extra=upload_body(SimulateFields, "an OpenEXR or Radiance .hdr image"),
)
async def post_simulate(
    request: Request,
    query: Annotated[SimulateFields, Query()],
    state: StateDep,
    _: SubmitKey,
) -> Response:
    """Encode an HDR image with the given sensor parameters (form fields or query)."""
    upload, fields = await read_upload_fields(request, SimulateFields, query)
    return await decode_in_turn(state, simulate_upload, upload, fields, state.settings)
