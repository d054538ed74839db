"""Export a trained run to ONNX (dynamic H and W) and write its model card.

The exported graph maps ``m`` (``1 x 1 x H x W`` float32, H and W multiples of the
card's ``multiple``, :func:`models.training.networks.multiple`) to ``winding``
(``1 x 1 x H x W`` int64): the argmax (or the rounded regression) is inside the graph.
An UnModNet run exports one pass, ``(m, winding) -> rollover`` (int64 0/1), that the
runtime repeats. The card (JSON, next to the .onnx) is what the runtime discovers;
:func:`models.decoders.learned.specs` reads it.

Before a model is written, onnxruntime runs the graph against PyTorch on two non-square
inputs (:func:`check_onnx`). An export does not replace an existing model, or add a
second model of a (decoder, encoding) another card serves, unless forced
(:func:`export_run`). The card records the sha256 of the checkpoint it was exported
from, so that ``mcam train all`` skips runs whose card is up to date
(:func:`card_is_current`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import torch
from numpy.typing import NDArray
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from models.decoders.learned import ONNX_DIR, read_card, read_cards, sha256_of
from models.errors import InvalidInputError, McamError
from models.scenes import TRAIN_SCENES
from models.training.checkpoints import checkpoint_segments, load_checkpoint, load_weights
from models.training.config import TrainConfig, saved_config
from models.training.networks import (
    MULTIPLE,
    NUM_CLASSES,
    MantissaNet,
    UnModNet,
    multiple,
    parameter_count,
)
from models.training.train import build_model

OPSET = 17
TILE = 256
#: UnModNet's default number of unwrapping passes at inference.
MAX_PASSES = 15
#: Input sizes of the export check, in multiples of the net's multiple (48 x 80 and
#: 80 x 48 px for a multiple of 16): non-square both ways, so that swapped axes show.
CHECK_SHAPES = ((3, 5), (5, 3))
#: The share of output pixels on which onnxruntime must agree with PyTorch, as the export
#: tests compare W: a few argmax ties may fall either way in float32.
AGREEMENT = 0.999
#: Per-neighbour jumps (float outputs, in wraps) agree within this, as the tests compare.
JUMPS_TOLERANCE = 1e-4


class ExportMismatchError(McamError):
    """An exported ONNX graph does not compute what the PyTorch model does."""

    code = "export_mismatch"


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


def check_inputs(
    module: nn.Module, shape: tuple[int, int], rng: np.random.Generator
) -> tuple[NDArray[np.float32], ...]:
    """Random inputs of an inference graph at ``shape`` (H, W): ``m`` in [0, 1), and for
    a rollover pass a W of 0 to 3."""
    m = rng.random((1, 1, *shape), dtype=np.float32)
    if isinstance(module, RolloverGraph):
        return m, rng.integers(0, 4, m.shape).astype(np.float32)
    return (m,)


def output_agreement(
    module: nn.Module, session: ort.InferenceSession, inputs: tuple[NDArray[np.float32], ...]
) -> float:
    """The share of output values on which ``session`` and ``module`` agree (equal, or
    within :data:`JUMPS_TOLERANCE` for float outputs); 0 when their shapes differ."""
    feeds = {item.name: value for item, value in zip(session.get_inputs(), inputs, strict=True)}
    onnx_out = session.run(None, feeds)[0]
    with torch.no_grad():
        torch_out = module(*(torch.from_numpy(value) for value in inputs)).numpy()
    if onnx_out.shape != torch_out.shape:
        return 0.0
    if np.issubdtype(torch_out.dtype, np.floating):
        return float(np.mean(np.abs(onnx_out - torch_out) <= JUMPS_TOLERANCE))
    return float(np.mean(onnx_out == torch_out))


def check_onnx(module: nn.Module, onnx_path: Path, multiple: int) -> None:
    """Run ``onnx_path`` in onnxruntime against ``module`` (eval mode) on random inputs
    of :data:`CHECK_SHAPES`; an ExportMismatchError when they agree on less than
    :data:`AGREEMENT` of the outputs."""
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    for rows, cols in CHECK_SHAPES:
        shape = (rows * multiple, cols * multiple)
        agreement = output_agreement(module, session, check_inputs(module, shape, rng))
        if agreement < AGREEMENT:
            raise ExportMismatchError(
                f"the ONNX export {onnx_path.name} disagrees with the PyTorch model on a "
                f"{shape[0]}x{shape[1]} input: {agreement:.2%} of the outputs equal, "
                f"{AGREEMENT:.1%} needed; nothing was exported. Check that torch "
                f"({torch.__version__}) and onnxruntime ({ort.__version__}) are the "
                "versions of constraints.txt"
            )


def trained_model(
    checkpoint: Path,
) -> tuple[MantissaNet | UnModNet, TrainConfig, dict[str, Any]]:
    """The eval-mode model of a checkpoint, its config and the raw checkpoint state."""
    state = load_checkpoint(checkpoint)
    config = saved_config(state["config"], checkpoint)
    model = build_model(config)
    load_weights(model, state["model"], checkpoint)
    return model.eval(), config, state


def training_facts(
    config: TrainConfig, state: dict[str, Any], checkpoint_sha256: str
) -> dict[str, Any]:
    """The card's ``training`` section: data, steps, wall time, settings, and the sha256
    of the checkpoint file exported."""
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
        **({"colour_fraction": config.colour_fraction} if config.colour_fraction else {}),
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
        "checkpoint_sha256": checkpoint_sha256,
    }


def add_val256(card_path: Path, read_noises: tuple[float, ...] = (0.0, 0.01)) -> dict[str, Any]:
    """Measure the card's model on val-256 (onnxruntime) and store the means in the card:
    ``val256`` per read noise and, for winding nets, ``val256_refined``: the same at no
    read noise after guided PUMA to convergence (``<decoder>+puma``, what ``auto`` at
    ``best`` runs). A model file that is missing or not the card's is a
    :class:`models.decoders.learned.ModelFileError` naming it."""
    from models.decoders.guided_puma import GuidedPumaDecoder
    from models.decoders.learned import LearnedDecoder
    from models.training.validate import val256_metrics

    card = read_card(card_path)
    model = {**card, "path": str(card_path.parent / card["file"])}
    decoder = LearnedDecoder(card["decoder"], [model])
    card["val256"] = {
        f"read_noise_{noise:g}": val256_metrics(decoder, card["encoding"], noise)
        for noise in read_noises
    }
    if card.get("family") == "mantissanet":
        refined = GuidedPumaDecoder(decoder)
        card["val256_refined"] = {"read_noise_0": val256_metrics(refined, card["encoding"])}
    write_card(card_path, card)
    return card


def write_card(path: Path, card: dict[str, Any]) -> None:
    """Write a model card atomically (a temporary file renamed over it)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(card, indent=2) + "\n")
    tmp.replace(path)


