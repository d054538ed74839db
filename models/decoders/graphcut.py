"""Graph-cut unwrapping (PUMA, Bioucas-Dias & Valadao 2007), as ModuloCam uses it.

The unwrapped value is ``u = K + m`` (wrap units; ``K`` integer, ``m`` in [0, 1)).
PUMA minimises the clique energy

    E(K) = sum over 4-neighbour pairs (i, j) of |u_j - u_i| ** p

by a sequence of binary moves: each move lets every pixel either keep ``K`` or
add one jump ``s`` (``K += s * delta``, ``delta`` in {0, 1}), choosing the
``delta`` of least energy with one s-t minimum cut (PyMaxflow). Moves are
repeated until the energy stops decreasing. For a convex potential (``p >= 1``)
every pairwise term is submodular and the unit-jump moves reach the global
minimum; for ``p < 1`` (discontinuity-preserving, not convex) non-submodular
terms are truncated to zero and a move is kept only if the true energy drops.

The decoder starts the moves from the ``itoh`` decoder's answer (least-squares
unwrapping, exact on smooth scenes), so PUMA only has to fix its errors;
``start="zeros"`` is the paper's all-zero start (at least one move per wrap,
slower; the same minimum when ``p >= 1``).

``K`` is known only up to a constant; :func:`anchor_winding` fixes it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Literal

import maxflow
import numpy as np
from numpy.typing import NDArray

from models.decoders.base import Decoder, anchor_winding
from models.decoders.classical import check_plane, least_squares_unwrap, relative_winding
from models.decoders.registry import DecoderSpec
from models.errors import InvalidInputError
from models.formation import SensorParams

#: A move must lower the energy by more than this (relative) to count as progress.
_REL_TOL = 1e-12
#: Cost per pixel and wrap of K outside :attr:`PumaEnergy.bounds`: far above what any
#: move can gain at a pixel (its four pairs change by at most a wrap each, at weight 1).
OUT_OF_BOUNDS_COST = 1e6
Start = Literal["itoh", "zeros"]


@dataclass(frozen=True)
class PumaResult:
    """Relative winding numbers (int64, H x W, minimum 0), the energy after each
    accepted move (``energies[0]`` is the energy of the start) and the min-cuts run."""

    winding: NDArray[np.int64]
    energies: list[float]
    moves: int


def _check_settings(p: float, jumps: tuple[int, ...], max_moves: int, start: str) -> None:
    if start not in ("itoh", "zeros"):
        raise InvalidInputError(f"start must be 'itoh' or 'zeros', got {start!r}")
    if not (np.isfinite(p) and 0.0 < p <= 4.0):
        raise InvalidInputError(f"the clique exponent p must be in (0, 4], got {p}")
    if not jumps or any(int(s) != s or s == 0 for s in jumps):
        raise InvalidInputError(f"jump sizes must be non-zero integers, got {jumps}")
    if max_moves < 1:
        raise InvalidInputError(f"max_moves must be at least 1, got {max_moves}")


def _check_wrapped(m: NDArray[np.floating]) -> NDArray[np.float64]:
    """``m`` as a float64 H x W map in [0, 1], or a clear error."""
    arr = np.asarray(m)
    check_plane(arr)
    if not np.issubdtype(arr.dtype, np.floating):
        raise InvalidInputError(
            f"m must be floats in [0, 1) (wrap units), got dtype {arr.dtype}; "
            "dequantize the codes first"
        )
    arr = arr.astype(np.float64)
    if arr.min() < 0.0 or arr.max() > 1.0:
        raise InvalidInputError(
            "m must be within [0, 1] (the fractional part of u); "
            f"got values in [{arr.min():.4g}, {arr.max():.4g}]"
        )
    return arr


def _differences(u: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unwrapped differences to the right and lower neighbour (wrap units)."""
    return u[:, 1:] - u[:, :-1], u[1:, :] - u[:-1, :]


#: Per-pair weights of the clique energy: (to the right neighbour, H x W-1; to the lower
#: neighbour, H-1 x W). None weighs every pair 1.
PairWeights = tuple[NDArray[np.float64], NDArray[np.float64]] | None


