"""The training recipes of the shipped models: ``mcam train all`` reruns exactly these."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from models.training.config import TrainConfig

#: Stage steps of the shipped small tier: edge net, winding net on true edges,
#: end to end on 64 px crops, end to end on 128 px crops. About 31 minutes per model
#: on one quiet EPYC core (2026-11-25). val-256 mantissa alone / refined by guided
#: PUMA: the earlier (500, 3500, 2000, 2000) 22.17 / 23.52 dB, (600, 7000, 2000, 1000)
#: 22.35 / 23.61 dB, this recipe 22.80 / 23.60 dB.
SMALL_STAGES = (600, 14000, 4000, 2000)

#: The half-resolution small tier (``small-s2d``). The modulo model, and the first of
#: the mantissa model's two runs, use the small tier's stage steps: about 17 minutes per
#: model on one core (2026-11-25, the other core training). val-256 alone / refined by
#: guided PUMA: mantissa 21.67 / 23.73 dB (shipped until the second run), modulo 22.20 /
#: 23.36 dB.
SMALL_S2D_STAGES = SMALL_STAGES
#: The mantissa model continues end to end from the first run's weights, with the
#: learning rate schedule of stages 3 and 4 restarted: 11 minutes on one core. val-256:
#: 22.17 / 23.87 dB, 88.2% W; auto-fast 21.38 -> 21.95 dB. The modulo model stays at one
#: run: continued the same way it measured 22.18 / 23.29 dB (88.8% W) against 22.20 /
#: 23.36, and took auto-balanced from 23.70 to 23.14 dB, auto-fast from 22.13 to 21.89.
SMALL_S2D_MORE_STAGES = (0, 0, 8000, 4000)
#: Label of the first run of a model trained in two.
FIRST_RUN = "part1"

#: Stage steps of the first of the base tier's two runs (mantissa only): the small
#: recipe, about 51 minutes on one core (2026-11-25, the other core training). val-256
#: mantissa alone / refined by guided PUMA: the earlier (300, 900, 300, 300) 21.36 /
#: 23.28 dB (87.7% W), this recipe 22.69 / 23.77 dB (90.7% W).
BASE_STAGES = SMALL_STAGES
#: The second run continues end to end like small-s2d's (:data:`SMALL_S2D_MORE_STAGES`):
#: 37 minutes on one core. val-256 mantissa 23.06 / 23.94 dB, 91.0% W, SSIM 0.869 (the
#: most W right of any tier; refined, the most accurate single decoder).
BASE_MORE_STAGES = SMALL_S2D_MORE_STAGES

#: Noise-aware small tier: the finished small model, continued end to end on large
#: crops with read noise (stage 4 only).
SMALL_NOISE_STAGES = (0, 0, 0, 2000)
#: Noise-aware base tier: the same from the finished base model, 6 minutes on one core.
#: val-256 mantissa alone 23.08 dB at read noise 0 and 23.25 dB at 0.01 (base: 23.06 and
#: 23.14), refined 23.99 dB: the most accurate refined net, so ``best`` runs it.
BASE_NOISE_STAGES = SMALL_NOISE_STAGES

#: The tier also shipped as an int8 QDQ model (its plain, not noise-aware, models).
INT8_TIER = "small"


def quantized(config: TrainConfig) -> bool:
    """Whether ``mcam train all`` also ships an int8 QDQ version of this run."""
    return config.tier == INT8_TIER and config.max_read_noise == 0


def exported(config: TrainConfig) -> bool:
    """Whether ``mcam train all`` exports this run: a labelled run is a step towards
    another (the first of two runs of one model), not a shipped model."""
    return not config.label

#: Stage steps of the shipped tiny tier: about 10 minutes per model on one quiet EPYC
#: core (2026-11-25). The earlier (300, 1500, 700, 500) measured 21.15 dB / 86.9% W on
#: val-256 mantissa; this recipe 21.63 dB / 88.9% with plain ce.
TINY_STAGES = (600, 5000, 2000, 1000)

#: UnModNet baseline: per encoding a chain of runs, each from the previous one's weights
#: (tiny tier widths; the rollover net is the tiny winding net's U-Net with one output).
#: Each entry: stage steps, ``own_states``, ``own_passes``. First: edge net, rollover net
#: on true edges, end to end, from random ``min(W, k)`` states, 5 minutes a model on one
#: core (2026-11-25); its first pass finds the rollovers (val-256 mantissa 85.4% W) but
#: later passes over-count bright regions (15 passes: 8.2 dB). Then end to end from the
#: model's own rolled-out states (``own_states`` of the batches, up to ``own_passes``
#: passes) on 64-px crops, 4 and 6 minutes (15 passes: mantissa 20.20 dB, modulo 19.73),
#: then on 128-px crops (stage 4), 2 minutes for 600 steps (20.88 / 20.87 dB). Last, 600
#: more such steps from states after up to 15 passes, the runtime's limit (2.5 minutes a
#: model; 2026-11-26): until then no training state had seen passes 9-15, which only the
#: brightest pixels reach (modulo W goes to 16). val-256 mantissa 20.88 -> 21.09 dB, PU21
#: 23.90 -> 24.08, MS-SSIM 0.817 -> 0.822; modulo 20.87 -> 21.02 dB, PU21 23.72 -> 24.10;
#: SSIM 0.0015 lower on both. 1500 such steps took modulo to 21.32 dB but cost 0.5 points
#: of W and 0.015 of MS-SSIM. The earlier residual rollover net, (600, 2400, 900) steps:
#: 18.91 dB / 80.1% W, about W = 0 everywhere.
UNMODNET_CHAIN: tuple[tuple[tuple[int, ...], float, int], ...] = (
    ((300, 2000, 800), 0.0, 4),
    ((0, 0, 1500), 0.5, 4),
    ((0, 0, 1500), 0.7, 8),
    ((0, 0, 0, 600), 0.7, 8),
    ((0, 0, 0, 600), 0.7, 15),
)


def unmodnet_chain(encoding: str) -> tuple[TrainConfig, ...]:
    """The runs of one UnModNet model (:data:`UNMODNET_CHAIN`): ``part1``, ``part2``, ...
    and the last, unlabelled one, which ships."""
    runs = []
    previous = None
    for index, (steps, own_states, own_passes) in enumerate(UNMODNET_CHAIN):
        label = f"part{index + 1}" if index + 1 < len(UNMODNET_CHAIN) else ""
        config = TrainConfig(
            family="unmodnet", tier="tiny", encoding=encoding, stage_steps=steps,
            own_states=own_states, own_passes=own_passes, init_from=previous, label=label,
        )  # fmt: skip
        runs.append(config)
        previous = config.name
    return tuple(runs)


#: Stage-step proportions of a timed GPU run (:mod:`models.training.timed` scales them
#: to the time it has): those of the base tier's two CPU runs together (edge net 2%,
#: winding net on true edges 43%, end to end 37%, end to end on large crops 18%).
TIMED_UNITS = (3, 42, 37, 18)
#: A timed run's batches: 16 crops of 128 px (stage 4: 4 of 256 px), 8x the pixels of a
#: CPU step, so the GPU runs fewer, larger steps.
TIMED_CROP, TIMED_LARGE_CROP, TIMED_BATCH = 128, 256, 16


def timed_run(tier: str, encoding: str, **changes: Any) -> TrainConfig:
    """A run of a lane set of :data:`TIMED_LANES`: the tier from scratch in
    :data:`TIMED_UNITS`, with ``changes`` to any field."""
    config = TrainConfig(
        tier=tier, encoding=encoding, stage_steps=TIMED_UNITS, crop=TIMED_CROP,
        large_crop=TIMED_LARGE_CROP, batch=TIMED_BATCH,
    )  # fmt: skip
    return replace(config, **changes)


#: Stage steps of the base tier on modulo frames, the one shipped model of a timed GPU
#: run (``first`` of :data:`TIMED_LANES`, 2026-11-26): given 500 s on an H200 with three other
#: lanes (bf16 autocast), it made 8876 steps there before the deadline; the last 1069
#: (stage 4) ran on one EPYC core from its checkpoint (bf16 autocast, 29 minutes; the
#: card's ``segments``). val-256 modulo alone / refined by guided PUMA: 23.10 / 24.06 dB,
#: 90.45% W (22.93 / 24.00 dB at the deadline), against small-s2d's 22.20 / 23.87 and
#: small's 22.84 / 23.70: the most accurate modulo net. The same lanes' base and
#: small-s2d mantissa nets and small-s2d modulo net measured below the shipped
#: CPU-trained ones (see docs/experiments.md, session 18) and were not shipped.
BASE_MODULO_STAGES = (298, 4177, 3680, 1790)

#: Stage steps of the tiny-s2d tier, from timed GPU runs (an H100, bf16 autocast). Modulo:
#: the ``s2d`` lanes (2026-11-26, 380 s with three other lanes). Mantissa: the ce lane of
#: ``tiny-s2d-mantissa`` (2026-11-26, 323 s with one other lane); in ``s2d`` its ce-risk
#: lane had made 3929 steps (ce-risk costs about twice a ce step on the GPU). val-256
#: alone / refined by guided PUMA (the model cards): mantissa 21.94 / 23.99 dB (the
#: ce-risk net it replaced: 21.42 / 23.84, and 21.45 / 23.81 with 4916 steps in the
#: same run as this one), modulo 21.72 / 23.47 dB, at 0.45 GFLOPs (small-s2d: 1.09),
#: 12-16 ms a frame on this host's slow spell where small-s2d took 19-23 ms. As
#: ``auto``'s fast net the ce-risk net lost 0.70 dB (mantissa) / 0.47 dB (modulo) for
#: 3.3-4.4 ms a frame, so ``auto`` kept small-s2d (the ce net that replaced it has run
#: at fast since 2026-11-27: ``models/decoders/adaptive_policy.py``); it ships as the
#: fastest learned decoder, ``mantissanet-tiny-s2d``. The ``s2d`` lanes' base-s2d nets
#: measured below small-s2d (mantissa 22.03 / 23.69 dB, modulo 22.29 / 23.54 dB at 23-34
#: ms) and were not shipped.
TINY_S2D_MANTISSA_STAGES = (281, 3935, 3466, 1686)
TINY_S2D_MODULO_STAGES = (286, 4004, 3528, 1716)
#: The tiny-s2d modulo net continues end to end from that run (lanes ``tiny-s2d-more``,
#: an H100, 2026-11-26: 4504 of these steps in 260 s before the deadline, the last 648
#: resumed on 2 EPYC cores in 3 minutes, bf16 autocast; the card's ``segments``). It ran
#: as ``mantissanet-tiny-s2d-more-modulo`` from the first run, then unlabelled; its
#: checkpoints were renamed to this recipe's names (a label does not change the batches,
#: which depend only on the seed and step). val-256 modulo alone / refined:
#: 21.80 / 23.51 dB, 88.61% W, PU21 24.16 dB (the first run: 21.72 / 23.47, 88.38%,
#: 23.96 dB), better on every metric, at read noise 0.01 too; at the deadline, before
#: the learning rate had decayed, it measured 21.94 / 23.71. Continued the same way the
#: mantissa net measured 21.83 / 23.93 dB against 21.94 / 23.99 and was not shipped.
TINY_S2D_MORE_STAGES = (0, 0, 3435, 1717)

#: Stage steps of the large tier (about twice base's widths, 3.4x its GFLOPs: 27.4 at 256x256),
#: per encoding, from timed GPU runs on an H100 (2026-11-27, bf16 autocast, two lanes):
#: lanes ``large`` (planned for 460 s, done in 353 s: the probe ran while both lanes were
#: starting) then ``large-more``, end to end from them (185 s). The runs ran as
#: ``mantissanet-large-<encoding>`` and ``mantissanet-large-more-<encoding>``; their
#: checkpoints were renamed to this recipe's names (a label does not change the batches).
#: val-256 alone / refined by guided PUMA, after the first run and after the second:
#: mantissa 22.50 / 24.23 -> 23.37 / 24.03 dB, W 91.32 -> 91.71%, PU21 alone 26.89 ->
#: 26.65 dB, MS-SSIM 0.902 -> 0.886; modulo 23.34 / 24.21 -> 23.57 / 24.37 dB, W 90.79 ->
#: 91.25%, better on every metric. Against base (the CPU-trained mantissa net, the GPU
#: modulo net): mantissa +0.31 dB and +0.7 points of W alone, -0.06 dB refined, PU21
#: -0.27 dB, MS-SSIM -0.017; modulo +0.47 dB alone, +0.31 refined, better on every
#: metric. Twice base's widths buy tenths of a dB, not the step the #3 targets need.
LARGE_STAGES = {"mantissa": (200, 2803, 2469, 1201), "modulo": (201, 2820, 2484, 1209)}
LARGE_MORE_STAGES = {"mantissa": (0, 0, 1869, 934), "modulo": (0, 0, 1882, 941)}


def large_chain(encoding: str) -> tuple[TrainConfig, TrainConfig]:
    """The two runs of a shipped large-tier model (:data:`LARGE_STAGES`)."""
    first = timed_run(
        "large", encoding, stage_steps=LARGE_STAGES[encoding], precision="bf16", label=FIRST_RUN
    )
    more = timed_run(
        "large", encoding, stage_steps=LARGE_MORE_STAGES[encoding], precision="bf16",
        init_from=first.name,
    )  # fmt: skip
    return first, more


#: Loss of the shipped tiny mantissa net: cross-entropy plus 0.1 x the expected log-MSE
#: (``ce-risk``). Measured on val-256 mantissa (net alone / refined by guided PUMA, dB):
#: tiny seed 0 ce-risk 22.09 / 23.88 against ce 21.63 / 23.56 (better on 19 of the 24
#: frames, worse on 1), seed 1 21.74 / 23.40 against 21.46 / 23.47: +0.3..+0.5 dB alone,
#: no reliable gain refined. Not kept elsewhere: the small recipe with ce-risk 22.28 /
#: 23.55 against ce 22.80 / 23.60 (its int8 version 20.22 against 21.75), the noise-aware
#: tiny 21.70 / 23.35 against 21.70 / 23.63, the tiny modulo net 22.06 / 23.25 against
#: 21.78 / 22.93 but with less W right (87.1 against 88.0%) and PU21 25.70 against
#: 25.86 dB (one seed, not shipped), the tiny-s2d net given the same GPU time (ce made
#: 1.9x the steps: 21.94 / 23.99 against 21.45 / 23.81); the modulo nets, the base and
#: tiny-s2d tiers use ce.
TINY_MANTISSA_LOSS = "ce-risk"

#: The three first runs of the ``large-prior`` lanes (:data:`TIMED_LANES`).
_LARGE_PRIOR = (
    timed_run("large", "mantissa", label="same"),
    timed_run("large", "mantissa", crop=TIMED_LARGE_CROP, batch=4, label="context"),
    timed_run("large", "mantissa", loss="ce-risk"),
)

#: Sets of lanes trained at once on a lent GPU (``python -m models.training.timed
#: --lanes NAME``), each lane a chain of runs from scratch. ``first`` (2026-11-26, an
#: H200): the base tier (then its noise-aware fine-tune, a fifth as long again) and the
#: small-s2d tier, per encoding. ``s2d`` (2026-11-26, an H100): the half-resolution
#: tiny and base tiers per encoding, candidates for ``auto``'s fast and balanced nets
#: (tiny-s2d runs in about half small-s2d's time on 2 EPYC cores, base-s2d in a third
#: of base's). ``tiny-s2d-mantissa`` (2026-11-26, an H100): the tiny-s2d mantissa net
#: alone, by loss (ce-risk, as shipped, and ce), since in ``s2d`` its ce-risk lane made
#: 2.4x fewer steps than the modulo one. ``tiny-s2d-more`` (2026-11-26, an H100): both
#: tiny-s2d nets continued end to end from a shipped recipe's run (its checkpoint copied
#: into the runs folder first; see :data:`TINY_S2D_MORE_STAGES`). ``large`` then
#: ``large-more`` (2026-11-27, an H100): the large tier per encoding, from scratch, then
#: continued end to end (see :data:`LARGE_STAGES`). ``large-prior`` (2026-11-28, an
#: H200): why the nets leave val-256's bright W >= 3 regions at W = 0, three large
#: mantissa lanes from scratch at once: as ``large`` (``same``), on 256-px crops in every
#: stage (``context``: a batch of 4, the same pixels a step; stage 4 a batch of 1), and
#: with the ``ce-risk`` loss; ``large-prior-more`` continues each end to end. val-256
#: alone after both: 23.15 / 21.78 / 23.48 dB, 91.31 / 89.07 / 91.16% W against the
#: shipped net's 23.37 dB, 91.71%: none shipped (``docs/experiments.md``, session 40).
#: The device, precision and step counts of the runs that shipped are in their cards.
TIMED_LANES: dict[str, tuple[tuple[TrainConfig, ...], ...]] = {
    "first": (
        (
            timed_run("base", "mantissa"),
            timed_run(
                "base", "mantissa", stage_steps=(0, 0, 0, TIMED_UNITS[3]), max_read_noise=0.02,
                init_from="mantissanet-base-mantissa",
            ),
        ),
        (timed_run("base", "modulo"),),
        (timed_run("small-s2d", "mantissa"),),
        (timed_run("small-s2d", "modulo"),),
    ),
    "s2d": (
        (timed_run("tiny-s2d", "mantissa", loss=TINY_MANTISSA_LOSS),),
        (timed_run("tiny-s2d", "modulo"),),
        (timed_run("base-s2d", "mantissa"),),
        (timed_run("base-s2d", "modulo"),),
    ),
    "tiny-s2d-mantissa": (
        (timed_run("tiny-s2d", "mantissa", loss=TINY_MANTISSA_LOSS),),
        (timed_run("tiny-s2d", "mantissa"),),
    ),
    "large": tuple(
        (timed_run("large", encoding, label=FIRST_RUN),) for encoding in ("mantissa", "modulo")
    ),
    "large-more": tuple(
        (
            timed_run(
                "large", encoding, stage_steps=(0, 0, 2, 1),
                init_from=f"mantissanet-large-{FIRST_RUN}-{encoding}",
            ),
        )
        for encoding in ("mantissa", "modulo")
    ),
    "large-prior": tuple((config,) for config in _LARGE_PRIOR),
    "large-prior-more": tuple(
        (
            replace(
                config, stage_steps=(0, 0, 2, 1), init_from=config.name,
                label=f"{config.label}-more" if config.label else "more",
            ),  # fmt: skip
        )
        for config in _LARGE_PRIOR
    ),
    "tiny-s2d-more": (
        (
            timed_run(
                "tiny-s2d", "mantissa", stage_steps=(0, 0, 2, 1), label="more",
                init_from="mantissanet-tiny-s2d-mantissa",
            ),
        ),
        (
            timed_run(
                "tiny-s2d", "modulo", stage_steps=(0, 0, 2, 1),
                init_from=f"mantissanet-tiny-s2d-{FIRST_RUN}-modulo",
            ),
        ),
    ),
}

SHIPPED: tuple[TrainConfig, ...] = (
    TrainConfig(tier="small", encoding="mantissa", stage_steps=SMALL_STAGES),
    TrainConfig(tier="small", encoding="modulo", stage_steps=SMALL_STAGES),
    TrainConfig(tier="base", encoding="mantissa", stage_steps=BASE_STAGES, label=FIRST_RUN),
    TrainConfig(
        tier="base", encoding="mantissa", stage_steps=BASE_MORE_STAGES,
        init_from=f"mantissanet-base-{FIRST_RUN}-mantissa",
    ),
    TrainConfig(
        tier="base", encoding="mantissa", stage_steps=BASE_NOISE_STAGES, max_read_noise=0.02,
        init_from="mantissanet-base-mantissa",
    ),
    TrainConfig(
        tier="small-s2d", encoding="mantissa", stage_steps=SMALL_S2D_STAGES, label=FIRST_RUN
    ),
    TrainConfig(
        tier="small-s2d", encoding="mantissa", stage_steps=SMALL_S2D_MORE_STAGES,
        init_from=f"mantissanet-small-s2d-{FIRST_RUN}-mantissa",
    ),
    TrainConfig(tier="small-s2d", encoding="modulo", stage_steps=SMALL_S2D_STAGES),
    TrainConfig(
        tier="tiny", encoding="mantissa", loss=TINY_MANTISSA_LOSS, stage_steps=TINY_STAGES
    ),
    TrainConfig(tier="tiny", encoding="modulo", stage_steps=TINY_STAGES),
    TrainConfig(tier="tiny", encoding="mantissa", stage_steps=TINY_STAGES, max_read_noise=0.02),
    TrainConfig(
        tier="small", encoding="mantissa", stage_steps=SMALL_NOISE_STAGES, max_read_noise=0.02,
        init_from="mantissanet-small-mantissa",
    ),
    *unmodnet_chain("mantissa"),
    *unmodnet_chain("modulo"),
    timed_run("base", "modulo", stage_steps=BASE_MODULO_STAGES, precision="bf16"),
    timed_run("tiny-s2d", "mantissa", stage_steps=TINY_S2D_MANTISSA_STAGES, precision="bf16"),
    timed_run(
        "tiny-s2d", "modulo", stage_steps=TINY_S2D_MODULO_STAGES, precision="bf16",
        label=FIRST_RUN,
    ),
    timed_run(
        "tiny-s2d", "modulo", stage_steps=TINY_S2D_MORE_STAGES, precision="bf16",
        init_from=f"mantissanet-tiny-s2d-{FIRST_RUN}-modulo",
    ),
    *large_chain("mantissa"),
    *large_chain("modulo"),
)
