"""Seeded, resumable CPU training of the MantissaCam nets in the paper's three stages.

Stage 1 trains the edge net alone (BCE against the true wrap edges); stage 2 the
winding net on the true edges; stage 3 both end to end (winding loss + 0.1 edge
BCE); an optional stage 4 continues end to end on larger crops (``large_crop``,
a quarter of the batch) so the net sees the context of a full frame. Batches depend
only on ``(seed, step)``; a checkpoint is written every
``checkpoint_every`` steps under ``runs/<name>/`` and a restarted run resumes from
it. Losses go to ``runs/<name>/log.jsonl``.

A run may start from another run's trained weights (``init_from``, e.g. a
noise-aware fine-tune of a finished model, or a model trained in two runs); stages
with 0 steps are skipped. ``label`` tells apart runs that would share a name (the
first of two runs of one model).

Training runs on the CPU (``device="cpu"``, the default) or a GPU (``"cuda"``), in
float32 or bf16 autocast (``precision``); ``workers`` processes make the batches ahead
(:func:`models.training.data.batch_stream`), which a GPU needs to be kept busy. None of
these changes which batches a step sees. ``train(..., deadline=...)`` stops at a wall
clock time with a checkpoint (a later call resumes).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.nn import functional as F

from models.errors import InvalidInputError
from models.training.data import Batch, PairConfig, batch_stream
from models.training.networks import NUM_CLASSES, TIERS, MantissaNet, UnModNet, wrap_edges

RUNS_DIR = Path(__file__).resolve().parents[2] / "runs"
#: Winding losses: cross-entropy over W classes, the same plus the expected PSNR loss
#: (``ce-risk``), MSE on W (the paper's), or MSE on the per-neighbour jumps of W
#: (integrated into W at inference).
#: Output channels of the winding head, per loss.
HEAD_OUTPUTS = {"ce": NUM_CLASSES, "ce-risk": NUM_CLASSES, "mse": 1, "jumps": 2}
#: ``ce-risk``: the expected relative MSE of a crop is floored here (60 dB PSNR).
RISK_FLOOR = 1e-6
#: ``ce-risk``: weight of the expected log-MSE term. Measured on the tiny recipe
#: (val-256 mantissa, net alone / refined by guided PUMA): 0.1 -> 22.09 / 23.88 dB,
#: 1.0 -> 21.42 / 23.32 dB, plain ce 21.63 / 23.56 dB.
RISK_WEIGHT = 0.1
LOSSES = tuple(HEAD_OUTPUTS)
FAMILIES = ("mantissanet", "unmodnet")
STAGE_LR = (2e-3, 2e-3, 5e-4, 3e-4)
EDGE_WEIGHT = 0.1
#: ``fp32``: float32 throughout; ``bf16``: bfloat16 autocast (a GPU's fast path).
PRECISIONS = ("fp32", "bf16")


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``stage_steps``: optimizer steps of stages 1, 2, 3 (and 4).

    ``risk_weight`` (``ce-risk`` only): weight of the expected-PSNR term, see
    :func:`winding_loss`. ``own_states`` / ``own_passes`` (``unmodnet`` only): the fraction
    of batches trained from the model's own state after up to that many passes, see
    :func:`rollover_losses`. ``label``: a tag in the run name (``-<label>`` before the
    encoding), for a run that is a step towards another rather than a model.
    ``device``, ``precision`` and ``workers``: where and how the steps run (see the module
    docstring).
    """

    family: str = "mantissanet"
    tier: str = "small"
    encoding: str = "mantissa"
    loss: str = "ce"
    stage_steps: tuple[int, ...] = (500, 3500, 2000)
    crop: int = 64
    large_crop: int = 128
    batch: int = 8
    max_read_noise: float = 0.0
    risk_weight: float = RISK_WEIGHT
    own_states: float = 0.0
    own_passes: int = 4
    init_from: str | None = None
    label: str = ""
    seed: int = 0
    threads: int = 1
    device: str = "cpu"
    precision: str = "fp32"
    workers: int = 0
    checkpoint_every: int = 100
    log_every: int = 20
    runs_dir: Path = field(default=RUNS_DIR, compare=False)

    @property
    def name(self) -> str:
        noise = "-noise" if self.max_read_noise > 0 else ""
        loss = "" if self.loss == "ce" else f"-{self.loss}"
        label = f"-{self.label}" if self.label else ""
        return f"{self.family}-{self.tier}{noise}{loss}{label}-{self.encoding}"

    @property
    def decoder(self) -> str:
        """The runtime decoder the run ships as (the loss is a training choice, so runs that
        differ only in their loss serve the same decoder)."""
        if self.family == "unmodnet":
            return "unmodnet"
        noise = "-noise" if self.max_read_noise > 0 else ""
        return f"{self.family}-{self.tier}{noise}"

    @property
    def run_dir(self) -> Path:
        return self.runs_dir / self.name

    @property
    def total_steps(self) -> int:
        return sum(self.stage_steps)

    def stage(self, step: int) -> int:
        """Stage (1 to 4) of global step ``step``."""
        ends = [sum(self.stage_steps[: i + 1]) for i in range(len(self.stage_steps))]
        return next((i + 1 for i, end in enumerate(ends) if step < end), len(ends))

    def pairs(self, stage: int) -> PairConfig:
        """What a batch of ``stage`` holds: stage 4 takes ``large_crop`` crops, a quarter
        as many."""
        if stage == 4:
            batch = max(self.batch // 4, 1)
            return PairConfig(self.encoding, self.large_crop, batch, self.max_read_noise)
        return PairConfig(self.encoding, self.crop, self.batch, self.max_read_noise)

    def learning_rate(self, step: int) -> float:
        """Per-stage rate with a cosine decay to 5% over each stage."""
        stage = self.stage(step)
        start = sum(self.stage_steps[: stage - 1])
        progress = (step - start) / max(self.stage_steps[stage - 1], 1)
        return STAGE_LR[stage - 1] * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))