def clique_energy(u: NDArray[np.float64], p: float, weights: PairWeights = None) -> float:
    """``E = sum w |u_j - u_i| ** p`` over horizontal and vertical neighbour pairs."""
    right, down = _differences(u)
    if weights is None:
        return float(np.sum(np.abs(right) ** p) + np.sum(np.abs(down) ** p))
    return float(np.sum(weights[0] * np.abs(right) ** p) + np.sum(weights[1] * np.abs(down) ** p))


@dataclass(frozen=True)
class PumaEnergy:
    """The energy PUMA minimises over integer ``K`` (``u = K + m``):

    ``sum w_ij |u_j - u_i| ** p + prior_weight * sum c(K - prior)``

    ``weights`` (see :data:`PairWeights`) weighs each neighbour pair; ``prior`` (int
    H x W, optional) pulls ``K`` towards a known guess (``prior_weight``: one weight, or
    one per pixel, H x W), at ``c(d) = -d`` per pixel below
    it and ``c(d) = above_factor * d`` above it (convex for ``above_factor >= 0``, so
    the moves still reach the global minimum). Without a prior the energy does not
    change when ``K`` shifts by a constant.

    ``bounds`` (lowest K, highest K or None) confines ``K`` to the encoding's range:
    each wrap outside costs :data:`OUT_OF_BOUNDS_COST` per pixel, so no move from
    inside leaves it. The penalty is convex too: the moves reach the least energy
    *within* the range, where clipping an unconfined minimum afterwards broke the
    relative W it had found (a dark region put at W = -1 under a sky at 0 became a sky
    at the dark region's W).
    """

    p: float = 1.0
    weights: PairWeights = None
    prior: NDArray[np.int64] | None = None
    prior_weight: float | NDArray[np.float64] = 0.0
    above_factor: float = 1.0
    bounds: tuple[int, int | None] | None = None

    def __call__(self, winding: NDArray[np.int64], m: NDArray[np.float64]) -> float:
        return clique_energy(winding + m, self.p, self.weights) + self.prior_energy(winding)

    def prior_energy(
        self, winding: NDArray[np.int64], pixels: NDArray[np.int64] | None = None
    ) -> float:
        """The per-pixel terms: the prior ``prior_weight * sum c(K - prior)`` (0 without
        a prior) plus the :meth:`bound_cost` (0 without bounds), summed over every pixel
        of ``winding`` (H x W) or only over ``pixels`` (flat indices)."""
        at = _pixels_of(winding, pixels)
        total = 0.0 if self.bounds is None else float(self.bound_cost(at).sum())
        if self.prior is None:
            return total
        prior, weight = self._prior_at(pixels)
        cost = self.prior_cost(at - prior)
        if np.ndim(weight) == 0:
            return total + float(weight) * float(cost.sum())
        return total + float(np.sum(weight * cost))

    def bound_cost(self, winding: NDArray[np.int64]) -> NDArray[np.float64]:
        """Per pixel of ``winding`` (any shape): :data:`OUT_OF_BOUNDS_COST` per wrap of K
        outside :attr:`bounds` (0 inside, and everywhere without bounds)."""
        if self.bounds is None:
            return np.zeros(np.shape(winding))
        lowest, highest = self.bounds
        outside = np.maximum(lowest - winding, 0)
        if highest is not None:
            outside = outside + np.maximum(winding - highest, 0)
        return OUT_OF_BOUNDS_COST * outside

    def _prior_at(
        self, pixels: NDArray[np.int64] | None
    ) -> tuple[NDArray[np.int64], float | NDArray[np.float64]]:
        """``prior`` and ``prior_weight`` whole (``pixels`` None) or at ``pixels`` (flat
        indices; 1-D); only with a prior."""
        assert self.prior is not None
        weight = self.prior_weight
        if pixels is None:
            return self.prior, weight
        if np.ndim(weight) != 0:
            weight = np.ravel(weight)[pixels]
        return self.prior.ravel()[pixels], weight

    def prior_cost(self, offset: NDArray[np.int64]) -> NDArray[np.float64]:
        """``c(K - prior)`` per pixel, in units of ``prior_weight``: ``max(-d, above * d)``,
        which is ``c`` for any ``above_factor >= 0``."""
        return np.maximum(-offset, self.above_factor * offset)

    def prior_move_cost(
        self, winding: NDArray[np.int64], jump: int, pixels: NDArray[np.int64] | None = None
    ) -> NDArray[np.float64]:
        """Change of the per-pixel terms (:meth:`prior_energy`) at each pixel if its ``K``
        grows by ``jump``: for every pixel of ``winding`` (H x W), or only at ``pixels``
        (flat indices into it; 1-D, in their order)."""
        at = _pixels_of(winding, pixels)
        change = np.zeros(at.shape)
        if self.bounds is not None:
            change += self.bound_cost(at + jump) - self.bound_cost(at)
        if self.prior is not None:
            prior, weight = self._prior_at(pixels)
            offset = at - prior
            change += weight * (self.prior_cost(offset + jump) - self.prior_cost(offset))
        return change


