"""``GET /v1/decoders``: the installed decoders with their speed/accuracy figures."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel

from models.decoders.registry import available_decoders
from service.api.deps import ReadKey, SettingsDep
from service.api.schemas import AUTH_ERRORS

router = APIRouter(prefix="/v1", tags=["decoders"])


class DecoderInfo(BaseModel):
    """A selectable decoder; ``figures`` come from its model card or the benchmark."""

    name: str
    kind: str
    description: str
    figures: dict[str, Any]
    default: bool


@router.get(
    "/decoders",
    response_model=list[DecoderInfo],
    responses=AUTH_ERRORS,
    summary="The decoders this installation can run",
)
def list_decoders(settings: SettingsDep, _: ReadKey) -> list[DecoderInfo]:
    """Every decoder in registration order; ``default`` marks the one used when none is named."""
    return [
        DecoderInfo(
            name=spec.name,
            kind=spec.kind,
            description=spec.description,
            figures=spec.figures,
            default=spec.name == settings.default_decoder,
        )
        for spec in available_decoders()
    ]