def superseded_cards(onnx_dir: Path, config: TrainConfig, force: bool) -> list[Path]:
    """The cards of ``onnx_dir`` other than the run's own that serve its (decoder,
    encoding), which its export replaces. Unless ``force``, an InvalidInputError when
    there is one, or when the run's .onnx or card exists."""
    own = onnx_dir / f"{config.name}.json"
    others = [
        path
        for path, card in read_cards(onnx_dir)
        if path != own and (card["decoder"], card["encoding"]) == (config.decoder, config.encoding)
    ]
    if force:
        return others
    for existing in (own.with_suffix(".onnx"), own):
        if existing.exists():
            raise InvalidInputError(
                f"{existing} exists (a shipped model or an earlier export): pass --force to "
                "replace it, or export to another --onnx-dir"
            )
    if others:
        raise InvalidInputError(
            f"{others[0]} already serves decoder {config.decoder!r} on {config.encoding} "
            f"frames, and the runtime takes one model for each: pass --force to replace it "
            "(its card and .onnx are removed), or export to another --onnx-dir"
        )
    return others


def remove_card(card_path: Path, keep: Path) -> str:
    """Remove a model card, then its .onnx unless that is ``keep``; returns the file name."""
    name = json.loads(card_path.read_text())["file"]
    card_path.unlink()
    if card_path.parent / name != keep:
        (card_path.parent / name).unlink(missing_ok=True)
    return name


def card_is_current(card_path: Path, checkpoint: Path) -> bool:
    """Whether ``card_path`` exists, was exported from ``checkpoint`` as it is now (the
    sha256 in its ``training``), and its .onnx is the file it describes. A file there that
    is not a model card is an InvalidInputError naming it (:func:`read_card`)."""
    if not card_path.exists():
        return False
    card = read_card(card_path)
    onnx_path = card_path.parent / card["file"]
    return (
        card.get("training", {}).get("checkpoint_sha256") == sha256_of(checkpoint)
        and onnx_path.exists()
        and sha256_of(onnx_path) == card["sha256"]
    )


def export_run(checkpoint: Path, onnx_dir: Path = ONNX_DIR, force: bool = False) -> Path:
    """Export a run's checkpoint to ``<onnx_dir>/<name>.onnx`` and write the card; returns it.

    The graph is checked against PyTorch first (:func:`check_onnx`); nothing is written
    in ``onnx_dir`` when they disagree. An existing .onnx or card of the run, or another
    card serving the run's (decoder, encoding), is refused unless ``force``: then they
    are replaced (the other card and its .onnx removed; the card's ``supersedes`` names
    them)."""
    model, config, state = trained_model(checkpoint)
    superseded = superseded_cards(onnx_dir, config, force)
    unmodnet = isinstance(model, UnModNet)
    graph = RolloverGraph(model) if unmodnet else WindingGraph(model, config.loss)
    onnx_path = onnx_dir / f"{config.name}.onnx"
    tmp = onnx_path.with_name(onnx_path.name + ".tmp")
    try:
        export_onnx(graph, tmp)
        check_onnx(graph, tmp, MULTIPLE if unmodnet else multiple(model.tier))
        # The whole card first, from the new file: an export stopped before the end
        # leaves the old .onnx and its card together.
        card = {
            "name": config.name,
            "decoder": config.decoder,
            "family": config.family,
            "tier": config.tier,
            "encoding": config.encoding,
            "noise_aware": config.max_read_noise > 0,
            "file": onnx_path.name,
            "sha256": sha256_of(tmp),
            "output": "jumps" if config.loss == "jumps" else "winding",
            "multiple": MULTIPLE if unmodnet else multiple(model.tier),
            "tile": TILE,
            "parameters": parameter_count(model),
            "gflops_256": round(gflops_at(graph), 3),
            **({"max_passes": MAX_PASSES, "gflops_per": "pass"} if unmodnet else {}),
            "training": training_facts(config, state, sha256_of(checkpoint)),
            "exported_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    replaced = [remove_card(path, keep=onnx_path) for path in superseded]
    if replaced:
        card["supersedes"] = replaced
    tmp.replace(onnx_path)
    card_path = onnx_path.with_suffix(".json")
    write_card(card_path, card)
    return card_path
