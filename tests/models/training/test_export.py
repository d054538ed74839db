"""Tests of models/training/export.py: ONNX matches PyTorch; the card is complete."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch
from torch import nn

from models.decoders.learned import ModelFileError, load_cards, onnx_model
from models.errors import InvalidInputError
from models.formation import dequantize
from models.scenes import val256_frames
from models.training.checkpoints import load_checkpoint, save_checkpoint
from models.training.config import TrainConfig
from models.training.export import (
    ExportMismatchError,
    RolloverGraph,
    WindingGraph,
    add_val256,
    card_is_current,
    check_onnx,
    export_run,
    sha256_of,
    trained_model,
    training_facts,
)
from models.training.losses import rolled_out_state
from models.training.train import train


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


class Shifted(nn.Module):
    """An inference graph whose W is one more than another's."""

    def __init__(self, graph: nn.Module) -> None:
        super().__init__()
        self.graph = graph

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        return self.graph(m) + 1


def test_an_onnx_graph_that_disagrees_with_pytorch_is_refused(
    exported: tuple[Path, Path],
) -> None:
    checkpoint, card_path = exported
    model, config, _ = trained_model(checkpoint)
    graph = WindingGraph(model, config.loss).eval()
    check_onnx(graph, card_path.with_suffix(".onnx"), 16)
    with pytest.raises(ExportMismatchError, match="on a 48x80 input: 0.00% of the outputs equal"):
        check_onnx(Shifted(graph), card_path.with_suffix(".onnx"), 16)


def tiny_run(runs: Path, loss: str = "ce") -> Path:
    """The checkpoint of a 3-step tiny mantissa run."""
    return train(TrainConfig(tier="tiny", loss=loss, stage_steps=(1, 1, 1), crop=32, batch=2,
                             runs_dir=runs))  # fmt: skip


def test_an_export_replaces_a_model_only_when_forced(tmp_path: Path) -> None:
    checkpoint, onnx_dir = tiny_run(tmp_path / "runs"), tmp_path / "onnx"
    card_path = export_run(checkpoint, onnx_dir)
    before = card_path.read_bytes()
    with pytest.raises(InvalidInputError, match="exists .* pass --force to replace it"):
        export_run(checkpoint, onnx_dir)
    assert card_path.read_bytes() == before
    assert export_run(checkpoint, onnx_dir, force=True) == card_path
    assert sorted(path.name for path in onnx_dir.iterdir()) == [
        "mantissanet-tiny-mantissa.json", "mantissanet-tiny-mantissa.onnx",
    ]  # fmt: skip


def test_a_second_model_of_a_decoder_and_encoding_supersedes_the_first_only_when_forced(
    tmp_path: Path,
) -> None:
    """ce and ce-risk runs both make mantissanet-tiny on mantissa frames: the runtime takes
    one, so the second export is refused, and forced it removes the first."""
    onnx_dir = tmp_path / "onnx"
    first = export_run(tiny_run(tmp_path / "runs", "ce-risk"), onnx_dir)
    checkpoint = tiny_run(tmp_path / "runs")
    with pytest.raises(InvalidInputError, match="already serves decoder 'mantissanet-t") as caught:
        export_run(checkpoint, onnx_dir)
    assert str(first) in caught.value.message and "--force" in caught.value.message
    card = json.loads(export_run(checkpoint, onnx_dir, force=True).read_text())
    assert card["supersedes"] == ["mantissanet-tiny-ce-risk-mantissa.onnx"]
    assert [c["name"] for c in load_cards(onnx_dir)] == ["mantissanet-tiny-mantissa"]
    assert not first.exists() and not first.with_suffix(".onnx").exists()


def test_a_card_is_current_until_its_run_is_trained_again(tmp_path: Path) -> None:
    checkpoint = tiny_run(tmp_path / "runs")
    card_path = export_run(checkpoint, tmp_path / "onnx")
    card = json.loads(card_path.read_text())
    assert card["training"]["checkpoint_sha256"] == sha256_of(checkpoint)
    assert card_is_current(card_path, checkpoint)
    shutil.rmtree(checkpoint.parent)
    assert not card_is_current(card_path, tiny_run(tmp_path / "runs"))