def _pixels_of(
    winding: NDArray[np.int64], pixels: NDArray[np.int64] | None
) -> NDArray[np.int64]:
    """``winding`` whole (``pixels`` None) or at ``pixels`` (flat indices; 1-D)."""
    return winding if pixels is None else winding.ravel()[pixels]


def move_terms(
    d: NDArray[np.float64], jump: int, p: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Binary-move terms of the pairs with unwrapped difference ``d = u_j - u_i``.

    With ``delta_i, delta_j`` in {0, 1} and ``d' = d + jump (delta_j - delta_i)``, the
    pair's energy is ``A + c delta_i - c delta_j + w (1 - delta_i) delta_j`` with
    ``A = V(d)``, ``c = V(d - jump) - V(d)`` and ``w = V(d + jump) + V(d - jump) - 2 V(d)``.
    Returns ``(c, w)``; negative ``w`` (non-submodular, only for p < 1) is truncated to 0.
    """
    base = np.abs(d) ** p
    down = np.abs(d - jump) ** p
    up = np.abs(d + jump) ** p
    return down - base, np.maximum(up + down - 2.0 * base, 0.0)


def pair_capacities(
    c: NDArray[np.float64], w: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Edges and t-links of pair terms ``c delta_i - c delta_j + w (1 - delta_i) delta_j``.

    The term costs ``a = c`` when only ``i`` moves and ``b = w - c`` when only ``j``
    does. Where both are non-negative it is two edges (``i -> j`` of capacity ``b``,
    ``j -> i`` of capacity ``a``) and needs no t-link; a negative one moves to the
    t-links. On a near-optimal map most pairs are of the first kind, so the source
    and sink reach few pixels and the max-flow has little to push (about 10x faster
    on val-256 than writing every ``c`` as t-links). Returns ``(forward, backward,
    unary_shift)``: ``unary_shift`` is added to ``i``'s move cost and subtracted
    from ``j``'s.
    """
    a_neg = np.minimum(c, 0.0)
    b = w - c
    b_neg = np.minimum(b, 0.0)
    return np.maximum(b, 0.0) + a_neg, np.maximum(c, 0.0) + b_neg, a_neg - b_neg


@dataclass(frozen=True)
class MoveCapacities:
    """One binary move as an s-t graph on the pixel grid.

    ``unary`` (H x W): a pixel's cost of moving, paid from the source when positive
    and to the sink when negative; ``right`` / ``down``: (forward, backward) edge
    capacities to the right (H x W-1) and lower (H-1 x W) neighbour. The move's
    energy change is ``sum unary[moved] + cut`` (see :func:`pair_capacities`).
    """

    unary: NDArray[np.float64]
    right: tuple[NDArray[np.float64], NDArray[np.float64]]
    down: tuple[NDArray[np.float64], NDArray[np.float64]]


def move_capacities(
    winding: NDArray[np.int64], m: NDArray[np.float64], jump: int, energy: PumaEnergy
) -> MoveCapacities:
    """The s-t graph of the move that adds ``jump`` to a subset of ``winding``."""
    right, down = _differences(winding + m)
    c_right, w_right = move_terms(right, jump, energy.p)
    c_down, w_down = move_terms(down, jump, energy.p)
    if energy.weights is not None:
        c_right, w_right = c_right * energy.weights[0], w_right * energy.weights[0]
        c_down, w_down = c_down * energy.weights[1], w_down * energy.weights[1]
    forward_right, backward_right, shift_right = pair_capacities(c_right, w_right)
    forward_down, backward_down, shift_down = pair_capacities(c_down, w_down)
    unary = energy.prior_move_cost(winding, jump)
    unary[:, :-1] += shift_right
    unary[:, 1:] -= shift_right
    unary[:-1, :] += shift_down
    unary[1:, :] -= shift_down
    return MoveCapacities(unary, (forward_right, backward_right), (forward_down, backward_down))


#: An energy as a function of ``(winding, m) -> float``, what :func:`minimise` compares
#: moves by.
EnergyValue = Callable[[NDArray[np.int64], NDArray[np.float64]], float]

#: A move solver: ``(winding, m, jump, energy) -> moved`` (bool H x W), the pixels whose
#: K grows by ``jump`` in the best move it can find.
MoveSolver = Callable[[NDArray[np.int64], NDArray[np.float64], int, PumaEnergy], NDArray[np.bool_]]


def best_pixel_move(
    winding: NDArray[np.int64], m: NDArray[np.float64], jump: int, energy: PumaEnergy
) -> NDArray[np.bool_]:
    """The pixels whose K should grow by ``jump``: the minimum cut of one binary move
    over every pixel (the exact best move)."""
    return cut_pixels(move_capacities(winding, m, jump, energy))


def cut_pixels(capacities: MoveCapacities) -> NDArray[np.bool_]:
    """The pixels (H x W) on the moving side of the minimum cut of ``capacities``."""
    shape = capacities.unary.shape
    index = np.arange(capacities.unary.size).reshape(shape)
    (forward_right, backward_right), (forward_down, backward_down) = (
        capacities.right, capacities.down
    )
    edges = (
        (
            index[:, :-1].ravel(), index[:, 1:].ravel(),
            forward_right.ravel(), backward_right.ravel(),
        ),
        (index[:-1].ravel(), index[1:].ravel(), forward_down.ravel(), backward_down.ravel()),
    )
    return min_cut(capacities.unary.ravel(), edges).reshape(shape)


#: Edges of an s-t graph: tail nodes, head nodes, capacity tail -> head and head -> tail.
Edges = tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]


