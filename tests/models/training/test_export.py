"""Tests of models/training/export.py: ONNX matches PyTorch; the card is complete."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from models.decoders.learned import onnx_model
from models.formation import dequantize
from models.scenes import val256_frames
from models.training.export import (
    RolloverGraph,
    WindingGraph,
    export_run,
    sha256_of,
    trained_model,
)
from models.training.losses import rolled_out_state
from models.training.train import TrainConfig, train


def torch_winding(checkpoint: Path, m: np.ndarray) -> np.ndarray:
    model, config, _ = trained_model(checkpoint)
    with torch.no_grad():
        return WindingGraph(model, config.loss)(torch.from_numpy(m)).numpy()


def test_card_describes_the_file(exported: tuple[Path, Path]) -> None:
    _, card_path = exported
    card = json.loads(card_path.read_text())
    onnx_path = card_path.parent / card["file"]
    assert card["sha256"] == sha256_of(onnx_path)
    assert card["decoder"] == "mantissanet-tiny" and card["encoding"] == "mantissa"
    assert card["parameters"] > 1000 and card["gflops_256"] > 0
    assert card["training"]["steps"] == 3 and "forest" not in card["training"]["scenes"]
    (segment,) = card["training"]["segments"]
    assert segment["steps"] == [0, 3] and segment["device"] == "cpu"


@pytest.mark.parametrize("source", ["random", "real"])
def test_onnxruntime_agrees_with_pytorch(exported: tuple[Path, Path], source: str) -> None:
    checkpoint, card_path = exported
    if source == "random":
        m = np.random.default_rng(0).random((1, 1, 48, 80), dtype=np.float32)
    else:
        frame = val256_frames("mantissa")[0]
        m = dequantize(frame.codes, 8).astype(np.float32)[None, None, :128, :96]
    session = ort.InferenceSession(str(card_path.with_suffix(".onnx")))
    onnx_w = session.run(None, {"m": m})[0]
    assert onnx_w.shape == m.shape and onnx_w.dtype == np.int64
    assert (onnx_w == torch_winding(checkpoint, m)).mean() > 0.999


def test_unmodnet_exports_one_rollover_pass_matching_pytorch(tmp_path: Path) -> None:
    config = TrainConfig(
        family="unmodnet", tier="tiny", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path
    )
    card_path = export_run(train(config), tmp_path / "onnx")
    card = json.loads(card_path.read_text())
    assert card["decoder"] == "unmodnet" and card["max_passes"] == 15
    m = np.random.default_rng(2).random((1, 1, 32, 48), dtype=np.float32)
    winding = np.ones_like(m)
    session = ort.InferenceSession(str(card_path.with_suffix(".onnx")))
    onnx_out = session.run(None, {"m": m, "winding": winding})[0]
    model, _, _ = trained_model(tmp_path / config.name / "checkpoint.pt")
    with torch.no_grad():
        torch_out = RolloverGraph(model)(torch.from_numpy(m), torch.from_numpy(winding)).numpy()
    assert onnx_out.shape == m.shape and set(np.unique(onnx_out)) <= {0, 1}
    assert (onnx_out == torch_out).mean() > 0.999


def test_the_iterative_runtime_rolls_like_the_trained_model(tmp_path: Path) -> None:
    """The runtime's passes (each inside the previous pass's rollovers) reach the state
    that training rolls out with the same model: ONNX and PyTorch agree on W."""
    config = TrainConfig(
        family="unmodnet", tier="tiny", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path
    )
    card = json.loads(export_run(train(config), tmp_path / "onnx").read_text())
    card["path"] = str(tmp_path / "onnx" / card["file"])
    m = np.random.default_rng(3).random((32, 48))
    runtime = onnx_model(card)
    model, _, _ = trained_model(tmp_path / config.name / "checkpoint.pt")
    m_torch = torch.from_numpy(m.astype(np.float32))[None, None]
    for passes in (1, 2, 5):
        runtime.card["max_passes"] = passes
        with torch.no_grad():
            expected = rolled_out_state(model, m_torch, model.edge(m_torch), passes)
        np.testing.assert_array_equal(runtime.run(m), expected[0, 0].numpy().astype(np.int64))


def test_half_resolution_tier_exports_its_multiple_and_decodes_any_size(tmp_path: Path) -> None:
    config = TrainConfig(
        tier="small-s2d", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path
    )
    checkpoint = train(config)
    card_path = export_run(checkpoint, tmp_path / "onnx")
    card = json.loads(card_path.read_text())
    assert card["decoder"] == "mantissanet-small-s2d" and card["multiple"] == 32
    m = np.random.default_rng(3).random((1, 1, 64, 96), dtype=np.float32)
    session = ort.InferenceSession(str(card_path.with_suffix(".onnx")))
    assert (session.run(None, {"m": m})[0] == torch_winding(checkpoint, m)).mean() > 0.999
    model = onnx_model({**card, "path": str(card_path.with_suffix(".onnx"))})
    assert model.predict(m[0, 0, :50, :70].astype(np.float64)).shape == (50, 70)


def test_jumps_model_exports_jumps_that_the_runtime_integrates(tmp_path: Path) -> None:
    config = TrainConfig(
        tier="tiny", loss="jumps", stage_steps=(1, 1, 1), crop=32, batch=2, runs_dir=tmp_path
    )
    card_path = export_run(train(config), tmp_path / "onnx")
    card = json.loads(card_path.read_text())
    assert card["output"] == "jumps" and card["decoder"] == "mantissanet-tiny"
    assert card["training"]["loss"] == "jumps"
    m = np.random.default_rng(3).random((1, 1, 48, 64), dtype=np.float32)
    session = ort.InferenceSession(str(card_path.with_suffix(".onnx")))
    jumps = session.run(None, {"m": m})[0]
    assert jumps.shape == (1, 2, 48, 64) and jumps.dtype == np.float32
    np.testing.assert_allclose(jumps, torch_winding(tmp_path / config.name / "checkpoint.pt", m),
                               atol=1e-4)  # fmt: skip
    card["path"] = str(card_path.with_suffix(".onnx"))
    winding = onnx_model(card).run(m[0, 0].astype(np.float64))
    assert winding.shape == (48, 64) and winding.dtype == np.int64 and winding.min() == 0
