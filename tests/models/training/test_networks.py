"""Tests of models/training/networks.py: shapes, the Laplacian, wrap edges, tiers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.training import networks as nets


@pytest.mark.parametrize("tier", sorted(nets.TIERS))
def test_every_tier_maps_m_to_logits_and_edges(tier: str) -> None:
    torch.manual_seed(0)
    model = nets.MantissaNet(nets.TIERS[tier]).eval()
    height, width = 2 * nets.multiple(nets.TIERS[tier]), 3 * nets.multiple(nets.TIERS[tier])
    with torch.no_grad():
        logits, edges = model(torch.rand(2, 1, height, width))
    assert logits.shape == (2, nets.NUM_CLASSES, height, width)
    assert edges.shape == (2, 1, height, width)
    assert edges.min() >= 0 and edges.max() <= 1
    assert torch.isfinite(logits).all()


def test_tiers_grow_in_parameters() -> None:
    counts = [
        nets.parameter_count(nets.MantissaNet(nets.TIERS[t]))
        for t in ("tiny", "small", "base", "large")
    ]
    assert counts == sorted(counts) and counts[0] > 1000


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_space_to_depth_round_trips_and_keeps_each_block_together(factor: int) -> None:
    x = torch.arange(2 * 3 * 8 * 12, dtype=torch.float32).reshape(2, 3, 8, 12)
    packed = nets.space_to_depth(x, factor)
    assert packed.shape == (2, 3 * factor**2, 8 // factor, 12 // factor)
    assert torch.equal(nets.depth_to_space(packed, factor), x)
    block = x[0, 0, :factor, :factor].flatten()
    assert torch.equal(packed[0, : factor**2, 0, 0], block)


def test_a_half_resolution_tier_keeps_one_prediction_per_pixel() -> None:
    """An unshuffled tier's output differs between the 4 pixels of a 2 x 2 block."""
    torch.manual_seed(0)
    tier = next(t for t in nets.TIERS.values() if t.unshuffle == 2)
    model = nets.MantissaNet(tier).eval()
    with torch.no_grad():
        logits, edges = model(torch.rand(1, 1, 64, 64))
    blocks = nets.space_to_depth(logits[:, :1], 2)[0]
    assert (blocks[0] != blocks[1]).float().mean() > 0.9
    assert nets.multiple(tier) == 2 * nets.MULTIPLE


@pytest.mark.parametrize("tier", sorted(nets.TIERS))
def test_classes_are_the_argmax_of_the_logits(tier: str) -> None:
    torch.manual_seed(1)
    model = nets.MantissaNet(nets.TIERS[tier]).eval()
    size = 2 * nets.multiple(nets.TIERS[tier])
    m = torch.rand(2, 1, size, size + nets.multiple(nets.TIERS[tier]))
    with torch.no_grad():
        logits, _ = model(m)
        classes = model.classes(m)
    assert classes.dtype == torch.int64 and classes.shape == (2, 1, *m.shape[2:])
    assert torch.equal(classes, logits.argmax(dim=1, keepdim=True))


def test_abs_laplacian_is_zero_on_flat_and_one_at_a_wrap_jump() -> None:
    m = torch.zeros(1, 1, 8, 8)
    assert nets.abs_laplacian(m).abs().max() == 0
    m[:, :, :, 4:] = 0.9
    lap = nets.abs_laplacian(m)
    assert torch.allclose(lap[0, 0, :, 3], torch.full((8,), 0.9))
    assert lap[0, 0, :, :3].abs().max() == 0


def test_wrap_edges_mark_both_sides_of_every_w_change() -> None:
    rng = np.random.default_rng(1)
    winding = rng.integers(0, 3, size=(1, 1, 9, 7))
    edges = nets.wrap_edges(torch.from_numpy(winding))[0, 0].numpy()
    w = winding[0, 0]
    expected = np.zeros(w.shape, bool)
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        shifted = np.full(w.shape, -1)
        ys = slice(max(dy, 0), w.shape[0] + min(dy, 0))
        yd = slice(max(-dy, 0), w.shape[0] + min(-dy, 0))
        xs = slice(max(dx, 0), w.shape[1] + min(dx, 0))
        xd = slice(max(-dx, 0), w.shape[1] + min(-dx, 0))
        shifted[yd, xd] = w[ys, xs]
        expected |= (shifted >= 0) & (shifted != w)
    np.testing.assert_array_equal(edges.astype(bool), expected)


def test_region_non_local_needs_the_pool_multiple() -> None:
    block = nets.RegionNonLocal(8)
    out = block(torch.rand(1, 8, nets.POOL * 2, nets.POOL * 3))
    assert out.shape == (1, 8, nets.POOL * 2, nets.POOL * 3)
