"""``GET /v1/decoders``: the installed decoders with their measured figures and their source,
and the default decoder where it is a parametrized name (``auto-40ms``) the list lacks."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, Field

from models.decoders.measured import ACCURACY_REPORT, benchmark_figures, measured_figures
from models.decoders.registry import DecoderSpec, available_decoders, resolve
from service.api.deps import ReadKey, SettingsDep
from service.api.schemas import AUTH_ERRORS

router = APIRouter(prefix="/v1", tags=["decoders"])


class DecoderInfo(BaseModel):
    """A selectable decoder, with the figures measured for it and where they come from."""

    name: str
    kind: str
    description: str
    figures: dict[str, Any] = Field(
        description="per encoding: {'val256': {'read_noise_<sigma>': {winding_accuracy, "
        "psnr, pu21_psnr (dB), ssim, ms_ssim, ms_per_frame}}}, measured on the val-256 "
        "frames (256x256, overexposed 0.2, max_wraps 16, 8 bits); learned decoders add "
        "parameters, gflops_256 and val256_refined (with +puma). Empty when none are "
        "measured: figures_source says why and where to find them"
    )
    figures_source: str = Field(
        description="where the figures come from (model cards, or the val-256 benchmark's "
        "report with its date, machine and commit), or why there are none"
    )
    default: bool


def listed_specs(default: str) -> list[DecoderSpec]:
    """Every installed decoder in registration order, then ``default`` when it is a
    parametrized name (``auto-40ms``, ``itoh+puma4``) none of them has: a client that
    offers the listed names, preselecting the default, would otherwise send another."""
    specs = available_decoders()
    if all(spec.name != default for spec in specs):
        specs = [*specs, resolve(default)]
    return specs


@router.get(
    "/decoders",
    response_model=list[DecoderInfo],
    responses=AUTH_ERRORS,
    summary="The decoders this installation can run",
)
def list_decoders(settings: SettingsDep, _: ReadKey) -> list[DecoderInfo]:
    """Every decoder in registration order; ``default`` marks the one used when none is named
    (listed last when it is a parametrized name)."""
    bench = benchmark_figures(settings.accuracy_report or ACCURACY_REPORT)
    found = []
    for spec in listed_specs(settings.default_decoder):
        figures, source = measured_figures(spec, bench)
        found.append(
            DecoderInfo(
                name=spec.name,
                kind=spec.kind,
                description=spec.description,
                figures=figures,
                figures_source=source,
                default=spec.name == settings.default_decoder,
            )
        )
    return found