def min_cut(unary: NDArray[np.float64], edges: Iterable[Edges]) -> NDArray[np.bool_]:
    """The nodes (one per entry of 1-D ``unary``) on the moving side of the minimum cut of
    a binary move: a node pays ``unary`` when it moves (from the source when positive, to
    the sink when negative), an edge its capacity when it is cut. The pixel, band and
    region moves all cut their graphs here.

    Each pair is one edge with its capacity in both directions (``add_edges``): at
    256x256 that built the pixel graph in 1.9 instead of 6.2 ms and cut it in 8.9
    instead of 15.5 ms, against a grid edge per direction (``add_grid_edges``, which
    adds a zero-capacity reverse arc to each), with the same cut."""
    graph = maxflow.GraphFloat()
    # The first nodes of a graph are numbered 0, 1, ...: node i is entry i of ``unary``.
    nodes = graph.add_nodes(unary.size)
    for tails, heads, forward, backward in edges:
        graph.add_edges(tails, heads, forward, backward)
    # Source capacity is paid when delta = 1 (sink side), sink capacity when delta = 0.
    graph.add_grid_tedges(nodes, np.maximum(unary, 0.0), np.maximum(-unary, 0.0))
    graph.maxflow()
    return graph.get_grid_segments(nodes)


def accepts(value: float, current: float) -> bool:
    """Whether a move to energy ``value`` lowers ``current`` by more than rounding."""
    return value < current - _REL_TOL * abs(current)