def build_model(config: TrainConfig) -> MantissaNet | UnModNet:
    """The seeded, freshly initialised net of the run's family, tier and loss."""
    torch.manual_seed(config.seed)
    if config.family == "unmodnet":
        return UnModNet(TIERS[config.tier])
    return MantissaNet(TIERS[config.tier], HEAD_OUTPUTS[config.loss])


def edge_bce(edges: Tensor, truth: Tensor) -> Tensor:
    """BCE of predicted wrap-edge probabilities against the true edges, in float32 outside
    any autocast (BCE on probabilities is unsafe in reduced precision)."""
    with torch.autocast(edges.device.type, enabled=False):
        return F.binary_cross_entropy(edges.float().clamp(1e-4, 1 - 1e-4), truth.float())


def winding_jumps(winding: Tensor) -> tuple[Tensor, Tensor]:
    """Per-neighbour jumps of W (float): along columns (``N x 1 x H x W-1``) and rows."""
    w = winding.float()
    return w[:, :, :, 1:] - w[:, :, :, :-1], w[:, :, 1:] - w[:, :, :-1]


def jumps_loss(output: Tensor, winding: Tensor) -> Tensor:
    """MSE of the predicted jumps (channel 0: to the right neighbour, 1: to the one below)."""
    along_cols, along_rows = winding_jumps(winding)
    return 0.5 * (
        F.mse_loss(output[:, :1, :, :-1], along_cols) + F.mse_loss(output[:, 1:, :-1], along_rows)
    )


def expected_log_mse(logits: Tensor, errors: Tensor) -> Tensor:
    """Mean over crops of ``ln(E[MSE] + RISK_FLOOR)``: the expected relative squared error
    of each crop under the predicted class probabilities (``errors`` from
    :func:`models.training.data.class_errors`). Mean PSNR over frames is
    ``-10 log10 MSE`` per frame, so this is its differentiable stand-in."""
    risk = (logits.softmax(dim=1) * errors).sum(dim=1).mean(dim=(1, 2))
    return torch.log(risk + RISK_FLOOR).mean()


