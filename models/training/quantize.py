"""Int8 static quantization (QDQ, per-channel weights) of an exported winding model.

Activations are calibrated (min-max) on training crops from the same on-the-fly
sampler as training, never on validation scenes. The quantized model gets its
own card (decoder ``<decoder>-int8``) next to the float one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_static,
)
from onnxruntime.quantization.shape_inference import quant_pre_process

from models.training.checkpoints import replace_durably
from models.training.data import PairConfig, sample_batch
from models.training.export import sha256_of, write_card

CALIBRATION_SEED = 7
CALIBRATION_CROP = 128


class TrainingCrops(CalibrationDataReader):
    """``batches`` single training crops of ``encoding`` as ``{"m": 1 x 1 x H x W}``."""

    def __init__(self, encoding: str, batches: int, crop: int = CALIBRATION_CROP) -> None:
        config = PairConfig(encoding, crop=crop, batch=1)
        self.items = iter(
            [{"m": sample_batch(CALIBRATION_SEED, i, config)[0]} for i in range(batches)]
        )

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self.items, None)


def quantized_card_path(card_path: Path) -> Path:
    """Where :func:`quantize_card` writes the int8 card of ``card_path``: its name with
    ``<decoder>-int8`` for the decoder."""
    card = json.loads(card_path.read_text())
    stem = Path(card["file"]).stem.replace(card["decoder"], card["decoder"] + "-int8")
    return card_path.with_name(f"{stem}.json")


def quantize_card(card_path: Path, batches: int = 32) -> Path:
    """Quantize the model of ``card_path``; write ``<name>-int8.onnx`` and its card.

    The model is written to a temporary file renamed over ``<name>-int8.onnx`` once
    whole (:func:`models.training.checkpoints.replace_durably`): a run stopped part-way
    leaves the previous int8 model, never a part of the new one."""
    card: dict[str, Any] = json.loads(card_path.read_text())
    source = card_path.parent / card["file"]
    prepared = source.with_name(source.stem + ".prep.onnx")
    target = quantized_card_path(card_path).with_suffix(".onnx")
    tmp = target.with_name(target.name + ".tmp")
    quant_pre_process(str(source), str(prepared), skip_symbolic_shape=True)
    try:
        quantize_static(
            str(prepared),
            str(tmp),
            TrainingCrops(card["encoding"], batches),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            calibrate_method=CalibrationMethod.MinMax,
        )
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        prepared.unlink(missing_ok=True)
    quantized = {
        **{k: v for k, v in card.items() if k not in ("val256", "val256_refined")},
        "name": target.stem,
        "decoder": card["decoder"] + "-int8",
        "tier": card["tier"] + "-int8",
        "file": target.name,
        "sha256": sha256_of(tmp),
        "quantization": {
            "format": "QDQ",
            "weights": "int8 per-channel",
            "activations": "uint8 per-tensor, min-max calibrated",
            "calibration": f"{batches} training crops of {CALIBRATION_CROP} px",
            "source": card["file"],
        },
    }
    replace_durably(tmp, target)
    quantized_card = target.with_suffix(".json")
    write_card(quantized_card, quantized)
    return quantized_card
