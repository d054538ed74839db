"""A training run's settings (:class:`TrainConfig`) and the checks made before it trains.

:func:`check_config` refuses a configuration the trainer cannot run, naming the field,
before anything is trained or written; :func:`check_same_training` refuses to resume a
checkpoint trained with other settings (:data:`RESUMABLE_CHANGES` lists those a resume
may change). :mod:`models.training.train` runs the configuration.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import torch

from models.errors import InvalidInputError
from models.training.data import PairConfig, largest_crop
from models.training.losses import LOSSES, RISK_WEIGHT
from models.training.networks import TIERS

RUNS_DIR = Path(__file__).resolve().parents[2] / "runs"
FAMILIES = ("mantissanet", "unmodnet")
STAGE_LR = (2e-3, 2e-3, 5e-4, 3e-4)
#: ``fp32``: float32 throughout; ``bf16``: bfloat16 autocast (a GPU's fast path).
PRECISIONS = ("fp32", "bf16")


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``stage_steps``: optimizer steps of stages 1, 2, 3 (and 4).

    ``risk_weight`` (``ce-risk`` only): weight of the expected-PSNR term, see
    :func:`models.training.losses.winding_loss`. ``own_states`` / ``own_passes``
    (``unmodnet`` only): the fraction of batches trained from the model's own state after
    up to that many passes, see :func:`models.training.losses.rollover_losses`.
    ``glow_fraction``: the share of synthetic scenes with smooth bright lobes (see
    :mod:`models.training.data`).
    ``label``: a tag in the run name (``-<label>`` before the encoding), for a run that is
    a step towards another rather than a model.
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
    colour_fraction: float = 0.0
    glow_fraction: float = 0.0
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
        loss = "" if self.loss == "ce" else f"-{self.loss}"
        label = f"-{self.label}" if self.label else ""
        return f"{self.family}-{self.tier}{self.data_tag}{loss}{label}-{self.encoding}"

    @property
    def data_tag(self) -> str:
        """``-noise`` for noise-aware training, ``-colour`` for colour-channel data."""
        noise = "-noise" if self.max_read_noise > 0 else ""
        return noise + ("-colour" if self.colour_fraction > 0 else "")

    @property
    def decoder(self) -> str:
        """The runtime decoder the run ships as (the loss is a training choice, so runs that
        differ only in their loss serve the same decoder)."""
        if self.family == "unmodnet":
            return "unmodnet"
        return f"{self.family}-{self.tier}{self.data_tag}"

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
            crop = self.large_crop
        else:
            crop, batch = self.crop, self.batch
        return PairConfig(
            self.encoding, crop, batch, self.max_read_noise,
            colour_fraction=self.colour_fraction, glow_fraction=self.glow_fraction,
        )  # fmt: skip

    def learning_rate(self, step: int) -> float:
        """Per-stage rate with a cosine decay to 5% over each stage."""
        stage = self.stage(step)
        start = sum(self.stage_steps[: stage - 1])
        progress = (step - start) / max(self.stage_steps[stage - 1], 1)
        return STAGE_LR[stage - 1] * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))


#: The shares a run sets, each in [0, 1], and what each is.
FRACTIONS = {
    "colour_fraction": "the share of HDRI crops taken as one channel of a colour frame",
    "glow_fraction": "the share of synthetic scenes with smooth bright lobes",
    "own_states": "the share of unmodnet batches trained from the model's own states",
}
#: Counts a run sets that must be at least 1, and what each is.
POSITIVE_COUNTS = {
    "batch": "crops per optimizer step",
    "threads": "torch threads",
    "own_passes": "unmodnet passes rolled out",
    "checkpoint_every": "steps between checkpoints",
    "log_every": "steps between log lines",
}
#: The largest read noise a frame may have (wrap units), ``SensorParams.read_noise``'s bound.
READ_NOISE_LIMIT = 1.0
#: Seeds are non-negative and below this (``torch.manual_seed`` takes 64-bit seeds).
SEED_LIMIT = 2**63
#: Training crops are multiples of this many px, and at least :data:`SMALLEST_CROP`.
CROP_MULTIPLE = 16
SMALLEST_CROP = 32
#: A run name's tag (``label``) and a run to start from (``init_from``) name one folder of
#: the runs folder: letters, digits, ``.``, ``_`` and ``-``, not starting with ``.`` or ``-``.
RUN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
ENCODINGS = ("mantissa", "modulo")


def check_config(config: TrainConfig) -> None:
    """Raise InvalidInputError (a ValueError), naming the field, for a configuration that
    :func:`train` cannot run; nothing is trained or written before these checks."""
    check_choices(config)
    check_amounts(config)
    check_stages(config)
    check_crops(config)
    check_names(config)
    check_device(config)


def check_choices(config: TrainConfig) -> None:
    """Family, tier, loss, encoding and precision are ones the trainer knows."""
    if config.loss not in LOSSES or config.tier not in TIERS or config.family not in FAMILIES:
        raise InvalidInputError(
            f"loss must be one of {LOSSES}, tier one of {tuple(TIERS)}, family one of {FAMILIES}"
        )
    if config.family == "unmodnet" and config.loss != "ce":
        raise InvalidInputError(
            f"unmodnet learns its rollover masks with cross-entropy only, got loss "
            f"{config.loss!r}: leave the loss out (it trained as ce under another name)"
        )
    if config.encoding not in ENCODINGS:
        raise InvalidInputError(f"encoding must be one of {ENCODINGS}, got {config.encoding!r}")
    if config.precision not in PRECISIONS:
        raise InvalidInputError(
            f"precision must be one of {PRECISIONS}, got {config.precision!r}"
        )


def check_amounts(config: TrainConfig) -> None:
    """Weights, shares, counts, the seed and the read noise are in range."""
    if not 0.0 <= config.risk_weight < math.inf:
        raise InvalidInputError(
            f"risk_weight must be finite and >= 0, got {config.risk_weight}"
        )
    for name, meaning in FRACTIONS.items():
        value = getattr(config, name)
        if not 0.0 <= value <= 1.0:
            raise InvalidInputError(f"{name} must be in [0, 1] ({meaning}), got {value}")
    for name, meaning in POSITIVE_COUNTS.items():
        value = getattr(config, name)
        if value < 1:
            raise InvalidInputError(f"{name} must be at least 1 ({meaning}), got {value}")
    if config.workers < 0:
        raise InvalidInputError(
            f"workers must be >= 0 (0 makes batches in-process), got {config.workers}"
        )
    if not 0 <= config.seed < SEED_LIMIT:
        raise InvalidInputError(f"seed must be in [0, 2**63), got {config.seed}")
    if not 0.0 <= config.max_read_noise <= READ_NOISE_LIMIT:
        raise InvalidInputError(
            f"max read noise must be in [0, {READ_NOISE_LIMIT}] (a Gaussian sigma in wrap "
            f"units; the shipped noise-aware nets use 0.02), got {config.max_read_noise}"
        )


def check_stages(config: TrainConfig) -> None:
    """3 or 4 stages of >= 0 steps, at least one step in all unless the run starts from
    another run's weights (else it would write an untrained checkpoint)."""
    steps = config.stage_steps
    if len(steps) not in (3, 4) or any(count < 0 for count in steps):
        raise InvalidInputError(
            f"stage steps must be 3 or 4 counts >= 0 (e.g. 500,3500,2000), got {steps}"
        )
    if config.total_steps == 0 and not config.init_from:
        raise InvalidInputError(
            f"stage steps {steps} train nothing: give at least one stage a step "
            "(e.g. 500,3500,2000)"
        )