def winding_loss(
    output: Tensor, winding: Tensor, loss: str, errors: Tensor | None = None,
    risk_weight: float = RISK_WEIGHT,
) -> Tensor:
    """Cross-entropy over W classes (``ce-risk`` adds ``risk_weight`` x the expected
    log-MSE, from the per-class ``errors``), MSE on W (the paper's), or MSE on the W
    jumps."""
    if loss == "ce-risk":
        if errors is None:
            raise ValueError("the ce-risk loss needs the per-class errors of the batch")
        cross_entropy = F.cross_entropy(output, winding[:, 0])
        return cross_entropy + risk_weight * expected_log_mse(output, errors)
    if loss == "mse":
        return F.mse_loss(output, winding.float())
    if loss == "jumps":
        return jumps_loss(output, winding)
    return F.cross_entropy(output, winding[:, 0])


def prediction_accuracy(output: Tensor, winding: Tensor, loss: str) -> Tensor:
    """Fraction right: pixels whose W is right (``ce``, ``mse``), or neighbour jumps whose
    rounded value is right (``jumps``: W itself needs the integration done at inference)."""
    if loss == "jumps":
        along_cols, along_rows = winding_jumps(winding)
        right = torch.cat([
            (output[:, :1, :, :-1].round() == along_cols).flatten(),
            (output[:, 1:, :-1].round() == along_rows).flatten(),
        ])  # fmt: skip
        return right.float().mean()
    if loss == "mse":
        predicted = output.round().clamp(0, NUM_CLASSES - 1)[:, 0].long()
    else:
        predicted = output.argmax(dim=1)
    return (predicted == winding[:, 0]).float().mean()


def rolled_out_state(
    model: UnModNet, m: Tensor, edges: Tensor, passes: int
) -> Tensor:
    """The partial W the model itself reaches from zero in ``passes`` passes, each pass
    rolling only inside the previous one's rollovers (as the runtime does), no gradient."""
    with torch.no_grad():
        state = torch.zeros_like(m)
        active = torch.ones_like(m, dtype=torch.bool)
        for _ in range(passes):
            active = (model.mask(m + state, edges.detach()) > 0) & active
            state = state + active.float()
    return state


def rollover_losses(
    model: UnModNet,
    m: Tensor,
    winding: Tensor,
    edges: Tensor,
    generator: torch.Generator,
    own_states: float = 0.0,
    own_passes: int = 4,
) -> tuple[Tensor, Tensor]:
    """UnModNet's pass loss: from a partial state, BCE of the logit that a pixel rolls
    over once more (``W > state``); returns (loss, accuracy).

    The state is a random ``min(W, k)`` (``k`` up to the crop's top W) or, for a fraction
    ``own_states`` of the batches, the model's own state after 1 to ``own_passes``
    passes (:func:`rolled_out_state`): at inference each pass starts from the previous
    passes' answer, mistakes included, and from ``min(W, k)`` alone the net never learns
    to stop where it over-counted (val-256 mantissa, 3 / 15 passes: 18.21 / 8.25 dB after
    the first run of the shipped recipe, 20.25 / 20.20 dB after the two runs on its own
    states). The roll-outs run the net in training mode, so they also update its batch
    norm statistics, as the shipped runs did."""
    top = winding.amax(dim=(1, 2, 3), keepdim=True).float()
    draws = torch.rand(top.shape, generator=generator).to(top.device)
    k = torch.floor(draws * (top + 1)).long()
    state = torch.minimum(winding, k).float()
    if own_states and torch.rand((), generator=generator).item() < own_states:
        passes = int(torch.randint(1, own_passes + 1, (), generator=generator).item())
        state = rolled_out_state(model, m, edges, passes)
    target = (winding.float() > state).float()
    logits = model.mask(m + state, edges)
    accuracy = ((logits > 0).float() == target).float().mean()
    return F.binary_cross_entropy_with_logits(logits, target), accuracy


