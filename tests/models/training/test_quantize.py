"""Tests of models/training/quantize.py: int8 QDQ per-channel model and its card."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from models.training import quantize
from models.training.export import sha256_of
from models.training.quantize import TrainingCrops, quantize_card, quantized_card_path


def test_quantized_model_is_qdq_per_channel_and_runs(exported: tuple[Path, Path]) -> None:
    _, card_path = exported
    quantized_path = quantize_card(card_path, batches=2)
    card = json.loads(quantized_path.read_text())
    model_path = quantized_path.parent / card["file"]
    assert card["decoder"] == "mantissanet-tiny-int8" and card["sha256"] == sha256_of(model_path)
    graph = onnx.load(str(model_path)).graph
    ops = [node.op_type for node in graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    weight_scales = [i for i in graph.initializer if i.name.endswith("_scale") and i.dims]
    assert any(i.dims[0] > 1 for i in weight_scales)
    session = ort.InferenceSession(str(model_path))
    out = session.run(None, {"m": np.random.default_rng(0).random((1, 1, 48, 64), np.float32)})
    assert out[0].shape == (1, 1, 48, 64) and out[0].dtype == np.int64
    assert not list(quantized_path.parent.glob("*.tmp")), "a temporary file was left"


class Killed(BaseException):
    """The process stopped while the quantized model was being written."""


def test_a_quantization_stopped_mid_write_keeps_the_previous_model(
    exported: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The int8 .onnx was written in place: a run stopped part-way left a cut-short
    model under the previous card."""
    _, shipped = exported
    card_path = tmp_path / shipped.name
    shutil.copy(shipped, card_path)
    shutil.copy(shipped.with_suffix(".onnx"), tmp_path)
    target = quantized_card_path(card_path).with_suffix(".onnx")
    target.write_bytes(b"the previous int8 model")

    def stopped_mid_write(source: str, output: str, *args: Any, **kwargs: Any) -> None:
        Path(output).write_bytes(b"the first half of")
        raise Killed

    monkeypatch.setattr(quantize, "quantize_static", stopped_mid_write)
    with pytest.raises(Killed):
        quantize_card(card_path, batches=2)
    assert target.read_bytes() == b"the previous int8 model"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [card_path.name, shipped.with_suffix(".onnx").name, target.name]
    )


def test_calibration_reads_training_crops_then_stops() -> None:
    reader = TrainingCrops("modulo", 2, crop=32)
    first = reader.get_next()
    assert first is not None and first["m"].shape == (1, 1, 32, 32)
    assert reader.get_next() is not None and reader.get_next() is None