def check_crops(config: TrainConfig) -> None:
    """The crops (and stage 4's large crops, when it has steps) are multiples of
    :data:`CROP_MULTIPLE` px, at least :data:`SMALLEST_CROP` and no larger than the
    smallest training panorama allows (:func:`models.training.data.largest_crop`)."""
    crops = {"crop": config.crop}
    if len(config.stage_steps) == 4 and config.stage_steps[3] > 0:
        crops["large_crop"] = config.large_crop
    for name, size in crops.items():
        if size % CROP_MULTIPLE or size < SMALLEST_CROP:
            raise InvalidInputError(
                f"{name} must be a multiple of {CROP_MULTIPLE} px and >= {SMALLEST_CROP}, "
                f"got {size}"
            )
        if size > largest_crop():
            raise InvalidInputError(
                f"{name} must be at most {largest_crop()} px (the smallest side of the "
                f"smallest training panorama), got {size}"
            )


def check_names(config: TrainConfig) -> None:
    """``label`` and ``init_from`` each name one folder of the runs folder."""
    for name, value in (("label", config.label), ("init_from", config.init_from)):
        if value and not RUN_NAME.fullmatch(value):
            raise InvalidInputError(
                f"{name} must be one folder name (letters, digits, '.', '_', '-'; no '/'), "
                f"got {value!r}"
            )


