"""The PyTorch networks: wrap-edge net, MantissaCam winding net (tiers), UnModNet mask net.

All nets take ``m`` (wrapped values in [0, 1), ``N x 1 x H x W``, float32) with
``H`` and ``W`` multiples of :data:`MULTIPLE` (times the tier's ``unshuffle``, see
:func:`multiple`); the runtime pads to it.

A tier with ``unshuffle = 2`` runs the whole net at half resolution: ``m`` and its
Laplacian are rearranged space-to-depth (each 2 x 2 block becomes 4 channels), and the
outputs depth-to-space back, so every pixel keeps its own prediction while no layer
runs at full resolution, where the narrow layers are memory bound (``bench.profile``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

#: Inputs must be a multiple of this (4 stride-2 downsamplings, non-local pooling 8).
MULTIPLE = 16
#: Region size of the non-local blocks: attention runs over ``POOL x POOL`` averaged regions.
POOL = 8
#: Winding classes 0 .. NUM_CLASSES - 1 (val-256 modulo reaches W = 16).
NUM_CLASSES = 17


@dataclass(frozen=True)
class Tier:
    """Width and depth of a winding-net tier (and of its edge net)."""

    name: str
    stem: int
    widths: tuple[int, int, int, int, int]
    depth: int
    edge_width: int
    edge_blocks: int
    unshuffle: int = 1


TIERS: dict[str, Tier] = {
    "tiny": Tier("tiny", 8, (8, 16, 24, 32, 32), 1, 8, 2),
    "small": Tier("small", 12, (16, 24, 32, 48, 64), 1, 12, 3),
    "base": Tier("base", 16, (24, 32, 48, 64, 96), 2, 16, 4),
    "small-s2d": Tier("small-s2d", 12, (16, 24, 32, 48, 64), 1, 12, 3, unshuffle=2),
    "tiny-s2d": Tier("tiny-s2d", 8, (8, 16, 24, 32, 32), 1, 8, 2, unshuffle=2),
    "base-s2d": Tier("base-s2d", 16, (24, 32, 48, 64, 96), 2, 16, 4, unshuffle=2),
    "large": Tier("large", 32, (48, 64, 96, 128, 160), 2, 24, 4),
}


def space_to_depth(x: Tensor, factor: int) -> Tensor:
    """Each ``factor x factor`` block to ``factor**2`` channels (identity for 1)."""
    return x if factor == 1 else F.pixel_unshuffle(x, factor)


def depth_to_space(x: Tensor, factor: int) -> Tensor:
    """The inverse of :func:`space_to_depth`."""
    return x if factor == 1 else F.pixel_shuffle(x, factor)


def multiple(tier: Tier) -> int:
    """Height and width of an input must be a multiple of this (pixels)."""
    return MULTIPLE * tier.unshuffle


def abs_laplacian(m: Tensor) -> Tensor:
    """``|Laplacian m|`` (4-neighbour, replicate borders), clipped to [0, 1]."""
    padded = F.pad(m, (1, 1, 1, 1), mode="replicate")
    lap = (
        padded[:, :, :-2, 1:-1]
        + padded[:, :, 2:, 1:-1]
        + padded[:, :, 1:-1, :-2]
        + padded[:, :, 1:-1, 2:]
        - 4 * m
    )
    return lap.abs().clamp(0.0, 1.0)


def conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution, batch norm, ReLU."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU()
    )


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with a skip (the edge net's body)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            conv_bn_relu(width, width), nn.Conv2d(width, width, 3, 1, 1, bias=False),
            nn.BatchNorm2d(width),
        )  # fmt: skip

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(x + self.body(x))


class Bottleneck(nn.Module):
    """Residual bottleneck block: 1x1 reduce, 3x3, 1x1 expand, skip."""

    def __init__(self, width: int) -> None:
        super().__init__()
        inner = max(width // 2, 4)
        self.body = nn.Sequential(
            nn.Conv2d(width, inner, 1, bias=False), nn.BatchNorm2d(inner), nn.ReLU(),
            conv_bn_relu(inner, inner),
            nn.Conv2d(inner, width, 1, bias=False), nn.BatchNorm2d(width),
        )  # fmt: skip

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(x + self.body(x))


class RegionNonLocal(nn.Module):
    """Non-local (self-attention) block over ``POOL x POOL`` averaged regions, residual."""

    def __init__(self, width: int) -> None:
        super().__init__()
        inner = max(width // 2, 4)
        self.query = nn.Conv2d(width, inner, 1)
        self.key = nn.Conv2d(width, inner, 1)
        self.value = nn.Conv2d(width, inner, 1)
        self.out = nn.Conv2d(inner, width, 1)
        self.scale = inner**-0.5

    def forward(self, x: Tensor) -> Tensor:
        pooled = F.avg_pool2d(x, POOL)
        n, _, h, w = pooled.shape
        q = self.query(pooled).flatten(2).transpose(1, 2)
        k = self.key(pooled).flatten(2)
        v = self.value(pooled).flatten(2).transpose(1, 2)
        attention = torch.softmax(torch.bmm(q, k) * self.scale, dim=-1)
        y = torch.bmm(attention, v).transpose(1, 2).reshape(n, -1, h, w)
        return x + F.interpolate(self.out(y), scale_factor=POOL, mode="nearest")


class SqueezeExcitation(nn.Module):
    """Channel re-weighting from globally pooled features."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.fc = nn.Sequential(
            nn.Conv2d(width, max(width // 4, 4), 1), nn.ReLU(),
            nn.Conv2d(max(width // 4, 4), width, 1), nn.Sigmoid(),
        )  # fmt: skip

    def forward(self, x: Tensor) -> Tensor:
        return x * self.fc(x.mean(dim=(2, 3), keepdim=True))


class AttentionGate(nn.Module):
    """Attention U-Net gate: weights a skip connection by the decoder's gating signal."""

    def __init__(self, skip: int, gate: int) -> None:
        super().__init__()
        inner = max(skip // 2, 4)
        self.skip = nn.Conv2d(skip, inner, 1, bias=False)
        self.gate = nn.Conv2d(gate, inner, 1)
        self.psi = nn.Sequential(nn.ReLU(), nn.Conv2d(inner, 1, 1), nn.Sigmoid())

    def forward(self, skip: Tensor, gate: Tensor) -> Tensor:
        return skip * self.psi(self.skip(skip) + self.gate(gate))


def stem(c_out: int, c_in: int = 1) -> nn.Sequential:
    """7x7 convolution, instance norm, ReLU on a ``c_in``-channel map."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 7, 1, 3), nn.InstanceNorm2d(c_out), nn.ReLU())


class EdgeNet(nn.Module):
    """UnModNet's modulo edge separator: wrap-edge probability from ``[m, |Laplacian m|]``.

    Output = ``clamp(|Laplacian m| + tanh(residual), 0, 1)``: the net corrects the
    Laplacian, which already peaks at wrap edges and at real (texture) edges. With
    ``unshuffle = f`` the residual is computed at 1/f resolution (module docstring).
    """

    def __init__(self, width: int, blocks: int, unshuffle: int = 1) -> None:
        super().__init__()
        self.unshuffle = unshuffle
        self.head = conv_bn_relu(2 * unshuffle**2, width)
        self.body = nn.Sequential(*(ResidualBlock(width) for _ in range(blocks)))
        self.attention = RegionNonLocal(width)
        self.tail = nn.Conv2d(width, unshuffle**2, 3, 1, 1)

    def forward(self, m: Tensor) -> Tensor:
        lap = abs_laplacian(m)
        x = space_to_depth(torch.cat([m, lap], dim=1), self.unshuffle)
        residual = self.tail(self.attention(self.body(self.head(x))))
        return (lap + torch.tanh(depth_to_space(residual, self.unshuffle))).clamp(0.0, 1.0)


class WindingNet(nn.Module):
    """The MantissaCam winding net: W logits (``NUM_CLASSES`` channels) in one pass.

    Features of ``m`` and of the edge map (7x7 conv + InstanceNorm + ReLU; non-local
    block on the edge branch), concatenated, squeeze-excitation, then an attention
    U-Net with 4 strided downsamplings and residual bottleneck blocks.
    """

    def __init__(self, tier: Tier, outputs: int = NUM_CLASSES) -> None:
        super().__init__()
        w = tier.widths
        self.unshuffle = tier.unshuffle
        inputs = tier.unshuffle**2
        self.m_branch = stem(tier.stem, inputs)
        self.edge_branch = nn.Sequential(stem(tier.stem, inputs), RegionNonLocal(tier.stem))
        self.se = SqueezeExcitation(2 * tier.stem)
        self.enter = conv_bn_relu(2 * tier.stem, w[0])
        self.down = nn.ModuleList(conv_bn_relu(w[i], w[i + 1], 2) for i in range(4))
        self.encode = nn.ModuleList(
            nn.Sequential(*(Bottleneck(w[i]) for _ in range(tier.depth))) for i in range(5)
        )
        self.gates = nn.ModuleList(AttentionGate(w[i], w[i + 1]) for i in range(4))
        self.merge = nn.ModuleList(conv_bn_relu(w[i] + w[i + 1], w[i]) for i in range(4))
        self.head = nn.Conv2d(w[0], outputs * inputs, 1)

    def forward(self, m: Tensor, edges: Tensor) -> Tensor:
        return depth_to_space(self.block_logits(m, edges), self.unshuffle)

    def block_logits(self, m: Tensor, edges: Tensor) -> Tensor:
        """Logits at the net's working resolution (``outputs x unshuffle**2`` channels,
        laid out as :func:`depth_to_space` expects)."""
        m, edges = (space_to_depth(t, self.unshuffle) for t in (m, edges))
        x = torch.cat([self.m_branch(m), self.edge_branch(edges)], dim=1)
        x = self.encode[0](self.enter(self.se(x)))
        skips = [x]
        for level in range(4):
            x = self.encode[level + 1](self.down[level](x))
            skips.append(x)
        for level in reversed(range(4)):
            skip = skips[level]
            up = F.interpolate(x, size=skip.shape[2:], mode="nearest")
            x = self.merge[level](torch.cat([self.gates[level](skip, up), up], dim=1))
        return self.head(x)


class MantissaNet(nn.Module):
    """Edge net + winding net end to end: ``m -> (W logits, edge map)``."""

    def __init__(self, tier: Tier, outputs: int = NUM_CLASSES) -> None:
        super().__init__()
        self.tier = tier
        self.edge = EdgeNet(tier.edge_width, tier.edge_blocks, tier.unshuffle)
        self.winding = WindingNet(tier, outputs)

    def forward(self, m: Tensor) -> tuple[Tensor, Tensor]:
        edges = self.edge(m)
        return self.winding(m, edges), edges

    def classes(self, m: Tensor) -> Tensor:
        """The most likely W class per pixel (int64, ``N x 1 x H x W``). A half-resolution
        tier takes the argmax before moving depth to space: 4 channels to rearrange
        instead of ``4 x NUM_CLASSES``."""
        factor = self.tier.unshuffle
        logits = self.winding.block_logits(m, self.edge(m))
        if factor == 1:
            return logits.argmax(dim=1, keepdim=True)
        n, channels, height, width = logits.shape
        blocks = logits.reshape(n, channels // factor**2, factor**2, height, width)
        return depth_to_space(blocks.argmax(dim=1).float(), factor).long()


class UnModMaskNet(nn.Module):
    """UnModNet's rollover net: the logit that a pixel rolls over one more wrap, from the
    current partial unwrapping ``u`` (scaled by ``1 / NUM_CLASSES``) and the edge map,
    by the winding net's attention U-Net with one output.

    Measured (val-256, 2026-11-25): the earlier rollover net, residual blocks of the
    edge net's width, saw too little of the frame to tell which side of a wrap edge
    rolls: its first pass found almost no rollover (80.1% W, as W = 0 everywhere).
    """

    def __init__(self, tier: Tier) -> None:
        super().__init__()
        self.net = WindingNet(tier, outputs=1)

    def forward(self, u: Tensor, edges: Tensor) -> Tensor:
        return self.net(u / NUM_CLASSES, edges)


class UnModNet(nn.Module):
    """UnModNet: the edge net + the rollover net, applied iteratively at inference.

    ``forward(m, winding)`` gives the rollover logits of the state ``m + winding``
    and the edge map; the runtime adds 1 to W where the logit is > 0 (each pass only
    inside the previous pass's rollovers), until no pixel rolls over (at most 15 passes).
    """

    def __init__(self, tier: Tier) -> None:
        super().__init__()
        self.tier = tier
        self.edge = EdgeNet(tier.edge_width, tier.edge_blocks)
        self.mask = UnModMaskNet(tier)

    def forward(self, m: Tensor, winding: Tensor) -> tuple[Tensor, Tensor]:
        edges = self.edge(m)
        return self.mask(m + winding, edges), edges


def wrap_edges(winding: Tensor) -> Tensor:
    """Ground-truth wrap edges (float 0/1): pixels whose W differs from a 4-neighbour."""
    w = winding.float()
    edges = torch.zeros_like(w)
    dy = (w[:, :, 1:] != w[:, :, :-1]).float()
    dx = (w[:, :, :, 1:] != w[:, :, :, :-1]).float()
    edges[:, :, 1:] = torch.maximum(edges[:, :, 1:], dy)
    edges[:, :, :-1] = torch.maximum(edges[:, :, :-1], dy)
    edges[:, :, :, 1:] = torch.maximum(edges[:, :, :, 1:], dx)
    edges[:, :, :, :-1] = torch.maximum(edges[:, :, :, :-1], dx)
    return edges


def parameter_count(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
