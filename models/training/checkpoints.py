"""Training checkpoints: what they hold, written atomically, and where each stretch of a
run's steps ran (its *segments*)."""

from __future__ import annotations

import os
import pickle
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from models.errors import InvalidInputError

if TYPE_CHECKING:
    from models.training.config import TrainConfig


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write atomically and durably: a temporary file, flushed to disk, renamed over
    ``path``, then the folder flushed so that the rename survives a power cut."""
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as file:
        torch.save(state, file)
    replace_durably(tmp, path)


def replace_durably(tmp: Path, path: Path) -> None:
    """Flush the written file ``tmp`` to disk, rename it over ``path``, then flush the
    folder so that the rename survives a power cut: ``path`` is the old file or the
    whole new one, never a part."""
    with tmp.open("rb") as file:
        os.fsync(file.fileno())
    tmp.replace(path)
    sync_folder(path.parent)


def sync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename in it) to disk."""
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


#: What ``torch.load`` raises on an empty, truncated or corrupt file (a file cut
#: short can also give EINVAL, a flipped byte a UnicodeDecodeError or a missing key).
UNREADABLE = (EOFError, RuntimeError, pickle.UnpicklingError, OSError, ValueError, KeyError)
#: What ``torch.load`` raises for a path that is no file it may read: not a damaged
#: checkpoint, so raised as it is (the CLI says "is a folder" or "permission denied").
NOT_A_FILE = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)


#: What every checkpoint holds (:func:`run_state`; ``segments`` came later, see
#: :func:`checkpoint_segments`).
CHECKPOINT_KEYS = ("model", "optimizer", "step", "wall_s", "config")


def load_checkpoint(path: Path, *, resuming: bool = False) -> dict[str, Any]:
    """A checkpoint written by :func:`models.training.train.train` (model, optimizer,
    step, wall_s, config, segments). An empty, cut short or corrupt file, or one that
    holds something else (a model's ``state_dict`` alone), is an InvalidInputError naming
    it and what to do (``resuming``: it is the run's own, which the run can also start
    again without)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except NOT_A_FILE:
        raise
    except UNREADABLE as exc:
        first_line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        reason = f"{first_line}: it is empty, cut short or corrupt"
        raise unreadable(path, reason, resuming) from exc
    if not isinstance(state, dict):
        reason = f"it holds a {type(state).__name__}, not a checkpoint's dict"
        raise unreadable(path, reason, resuming)
    missing = [key for key in CHECKPOINT_KEYS if key not in state]
    if missing:
        reason = (
            f"it lacks {', '.join(missing)}: a model's weights alone (a state_dict) or "
            "another program's file, not one training wrote"
        )
        raise unreadable(path, reason, resuming)
    return state


def unreadable(path: Path, reason: str, resuming: bool) -> InvalidInputError:
    """The error for a checkpoint file that cannot be read, saying what to do: only a run
    resuming from its own checkpoint is told it may delete its run folder (export and
    ``init_from`` read a checkpoint that is the user's to keep)."""
    advice = (
        f"put back a good copy, or delete the run folder {path.parent} to train the run "
        "again from scratch"
        if resuming
        else "name a checkpoint.pt that training wrote (runs/<name>/checkpoint.pt)"
    )
    return InvalidInputError(f"{path} is not a readable checkpoint ({reason}); {advice}")


#: Characters of PyTorch's first reason that weights do not fit a net that an error quotes
#: (its list of missing keys may name every layer).
REASON_CHARS = 160


def load_weights(
    model: torch.nn.Module, weights: dict[str, Any], path: Path, *, resuming: bool = False
) -> None:
    """Load the weights of checkpoint ``path`` into ``model``. Weights of another net
    (the checkpoint written by a version of the code whose nets differed, or edited) are
    the checkpoint's InvalidInputError (:func:`unreadable`) quoting PyTorch's first
    reason, not its traceback."""
    try:
        model.load_state_dict(weights)
    except RuntimeError as exc:
        reasons = [line.strip() for line in str(exc).splitlines()[1:] if line.strip()]
        first = (reasons or [str(exc)])[0]
        if len(first) > REASON_CHARS:
            first = first[:REASON_CHARS] + "..."
        reason = f"its weights do not fit the net its settings build: {first}"
        raise unreadable(path, reason, resuming) from None


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
    ``steps`` [first, last), wall s), one per call of :func:`models.training.train.train`
    that made steps."""
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
