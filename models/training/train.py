"""Seeded, resumable training of the MantissaCam nets in the paper's three stages.

Stage 1 trains the edge net alone (BCE against the true wrap edges); stage 2 the
winding net on the true edges; stage 3 both end to end (winding loss + 0.1 edge BCE;
the losses are in :mod:`models.training.losses`); an optional stage 4 continues end to
end on larger crops (``large_crop``, a quarter of the batch) so the net sees the context
of a full frame. Batches depend only on ``(seed, step)``; a checkpoint
(:mod:`models.training.checkpoints`) is written every ``checkpoint_every`` steps under
``runs/<name>/`` and a restarted run resumes from it. Losses go to
``runs/<name>/log.jsonl`` (on a resume, its records past the checkpoint's step are
dropped: one history). One process at a time trains a run: it holds
``runs/<name>/lock`` (:func:`run_lock`).

A run may start from another run's trained weights (``init_from``, e.g. a
noise-aware fine-tune of a finished model, or a model trained in two runs); stages
with 0 steps are skipped. ``label`` tells apart runs that would share a name (the
first of two runs of one model). The settings (:class:`TrainConfig`) and the checks
made before a run trains or resumes are in :mod:`models.training.config`.

Training runs on the CPU (``device="cpu"``, the default) or a GPU (``"cuda"``), in
float32 or bf16 autocast (``precision``); ``workers`` processes make the batches ahead
(:func:`models.training.data.batch_stream`), which a GPU needs to be kept busy. None of
these changes which batches a step sees. ``train(..., deadline=...)`` stops at a wall
clock time with a checkpoint (a later call resumes). SIGINT (Ctrl-C) and SIGTERM stop
it the same way after the step in progress, then raise :class:`Stopped`.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from models.errors import InvalidInputError, McamError
from models.training.checkpoints import (
    checkpoint_segments,
    hardware_name,
    load_checkpoint,
    load_weights,
    run_state,
    save_checkpoint,
)
from models.training.config import STAGE_LR, TrainConfig, check_config, check_same_training
from models.training.data import Batch, batch_stream
from models.training.losses import HEAD_OUTPUTS, step_losses
from models.training.networks import TIERS, MantissaNet, UnModNet
from models.training.run_control import (
    LOG_FILE,
    Stopped,
    run_lock,
    stop_requests,
    trim_log,
)


class TrainingDivergedError(McamError):
    """A step's loss was not finite: the weights are lost to NaN from there on."""

    code = "training_diverged"


def divergence_advice(config: TrainConfig) -> str:
    """What to change, as ``mcam train run`` options, to train a run whose loss was not
    finite again: a lower risk weight (``ce-risk``), float32 (``bf16``), or other batches
    and initial weights (another seed). The learning rates are not an option: they are
    :data:`STAGE_LR`'s, per stage."""
    changes = []
    if config.loss == "ce-risk":
        changes.append(f"a lower --risk-weight (now {config.risk_weight:g})")
    if config.precision == "bf16":
        changes.append("--precision fp32")
    changes.append("another --seed")
    return (
        f"train it again with {' or '.join(changes)}, as a new run (--label); the learning "
        "rates are fixed per stage (STAGE_LR in models/training/config.py)"
    )


def build_model(config: TrainConfig) -> MantissaNet | UnModNet:
    """The seeded, freshly initialised net of the run's family, tier and loss."""
    torch.manual_seed(config.seed)
    if config.family == "unmodnet":
        return UnModNet(TIERS[config.tier])
    return MantissaNet(TIERS[config.tier], HEAD_OUTPUTS[config.loss])


def load_initial_weights(config: TrainConfig, model: torch.nn.Module) -> None:
    """Load the finished weights of the run ``config.init_from`` (same runs folder) into
    ``model``; a run of another net, or one that has not reached its last step, is
    refused."""
    source = config.runs_dir / str(config.init_from) / "checkpoint.pt"
    if not source.exists():
        raise FileNotFoundError(
            f"{config.name} starts from {source}, which does not exist: train "
            f"{config.init_from} first (mcam train all trains the recipes in order)"
        )
    state = load_checkpoint(source)
    check_same_net(config, state["config"])
    planned = sum(state["config"]["stage_steps"])
    if state["step"] < planned:
        raise InvalidInputError(
            f"{config.name} starts from {config.init_from}, which stopped at step "
            f"{state['step']} of {planned}: train it to the end first (mcam train run "
            "with its settings resumes it)"
        )
    load_weights(model, state["model"], source)


def net_shape(family: str, tier: str, loss: str) -> str:
    """The net a run trains, in words: family, tier and outputs per pixel (the loss's
    head, :data:`models.training.losses.HEAD_OUTPUTS`)."""
    outputs = 1 if family == "unmodnet" else HEAD_OUTPUTS.get(loss)
    return f"a {family} {tier} net with {outputs} outputs per pixel"