def step_losses(
    model: MantissaNet | UnModNet, m: Tensor, winding: Tensor, stage: int, loss: str,
    step: int = 0, errors: Tensor | None = None, risk_weight: float = RISK_WEIGHT,
    own_states: float = 0.0, own_passes: int = 4,
) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss of one batch in ``stage`` and its logged parts (edge BCE, pixel accuracy,
    detached scalars: reading them waits for a GPU, so the loop reads them only to log);
    ``errors`` are the per-class errors that ``ce-risk`` needs."""
    truth = wrap_edges(winding)
    if stage == 1:
        edge_error = edge_bce(model.edge(m), truth)
        return edge_error, {"edge_bce": edge_error.detach()}
    if isinstance(model, UnModNet):
        edges = truth if stage == 2 else model.edge(m)
        generator = torch.Generator().manual_seed(step)
        total, accuracy = rollover_losses(
            model, m, winding, edges, generator, own_states, own_passes
        )
        if stage == 2:
            return total, {"accuracy": accuracy.detach()}
        edge_error = edge_bce(edges, truth)
        total = total + EDGE_WEIGHT * edge_error
        return total, {"edge_bce": edge_error.detach(), "accuracy": accuracy.detach()}
    if stage == 2:
        logits = model.winding(m, truth)
        total = winding_loss(logits, winding, loss, errors, risk_weight)
        parts: dict[str, Tensor] = {}
    else:
        logits, edges = model(m)
        edge_error = edge_bce(edges, truth)
        total = winding_loss(logits, winding, loss, errors, risk_weight) + EDGE_WEIGHT * edge_error
        parts = {"edge_bce": edge_error.detach()}
    accuracy = prediction_accuracy(logits, winding, loss)
    return total, {**parts, "accuracy": accuracy.detach()}


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write atomically (temporary file, then rename)."""
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint written by :func:`train` (model, optimizer, step, wall_s, config)."""
    return torch.load(path, map_location="cpu", weights_only=False)


def hardware_name(device: torch.device) -> str:
    """The GPU's name, or the CPU's model name (``cpu`` where the system does not say)."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.exists() else []
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return names[0] if names else "cpu"


def run_state(
    config: TrainConfig, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
    step: int, wall_s: float, segments: list[dict[str, Any]],
) -> dict[str, Any]:
    """What a checkpoint holds: weights, optimizer state, step, wall time (s), config, and
    the run's segments: where each stretch of steps ran (hardware, device, precision,
    ``steps`` [first, last), wall s), one per call of :func:`train` that made steps."""
    return {
        "model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
        "wall_s": wall_s, "config": {**asdict(config), "runs_dir": str(config.runs_dir)},
        "segments": segments,
    }  # fmt: skip


def checkpoint_segments(state: dict[str, Any]) -> list[dict[str, Any]]:
    """A checkpoint's segments; one on an unnamed CPU for checkpoints written before
    segments were recorded (all of them ran on one CPU core)."""
    if "segments" in state:
        return list(state["segments"])
    config = state["config"]
    return [{
        "hardware": "cpu", "device": "cpu", "precision": config.get("precision", "fp32"),
        "steps": [0, state["step"]], "wall_s": round(state["wall_s"], 1),
    }] if state["step"] else []  # fmt: skip


def initial_weights(config: TrainConfig) -> dict[str, Tensor]:
    """The finished weights of the run ``config.init_from`` (same runs folder)."""
    source = config.runs_dir / str(config.init_from) / "checkpoint.pt"
    if not source.exists():
        raise FileNotFoundError(
            f"{config.name} starts from {source}, which does not exist: train "
            f"{config.init_from} first (mcam train all trains the recipes in order)"
        )
    return load_checkpoint(source)["model"]


def check_config(config: TrainConfig) -> None:
    """Raise InvalidInputError (a ValueError), naming the field, for a configuration that
    :func:`train` cannot run."""
    if config.loss not in LOSSES or config.tier not in TIERS or config.family not in FAMILIES:
        raise InvalidInputError(
            f"loss must be one of {LOSSES}, tier one of {tuple(TIERS)}, family one of {FAMILIES}"
        )
    if not config.risk_weight >= 0.0:
        raise InvalidInputError(f"risk_weight must be >= 0, got {config.risk_weight}")
    if config.precision not in PRECISIONS:
        raise InvalidInputError(
            f"precision must be one of {PRECISIONS}, got {config.precision!r}"
        )
    if config.workers < 0:
        raise InvalidInputError(
            f"workers must be >= 0 (0 makes batches in-process), got {config.workers}"
        )
    try:
        device = torch.device(config.device)
    except RuntimeError as exc:
        raise InvalidInputError(
            f"device must be a torch device such as cpu or cuda, got {config.device!r}"
        ) from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InvalidInputError(f"device {config.device!r} asked for, but torch sees no CUDA GPU")


