"""Tests of models/decoders/adaptive_policy.py: what ``auto`` runs at each quality."""

from __future__ import annotations

import math

import pytest

from models.decoders import available_decoders
from models.decoders.adaptive_policy import (
    JOINT_COLOUR,
    NET_BY_PSNR,
    QUALITIES,
    REFINEMENT,
    TIER_LADDER,
    measured_psnr,
    most_accurate_net,
    net_gflops,
)
from models.decoders.registry import DecoderSpec
from models.formation import SensorParams

MANTISSA = SensorParams(encoding="mantissa", alpha=2.0, bits=8)


def test_every_quality_has_a_ladder_and_a_budget() -> None:
    assert set(TIER_LADDER) == set(REFINEMENT) == set(QUALITIES)
    assert set(NET_BY_PSNR) | set(JOINT_COLOUR) <= set(QUALITIES)
    assert REFINEMENT["fast"] == 0 < REFINEMENT["balanced"] < REFINEMENT["best"]


def test_a_card_without_figures_states_nothing() -> None:
    bare = DecoderSpec("mantissanet-none", "learned", "no card", lambda: None)
    assert measured_psnr(bare, "mantissa") is None
    assert measured_psnr(bare, "mantissa", refined=True) is None
    assert math.isinf(net_gflops(bare, "mantissa"))


def test_the_cost_cap_leaves_out_expensive_nets() -> None:
    expensive = [
        spec.name
        for spec in available_decoders()
        if spec.name.startswith("mantissanet-") and net_gflops(spec, "mantissa") > 4.0
    ]
    chosen = {most_accurate_net(MANTISSA, cap) for cap in (0.0, 4.0)}
    assert chosen.isdisjoint(expensive)
    assert most_accurate_net(MANTISSA, 0.0) is None


def test_the_uncapped_choice_has_the_highest_stated_psnr() -> None:
    nets = [s for s in available_decoders() if s.name.startswith("mantissanet-")]
    refined = {s.name: measured_psnr(s, "mantissa", refined=True) for s in nets}
    stated = {name: psnr for name, psnr in refined.items() if psnr is not None}
    if not stated:
        pytest.skip("no shipped model card states a refined val-256 PSNR")
    assert most_accurate_net(MANTISSA) == max(stated, key=stated.__getitem__)