def check_device(config: TrainConfig) -> None:
    """The device is a torch device this machine has (a GPU's number included)."""
    try:
        device = torch.device(config.device)
    except RuntimeError as exc:
        raise InvalidInputError(
            f"device must be a torch device such as cpu or cuda, got {config.device!r}"
        ) from exc
    if device.type not in ("cpu", "cuda"):
        raise InvalidInputError(
            f"device must be cpu or cuda[:N] (the trainer runs on those), got {config.device!r}"
        )
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InvalidInputError(f"device {config.device!r} asked for, but torch sees no CUDA GPU")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise InvalidInputError(
            f"device {config.device!r} asked for, but torch sees {torch.cuda.device_count()} "
            "CUDA GPU(s), numbered from 0: name one of them (cuda:0), or cuda"
        )


#: The settings a resumed run may change: they do not change which weights its steps
#: reach. Where and how the steps run (``device``, ``precision``, ``threads``: each
#: segment of the checkpoint records its own; ``workers``: the batches are the same), how
#: often it logs and checkpoints, its runs folder, and its name's ``label`` (a run's
#: folder may be renamed: its batches depend only on the seed and step). Every other
#: field of :class:`TrainConfig` changes what is trained and must match the checkpoint.
RESUMABLE_CHANGES = frozenset({
    "device", "precision", "threads", "workers", "checkpoint_every", "log_every",
    "runs_dir", "label",
})  # fmt: skip


def changed_settings(config: TrainConfig, saved: dict[str, Any]) -> list[str]:
    """The fields that change what is trained on which ``config`` differs from a
    checkpoint's ``saved`` configuration, as ``name saved (now new)``; a field the
    checkpoint predates counts as its default."""
    changes = []
    for item in fields(TrainConfig):
        if item.name in RESUMABLE_CHANGES:
            continue
        now = getattr(config, item.name)
        before = saved.get(item.name, item.default)
        if isinstance(now, tuple):
            before = tuple(before)
        if before != now:
            changes.append(f"{item.name} {before!r} (now {now!r})")
    return changes


def saved_config(saved: dict[str, Any], checkpoint: Path) -> TrainConfig:
    """The configuration a checkpoint's ``saved`` settings describe, as this version of the
    code knows it: settings of features since removed (``psnr_share`` of the ce-psnr
    loss, ``saturation``) are left out, and a loss, tier or family this version lacks is
    an InvalidInputError naming the checkpoint."""
    known = {item.name for item in fields(TrainConfig)}
    raw = {name: value for name, value in saved.items() if name in known}
    config = TrainConfig(**{
        **raw, "stage_steps": tuple(raw["stage_steps"]), "runs_dir": Path(raw["runs_dir"]),
    })  # fmt: skip
    try:
        check_choices(config)
    except InvalidInputError as exc:
        raise InvalidInputError(
            f"{checkpoint} was trained by another version of the code, with settings this "
            f"one cannot build ({exc.message}, got loss {config.loss!r}, tier "
            f"{config.tier!r}, family {config.family!r}); use the version that trained it"
        ) from None
    return config


def check_same_training(config: TrainConfig, saved: dict[str, Any], checkpoint: Path) -> None:
    """Refuse to resume (or return) a checkpoint trained with other settings than
    ``config``'s, naming each that differs and what to do."""
    changes = changed_settings(config, saved)
    if changes:
        raise InvalidInputError(
            f"{checkpoint} was trained with other settings: {', '.join(changes)}; rerun with "
            "the checkpoint's settings to resume it, or train these settings as another run "
            "(another --runs-dir or --label)"
        )