def restore(
    config: TrainConfig, model: torch.nn.Module, optimizer: torch.optim.Optimizer
) -> tuple[int, float, list[dict[str, Any]]]:
    """Load the run's checkpoint (or ``init_from``'s weights) into ``model`` and
    ``optimizer``; returns the step and wall seconds reached and the segments so far,
    (0, 0.0, []) for a fresh run."""
    checkpoint = config.run_dir / "checkpoint.pt"
    if checkpoint.exists():
        state = load_checkpoint(checkpoint)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        return state["step"], state["wall_s"], checkpoint_segments(state)
    if config.init_from:
        model.load_state_dict(initial_weights(config))
    return 0, 0.0, []


def step_batches(config: TrainConfig, start: int) -> Iterator[Batch]:
    """The batches of steps ``start`` .. the last (stage 4's are larger crops)."""
    plan = ((step, config.pairs(config.stage(step))) for step in range(start, config.total_steps))
    return batch_stream(config.seed, plan, config.loss == "ce-risk", config.workers)


def optimizer_step(
    config: TrainConfig, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
    batch: Batch, step: int,
) -> tuple[Tensor, dict[str, Tensor]]:
    """One step on ``batch`` at the step's learning rate, on the model's device and in the
    run's precision; returns the loss and its logged parts (detached)."""
    device = next(model.parameters()).device
    for group in optimizer.param_groups:
        group["lr"] = config.learning_rate(step)
    errors = None if batch.errors is None else torch.from_numpy(batch.errors).to(device)
    bf16 = config.precision == "bf16"
    with torch.autocast(device.type, torch.bfloat16, enabled=bf16):
        loss, parts = step_losses(
            model, torch.from_numpy(batch.m).to(device),
            torch.from_numpy(batch.winding).to(device), config.stage(step), config.loss, step,
            errors, config.risk_weight, config.own_states, config.own_passes,
        )  # fmt: skip
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.detach(), parts


def use_device(config: TrainConfig) -> torch.device:
    """The run's torch device, with the threads and GPU fast paths (cuDNN autotuning,
    TF32) set for it."""
    device = torch.device(config.device)
    torch.set_num_threads(config.threads)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    return device


def train(
    config: TrainConfig,
    report: Callable[[dict[str, Any]], None] | None = None,
    deadline: float | None = None,
) -> Path:
    """Train (or resume) the run; returns the checkpoint path. ``report`` gets log records.

    ``deadline`` (``time.monotonic()`` seconds): stop after the first step past it, with a
    checkpoint, even if steps remain (calling again resumes there)."""
    check_config(config)
    device = use_device(config)
    config.run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint = config.run_dir / "checkpoint.pt"
    model = build_model(config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=STAGE_LR[0])
    step, wall_s, segments = restore(config, model, optimizer)
    segment: dict[str, Any] = {
        "hardware": hardware_name(device), "device": config.device,
        "precision": config.precision, "steps": [step, step], "wall_s": 0.0,
    }  # fmt: skip
    model.train()
    started = time.monotonic() - wall_s
    segment_started = time.monotonic()
    with (config.run_dir / "log.jsonl").open("a") as log:
        for batch in step_batches(config, step):
            loss, parts = optimizer_step(config, model, optimizer, batch, step)
            step += 1
            now = time.monotonic()
            last = step == config.total_steps or (deadline is not None and now > deadline)
            if step % config.log_every == 0 or last:
                record = {"step": step, "stage": config.stage(step - 1), "loss": loss.item(),
                          **{name: value.item() for name, value in parts.items()},
                          "lr": config.learning_rate(step - 1),
                          "wall_s": round(now - started, 1)}  # fmt: skip
                log.write(json.dumps(record) + "\n")
                log.flush()
                if report:
                    report(record)
            if step % config.checkpoint_every == 0 or last:
                segment["steps"][1] = step
                segment["wall_s"] = round(now - segment_started, 1)
                done = [*segments, segment]
                save_checkpoint(
                    checkpoint, run_state(config, model, optimizer, step, now - started, done)
                )
            if last:
                break
    if not checkpoint.exists():
        save_checkpoint(checkpoint, run_state(config, model, optimizer, step, wall_s, segments))
    return checkpoint
