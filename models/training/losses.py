"""The training losses of the nets, per stage (:func:`step_losses`).

Stage 1 trains the edge net alone (BCE against the true wrap edges); stage 2 the
winding net on the true edges; stages 3 and 4 both end to end (winding loss +
:data:`EDGE_WEIGHT` x edge BCE). The winding loss is one of :data:`LOSSES`; UnModNet's
rollover net gets its pass loss (:func:`rollover_losses`) instead.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

from models.training.networks import NUM_CLASSES, MantissaNet, UnModNet, wrap_edges

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
EDGE_WEIGHT = 0.1


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