def minimise(
    m: NDArray[np.float64],
    winding: NDArray[np.int64],
    energy: PumaEnergy,
    jumps: tuple[int, ...],
    max_moves: int,
    solver: MoveSolver = best_pixel_move,
    value: EnergyValue | None = None,
) -> PumaResult:
    """PUMA's binary moves from ``winding`` (absolute K, not normalised).

    The jump sizes are tried in turn, cyclically; each move is found by ``solver``
    (one min-cut) and kept when it lowers the energy. It stops once every jump size
    in a row failed, or after ``max_moves`` min-cuts. ``value`` (default ``energy``)
    is what moves are compared by and what ``energies`` records: a solver whose moves
    leave part of the frame alone may pass the share of the energy they can change
    (:meth:`models.decoders.band_moves.BandGraph.moves`). A move must then gain more
    than :func:`accepts`' tolerance of that share, not of the whole energy, so a gain
    between the two is kept where comparing the whole energy refuses it.
    """
    value = value or energy
    energies = [value(winding, m)]
    moves = 0
    failed = 0
    while failed < len(jumps) and moves < max_moves:
        jump = jumps[moves % len(jumps)]
        moves += 1
        candidate = winding + jump * solver(winding, m, jump, energy).astype(np.int64)
        reached = value(candidate, m)
        if not accepts(reached, energies[-1]):
            failed += 1
            continue
        failed = 0
        winding = candidate
        energies.append(reached)
    return PumaResult(winding, energies, moves)


def _check_start(start: NDArray[np.integer], shape: tuple[int, ...]) -> NDArray[np.int64]:
    """A start winding map as int64 of ``shape``, or a clear error."""
    winding = np.asarray(start)
    if winding.shape != shape or winding.dtype.kind not in "iu":
        raise InvalidInputError(
            f"the start winding map must be integers of shape {shape}, "
            f"got {winding.dtype} {winding.shape}"
        )
    return winding.astype(np.int64)


def puma_unwrap(
    m: NDArray[np.floating],
    p: float = 1.0,
    jumps: tuple[int, ...] = (1,),
    max_moves: int = 500,
    start: NDArray[np.integer] | None = None,
) -> PumaResult:
    """Unwrap ``m`` (H x W, wrap units in [0, 1)) by PUMA; relative ``K``, min 0.

    ``jumps`` are the jump sizes (tried in turn, see :func:`minimise`); ``max_moves``
    bounds the total number of min-cuts; ``start`` is the first ``K`` (integers, same
    shape as ``m``; all zeros when None).
    """
    _check_settings(p, jumps, max_moves, "zeros")
    m = _check_wrapped(m)
    winding = np.zeros(m.shape, np.int64) if start is None else _check_start(start, m.shape)
    result = minimise(m, winding, PumaEnergy(p), jumps, max_moves)
    return PumaResult(result.winding - result.winding.min(), result.energies, result.moves)


class GraphCutDecoder(Decoder):
    """PUMA graph-cut unwrapping with an ``|du| ** p`` clique potential, then anchoring."""

    name = "graphcut"

    def __init__(
        self,
        p: float = 1.0,
        jumps: tuple[int, ...] = (1,),
        max_moves: int = 500,
        start: Start = "itoh",
    ) -> None:
        _check_settings(p, jumps, max_moves, start)
        self.p = p
        self.jumps = jumps
        self.max_moves = max_moves
        self.start: Start = start

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        """Winding numbers (int64, H x W) of one channel of ``m`` in [0, 1)."""
        return self.explain_winding(m, params)[0]

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """Winding numbers plus the PUMA run: min-cuts made, start and final energy."""
        m = _check_wrapped(m)
        start = None if self.start == "zeros" else relative_winding(least_squares_unwrap(m), m)
        result = puma_unwrap(m, self.p, self.jumps, self.max_moves, start)
        facts = {
            "moves": result.moves,
            "start_energy": result.energies[0],
            "energy": result.energies[-1],
        }
        return anchor_winding(result.winding, params), facts


def specs() -> list[DecoderSpec]:
    """The graph-cut decoder for the registry."""
    return [
        DecoderSpec(
            name="graphcut",
            kind="classical",
            description=(
                "PUMA graph-cut unwrapping (ModuloCam baseline): L1 clique energy minimised "
                "by max-flow binary moves; no training, slower than itoh, robust to noise"
            ),
            factory=GraphCutDecoder,
        )
    ]