def test_an_export_stopped_before_its_card_leaves_the_old_model_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A re-export interrupted (Ctrl-C) while its card is made: the old .onnx and its card
    stay together (the new file had replaced the old one under the old card), and no
    temp file is left."""
    checkpoint, onnx_dir = tiny_run(tmp_path / "runs"), tmp_path / "onnx"
    card_path = export_run(checkpoint, onnx_dir)
    files = {path.name: path.read_bytes() for path in onnx_dir.iterdir()}
    state = load_checkpoint(checkpoint)
    for weights in state["model"].values():
        if weights.is_floating_point():
            weights.add_(0.01)
    retrained = tmp_path / "retrained.pt"
    save_checkpoint(retrained, state)

    def interrupted(*_args: object) -> float:
        raise KeyboardInterrupt

    monkeypatch.setattr("models.training.export.gflops_at", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_run(retrained, onnx_dir, force=True)
    assert {path.name: path.read_bytes() for path in onnx_dir.iterdir()} == files
    card = json.loads(card_path.read_text())
    assert card["sha256"] == sha256_of(onnx_dir / card["file"])


def test_the_card_records_every_share_that_changed_the_training_data(tmp_path: Path) -> None:
    """A colour-trained run's card said nothing of its colour crops."""
    config = TrainConfig(tier="tiny", colour_fraction=0.5, glow_fraction=0.25, runs_dir=tmp_path)
    facts = training_facts(config, {"step": 0, "wall_s": 0.0, "segments": []}, "0" * 64)
    assert facts["colour_fraction"] == 0.5 and facts["glow_fraction"] == 0.25
    plain = training_facts(
        TrainConfig(runs_dir=tmp_path), {"step": 0, "wall_s": 0.0, "segments": []}, "0" * 64
    )
    assert "colour_fraction" not in plain and "glow_fraction" not in plain


@pytest.mark.parametrize("damage", ["missing", "cut-short"])
def test_measuring_a_card_without_its_model_file_names_the_file(
    exported: tuple[Path, Path], tmp_path: Path, damage: str
) -> None:
    """Without its .onnx, the card was measured by a decoder with no model at all:
    "decoder 'mantissanet-tiny' has no model for the 'mantissa' encoding; it supports: "."""
    _, card_path = exported
    card = Path(shutil.copy(card_path, tmp_path / card_path.name))
    onnx_path = tmp_path / json.loads(card_path.read_text())["file"]
    if damage == "cut-short":
        onnx_path.write_bytes(card_path.with_suffix(".onnx").read_bytes()[:1000])
    words = "is missing" if damage == "missing" else "cut short"
    with pytest.raises(ModelFileError, match=f"{onnx_path} .*{words}"):
        add_val256(card)


def test_a_damaged_card_is_named_when_checked_for_being_current(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    """``mcam train all`` failed on a damaged card of models/onnx with a bare
    JSONDecodeError traceback (after training every recipe)."""
    checkpoint, _ = exported
    card_path = tmp_path / "mantissanet-tiny-mantissa.json"
    card_path.write_text('{"file": ')
    with pytest.raises(InvalidInputError, match=f"{card_path} is not a model card"):
        card_is_current(card_path, checkpoint)


def test_a_checkpoint_whose_weights_do_not_fit_its_net_is_not_exported(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    """It failed in load_state_dict with PyTorch's 'size mismatch' traceback."""
    state = load_checkpoint(exported[0])
    layer = next(iter(state["model"]))
    state["model"][layer] = torch.zeros(3)
    checkpoint = tmp_path / "checkpoint.pt"
    torch.save(state, checkpoint)
    with pytest.raises(InvalidInputError, match=f"weights do not fit .*size mismatch for {layer}"):
        export_run(checkpoint, tmp_path / "onnx")
    assert not (tmp_path / "onnx").exists()


def test_a_checkpoint_with_settings_since_removed_exports_or_says_why(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    """Checkpoints of the ce-psnr era hold psnr_share, whatever their loss: exporting one
    failed with "TrainConfig.__init__() got an unexpected keyword argument 'psnr_share'"
    in a traceback. A ce run exports; a ce-psnr one (a loss since removed) says why not."""
    state = load_checkpoint(exported[0])
    state["config"] = {**state["config"], "psnr_share": 0.5}
    checkpoint = tmp_path / "checkpoint.pt"
    torch.save(state, checkpoint)
    card = json.loads(export_run(checkpoint, tmp_path / "onnx").read_text())
    assert card["training"]["loss"] == "ce" and "psnr_share" not in card["training"]
    state["config"]["loss"] = "ce-psnr"
    torch.save(state, checkpoint)
    with pytest.raises(InvalidInputError, match="another version .*got loss 'ce-psnr'"):
        export_run(checkpoint, tmp_path / "other")