def check_same_net(config: TrainConfig, saved: dict[str, Any]) -> None:
    """Refuse to start ``config`` from the weights of ``init_from``'s run (its
    ``saved`` configuration) when they are those of another net (family, tier or head),
    which the weights cannot be loaded into."""
    source = net_shape(saved["family"], saved["tier"], saved.get("loss", "ce"))
    target = net_shape(config.family, config.tier, config.loss)
    if source != target:
        raise InvalidInputError(
            f"{config.name} starts from {config.init_from}, {source} ({saved.get('loss', 'ce')} "
            f"loss), but it trains {target} ({config.loss} loss): the weights do not fit. "
            "Start from a run of the same family and tier, with a loss of as many outputs, "
            "or leave --init-from out to train from scratch"
        )


def restore(
    config: TrainConfig, model: torch.nn.Module, optimizer: torch.optim.Optimizer
) -> tuple[int, float, list[dict[str, Any]]]:
    """Load the run's checkpoint (or ``init_from``'s weights) into ``model`` and
    ``optimizer``; returns the step and wall seconds reached and the segments so far,
    (0, 0.0, []) for a fresh run. A checkpoint trained with other settings is refused
    (:func:`check_same_training`)."""
    checkpoint = config.run_dir / "checkpoint.pt"
    if checkpoint.exists():
        state = load_checkpoint(checkpoint, resuming=True)
        check_same_training(config, state["config"], checkpoint)
        load_weights(model, state["model"], checkpoint, resuming=True)
        optimizer.load_state_dict(state["optimizer"])
        return state["step"], state["wall_s"], checkpoint_segments(state)
    if config.init_from:
        load_initial_weights(config, model)
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


def record_line(record: dict[str, Any]) -> str:
    """A log record (step, stage, loss and its parts, ...) as one ``key=value`` line."""
    return " ".join(
        f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items()
    )


def train(
    config: TrainConfig,
    report: Callable[[dict[str, Any]], None] | None = None,
    deadline: float | None = None,
) -> Path:
    """Train (or resume) the run; returns the checkpoint path. ``report`` gets log records.

    ``deadline`` (``time.monotonic()`` seconds): stop after the first step past it, with a
    checkpoint, even if steps remain (calling again resumes there). SIGINT or SIGTERM
    (in the main thread) stops it the same way, then raises :class:`Stopped`. The run
    folder is locked meanwhile (:func:`run_lock`)."""
    check_config(config)
    device = use_device(config)
    with run_lock(config.run_dir), stop_requests() as stops:
        checkpoint, step = run_steps(config, device, report, deadline, stops)
        if stops:
            raise Stopped(stops[0], step, config.total_steps, checkpoint)
        return checkpoint


def run_steps(
    config: TrainConfig,
    device: torch.device,
    report: Callable[[dict[str, Any]], None] | None,
    deadline: float | None,
    stops: list[int],
) -> tuple[Path, int]:
    """The steps of :func:`train`, in its locked run folder, until the last, the
    deadline or a signal noted in ``stops``; returns the checkpoint and its step."""
    checkpoint = config.run_dir / "checkpoint.pt"
    model = build_model(config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=STAGE_LR[0])
    step, wall_s, segments = restore(config, model, optimizer)
    trim_log(config.run_dir / LOG_FILE, step)
    segment: dict[str, Any] = {
        "hardware": hardware_name(device), "device": config.device,
        "precision": config.precision, "steps": [step, step], "wall_s": 0.0,
    }  # fmt: skip
    model.train()
    started = time.monotonic() - wall_s
    segment_started = time.monotonic()
    with (config.run_dir / LOG_FILE).open("a") as log:
        for batch in step_batches(config, step):
            loss, parts = optimizer_step(config, model, optimizer, batch, step)
            if not math.isfinite(loss.item()):
                raise TrainingDivergedError(
                    f"{config.name} diverged at step {step + 1}: its loss is "
                    f"{loss.item()}; nothing past it is saved, and resuming would repeat "
                    f"the same steps: {divergence_advice(config)}"
                )
            step += 1
            now = time.monotonic()
            late = deadline is not None and now > deadline
            last = step == config.total_steps or late or bool(stops)
            if step % config.log_every == 0 or last:
                record = {"step": step, "stage": config.stage(step - 1), "loss": loss.item(),
                          **{name: value.item() for name, value in parts.items()},
                          "lr": config.learning_rate(step - 1),
                          "wall_s": round(now - started, 1)}  # fmt: skip
                log.write(json.dumps(record) + "\n")
                log.flush()
                if report:
                    report(record)
            # A signal that came while the step was logged stops the run at this step too.
            last = last or bool(stops)
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
    return checkpoint, step
