"""Export a trained run to ONNX (dynamic H and W) and write its model card.

The exported graph maps ``m`` (``1 x 1 x H x W`` float32, H and W multiples of the
card's ``multiple``, :func:`models.training.networks.multiple`) to ``winding``
(``1 x 1 x H x W`` int64): the argmax (or the rounded regression) is inside the graph.
An UnModNet run exports one pass, ``(m, winding) -> rollover`` (int64 0/1), that the
runtime repeats. The card (JSON, next to the .onnx) is what the runtime discovers;
:func:`models.decoders.learned.specs` reads it.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from models.decoders.learned import ONNX_DIR
from models.scenes import TRAIN_SCENES
from models.training.checkpoints import checkpoint_segments, load_checkpoint
from models.training.networks import (
    MULTIPLE,
    NUM_CLASSES,
    MantissaNet,
    UnModNet,
    multiple,
    parameter_count,
)
from models.training.train import TrainConfig, build_model

OPSET = 17
TILE = 256
#: UnModNet's default number of unwrapping passes at inference.
MAX_PASSES = 15


class WindingGraph(nn.Module):
    """Inference graph: ``m -> W`` (int64, argmax or rounded regression inside), or for the
    ``jumps`` loss ``m -> jumps`` (float32, 2 channels: to the right and lower neighbour),
    which the runtime integrates into W."""

    def __init__(self, model: MantissaNet, loss: str) -> None:
        super().__init__()
        self.model = model
        self.loss = loss

    def forward(self, m: Tensor) -> Tensor:
        if self.loss not in ("mse", "jumps"):
            return self.model.classes(m)
        logits, _ = self.model(m)
        if self.loss == "mse":
            return logits.round().clamp(0, NUM_CLASSES - 1).long()
        return logits


class RolloverGraph(nn.Module):
    """UnModNet inference pass: ``(m, winding) -> rollover`` (int64 0/1)."""

    def __init__(self, model: UnModNet) -> None:
        super().__init__()
        self.model = model

    def forward(self, m: Tensor, winding: Tensor) -> Tensor:
        logits, _ = self.model(m, winding)
        return (logits > 0).long()


def graph_inputs(module: nn.Module, size: int) -> tuple[Tensor, ...]:
    """Example inputs of an inference graph at ``size x size``."""
    m = torch.rand(1, 1, size, size)
    return (m, torch.zeros_like(m)) if isinstance(module, RolloverGraph) else (m,)


def gflops_at(module: nn.Module, size: int = TILE) -> float:
    """GFLOPs (2 per multiply-add) of one ``size x size`` forward pass."""
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        module(*graph_inputs(module, size))
    return counter.get_total_flops() / 1e9


def export_onnx(module: nn.Module, path: Path) -> None:
    """Export an inference graph with dynamic batch, height and width."""
    path.parent.mkdir(parents=True, exist_ok=True)
    axes = {0: "batch", 2: "height", 3: "width"}
    inputs = graph_inputs(module, 64)
    names = ["m", "winding"][: len(inputs)]
    output = "rollover" if isinstance(module, RolloverGraph) else "winding"
    torch.onnx.export(
        module.eval(),
        inputs,
        str(path),
        input_names=names,
        output_names=[output],
        dynamic_axes={name: axes for name in [*names, output]},
        opset_version=OPSET,
        dynamo=False,
    )


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def trained_model(
    checkpoint: Path,
) -> tuple[MantissaNet | UnModNet, TrainConfig, dict[str, Any]]:
    """The eval-mode model of a checkpoint, its config and the raw checkpoint state."""
    state = load_checkpoint(checkpoint)
    raw = dict(state["config"])
    raw["stage_steps"] = tuple(raw["stage_steps"])
    raw["runs_dir"] = Path(raw["runs_dir"])
    config = TrainConfig(**raw)
    model = build_model(config)
    model.load_state_dict(state["model"])
    return model.eval(), config, state


def training_facts(config: TrainConfig, state: dict[str, Any]) -> dict[str, Any]:
    """The card's ``training`` section: data, steps, wall time, settings."""
    return {
        "scenes": list(TRAIN_SCENES),
        "synthetic_fraction": 0.5,
        "steps": state["step"],
        "planned_stage_steps": list(config.stage_steps),
        "wall_s": round(state["wall_s"], 1),
        "crop": config.crop,
        "batch": config.batch,
        "loss": config.loss,
        **({"risk_weight": config.risk_weight} if config.loss == "ce-risk" else {}),
        "max_read_noise": config.max_read_noise,
        **({"glow_fraction": config.glow_fraction} if config.glow_fraction else {}),
        **(
            {"own_states": config.own_states, "own_passes": config.own_passes}
            if config.family == "unmodnet"
            else {}
        ),
        "init_from": config.init_from,
        "seed": config.seed,
        "threads": config.threads,
        "large_crop": config.large_crop,
        "precision": config.precision,
        "segments": checkpoint_segments(state),
        "alpha": 2.0,
        "bits": 8,
    }


def add_val256(card_path: Path, read_noises: tuple[float, ...] = (0.0, 0.01)) -> dict[str, Any]:
    """Measure the card's model on val-256 (onnxruntime) and store the means in the card:
    ``val256`` per read noise and, for winding nets, ``val256_refined``: the same at no
    read noise after guided PUMA to convergence (``<decoder>+puma``, what ``auto`` at
    ``best`` runs)."""
    from models.decoders.guided_puma import GuidedPumaDecoder
    from models.decoders.learned import LearnedDecoder, load_cards
    from models.training.validate import val256_metrics

    card = json.loads(card_path.read_text())
    cards = [c for c in load_cards(card_path.parent) if c["file"] == card["file"]]
    decoder = LearnedDecoder(card["decoder"], cards)
    card["val256"] = {
        f"read_noise_{noise:g}": val256_metrics(decoder, card["encoding"], noise)
        for noise in read_noises
    }
    if card["family"] == "mantissanet":
        refined = GuidedPumaDecoder(decoder)
        card["val256_refined"] = {"read_noise_0": val256_metrics(refined, card["encoding"])}
    card_path.write_text(json.dumps(card, indent=2) + "\n")
    return card


def export_run(checkpoint: Path, onnx_dir: Path = ONNX_DIR) -> Path:
    """Export a run's checkpoint to ``<onnx_dir>/<name>.onnx`` and write the card; returns it."""
    model, config, state = trained_model(checkpoint)
    unmodnet = isinstance(model, UnModNet)
    graph = RolloverGraph(model) if unmodnet else WindingGraph(model, config.loss)
    onnx_path = onnx_dir / f"{config.name}.onnx"
    export_onnx(graph, onnx_path)
    card = {
        "name": config.name,
        "decoder": config.decoder,
        "family": config.family,
        "tier": config.tier,
        "encoding": config.encoding,
        "noise_aware": config.max_read_noise > 0,
        "file": onnx_path.name,
        "sha256": sha256_of(onnx_path),
        "output": "jumps" if config.loss == "jumps" else "winding",
        "multiple": MULTIPLE if unmodnet else multiple(model.tier),
        "tile": TILE,
        "parameters": parameter_count(model),
        "gflops_256": round(gflops_at(graph), 3),
        **({"max_passes": MAX_PASSES, "gflops_per": "pass"} if unmodnet else {}),
        "training": training_facts(config, state),
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    card_path = onnx_path.with_suffix(".json")
    card_path.write_text(json.dumps(card, indent=2) + "\n")
    return card_path
