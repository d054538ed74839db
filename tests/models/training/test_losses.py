"""Tests of models/training/losses.py: the winding, jump, risk and rollover losses."""

from __future__ import annotations

import math

import pytest
import torch

from models.training.losses import (
    HEAD_OUTPUTS,
    RISK_FLOOR,
    edge_bce,
    expected_log_mse,
    prediction_accuracy,
    rolled_out_state,
    rollover_losses,
    winding_jumps,
    winding_loss,
)
from models.training.networks import TIERS, UnModNet


def test_jumps_loss_is_zero_for_the_true_jumps_and_counts_them_right() -> None:
    winding = torch.tensor([[0, 0, 2], [0, 1, 3], [1, 1, 3]]).reshape(1, 1, 3, 3)
    along_cols, along_rows = winding_jumps(winding)
    output = torch.zeros(1, 2, 3, 3)
    output[:, :1, :, :-1] = along_cols
    output[:, 1:, :-1] = along_rows
    assert winding_loss(output, winding, "jumps").item() == 0.0
    assert prediction_accuracy(output, winding, "jumps").item() == 1.0
    output[0, 0, 0, 1] += 1.0
    assert winding_loss(output, winding, "jumps").item() > 0.0
    assert prediction_accuracy(output, winding, "jumps").item() == pytest.approx(11 / 12)


def test_ce_risk_adds_the_expected_log_mse_and_needs_the_errors() -> None:
    logits = torch.randn(2, HEAD_OUTPUTS["ce"], 4, 4, generator=torch.Generator().manual_seed(0))
    winding = torch.randint(0, HEAD_OUTPUTS["ce"], (2, 1, 4, 4))
    plain = winding_loss(logits, winding, "ce")
    errors = torch.zeros(2, HEAD_OUTPUTS["ce"], 4, 4)
    floor = math.log(RISK_FLOOR)
    torch.testing.assert_close(winding_loss(logits, winding, "ce-risk", errors, 2.0),
                               plain + 2.0 * floor)  # fmt: skip
    with pytest.raises(ValueError, match="needs the per-class errors"):
        winding_loss(logits, winding, "ce-risk")


def test_expected_log_mse_is_the_log_of_the_probability_weighted_error() -> None:
    # Two classes, one pixel: p = (0.75, 0.25) on errors (0, 8) expects an MSE of 2.
    logits = torch.log(torch.tensor([0.75, 0.25])).reshape(1, 2, 1, 1)
    errors = torch.tensor([0.0, 8.0]).reshape(1, 2, 1, 1)
    expected = math.log(2.0 + RISK_FLOOR)
    assert expected_log_mse(logits, errors).item() == pytest.approx(expected, rel=1e-6)


def test_rolled_out_passes_stay_inside_the_previous_ones() -> None:
    torch.manual_seed(0)
    model = UnModNet(TIERS["tiny"]).eval()
    m = torch.rand(2, 1, 32, 32)
    edges = model.edge(m)
    states = [rolled_out_state(model, m, edges, passes) for passes in range(4)]
    assert not states[0].any()
    for before, after in zip(states, states[1:], strict=False):
        grew = after - before
        assert set(grew.unique().tolist()) <= {0.0, 1.0}
    for previous, before, after in zip(states, states[1:], states[2:], strict=False):
        assert torch.all((after - before) <= (before - previous))


def test_own_states_train_from_the_models_answer() -> None:
    """With ``own_states = 1`` every batch starts from the model's own rolled-out state,
    so the targets are where the true W is above that state; with 0 the random
    ``min(W, k)`` states are used and the generator draws the same numbers as before."""
    torch.manual_seed(0)
    model = UnModNet(TIERS["tiny"]).eval()
    m = torch.rand(2, 1, 32, 32)
    winding = torch.randint(0, 3, (2, 1, 32, 32))
    edges = model.edge(m)
    plain = rollover_losses(model, m, winding, edges, torch.Generator().manual_seed(5))
    again = rollover_losses(model, m, winding, edges, torch.Generator().manual_seed(5), 0.0)
    assert torch.equal(plain[0], again[0])
    own_loss, own_accuracy = rollover_losses(
        model, m, winding, edges, torch.Generator().manual_seed(5), 1.0, 3
    )
    assert torch.isfinite(own_loss) and 0.0 <= float(own_accuracy) <= 1.0
    assert not torch.equal(own_loss, plain[0])


def test_edge_bce_runs_in_float32_under_bf16_autocast() -> None:
    edges = torch.tensor([0.0, 0.5, 1.0]).reshape(1, 1, 1, 3)
    truth = torch.tensor([0.0, 1.0, 1.0]).reshape(1, 1, 1, 3)
    plain = edge_bce(edges, truth)
    with torch.autocast("cpu", torch.bfloat16):
        autocast = edge_bce(edges.bfloat16(), truth)
    assert autocast.dtype == torch.float32
    torch.testing.assert_close(autocast, plain)
    assert plain.item() == pytest.approx(math.log(2) / 3, rel=1e-3)
