"""Learned decoders run with onnxruntime: ``mantissanet-<tier>`` and ``unmodnet``.

``mantissanet-*`` predicts W in one pass (or, for a net trained on the
per-neighbour jumps of W, the jumps, integrated into W); ``unmodnet`` starts from W = 0 and adds
the pixels its net says roll over once more, pass by pass (at most the card's
``max_passes``, 15).

Models are discovered from the JSON model cards in ``models/onnx/``; a decoder
picks the card of the frame's encoding. Each ONNX session is created once (per
decoder instance and encoding) and reused; intra-op threads come from the
environment variable ``MCAM_WORKER_THREADS`` (default 2), and ``MCAM_ORT_SPIN=1``
lets idle intra-op threads spin (see :func:`make_session`).

A frame is padded (reflected) to the net's multiple; frames larger than the
card's tile size are cut into overlapping tiles. W is global, so tiles are not
blended: each tile's integer offset is set by the median difference to the
already decoded pixels of its overlap, and only new pixels are written.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from models.decoders.base import ANCHOR_PERCENTILE, Decoder, anchor_winding, refuse_empty
from models.decoders.classical import HerraezDecoder, integrate_gradient, least_squares_unwrap
from models.decoders.registry import DecoderSpec
from models.errors import InvalidInputError
from models.formation import SensorParams, max_winding
from models.scene_analysis import neighbour_jumps, residue_map
from models.tile_reconcile import integrate_jumps

ONNX_DIR = Path(__file__).resolve().parents[1] / "onnx"
THREADS_ENV = "MCAM_WORKER_THREADS"
#: The environment variables that set a process's intra-op threads: onnxruntime's
#: (:data:`THREADS_ENV`, read when a session is made) and the numerical libraries'
#: (read when they load).
THREAD_VARIABLES = (THREADS_ENV, "OMP_NUM_THREADS")
DEFAULT_THREADS = 2
SPIN_ENV = "MCAM_ORT_SPIN"
#: The spellings of ``MCAM_ORT_SPIN`` (those pydantic reads as booleans, so the
#: worker's settings and the models agree).
SPIN_WORDS = {
    **dict.fromkeys(("1", "on", "t", "true", "y", "yes"), True),
    **dict.fromkeys(("0", "off", "f", "false", "n", "no"), False),
}
#: Overlap between neighbouring tiles, in pixels (a multiple of the net's multiple).
OVERLAP = 64
#: A frame is run whole when its longer side is at most the card's ``tile`` plus this
#: many px; larger ones are tiled. Tiled, a frame just over the tile took 2-4 runs of a
#: whole tile (the windows of ``auto``'s hard tiles are 288 px when four tiles wide).
#: Measured on the 512x512 frames of bench.tradeoff (2026-11-26, three alternating
#: rounds, medians): auto-fast 67 -> 55 ms, auto-balanced 150 -> 136 ms, the same W.
#: Tiles of 320 px for every larger frame too measured about even on W accuracy over
#: the nets (-7.8 to +3.4 points per net and frame set: which tile border lands on a
#: hard spot changes), so larger frames keep the card's tile.
WHOLE_RUN_SLACK = OVERLAP
#: The highest W one run of a ``mantissanet`` outputs: its classes are 0 .. 16
#: (``NUM_CLASSES`` in :mod:`models.training.networks`). UnModNet's is its card's
#: ``max_passes``; a net of jumps integrates them and has none.
TOP_CLASS = 16
#: The decoder of frames of which a net cannot output much (:data:`FALLBACK_SHARE`):
#: exact under the Itoh condition, and where residues break it it keeps the reliable
#: regions (a 512x512 log ramp of 1e-12 .. 1e30 with read noise 0.1: 99.8% of W right,
#: itoh 30%).
FALLBACK = HerraezDecoder()
#: A frame goes to :data:`FALLBACK` when more than this share of it lies beyond the W a
#: net outputs (:func:`share_beyond`): the share anchoring ignores. Below it (a lamp's
#: core), the net decodes the frame, whose glow ``<net>+puma`` lifts as it lifts any
#: region the net under-counts, and its details warn.
FALLBACK_SHARE = 0.05
#: Why a frame without residues was integrated rather than given to the net.
NO_RESIDUE = "no residue: the wrap edges were integrated (exact), the net was not run"


def worker_threads() -> int:
    """Intra-op threads for onnxruntime: ``MCAM_WORKER_THREADS`` or 2."""
    raw = os.environ.get(THREADS_ENV, str(DEFAULT_THREADS))
    if not raw.isdigit() or int(raw) < 1:
        raise InvalidInputError(f"{THREADS_ENV} must be a positive integer, got {raw!r}")
    return int(raw)


def ort_spinning() -> bool:
    """Whether idle onnxruntime intra-op threads spin: ``MCAM_ORT_SPIN`` is ``1`` (or
    ``true``, ``yes``, ``on``); unset or ``0``: they sleep."""
    raw = os.environ.get(SPIN_ENV, "0")
    spinning = SPIN_WORDS.get(raw.strip().lower())
    if spinning is None:
        raise InvalidInputError(f"{SPIN_ENV} must be 0 or 1 (or true / false), got {raw!r}")
    return spinning


#: Fields every model card has: what the runtime reads to serve and describe its model
#: (a card lacking one was accepted, then failed with a KeyError when used).
CARD_FIELDS: tuple[str, ...] = (
    "file", "decoder", "encoding", "family", "sha256", "multiple", "tile", "parameters",
    "gflops_256",
)


#: What each family's graph takes and gives (:mod:`models.training.export`): its input
#: names, and its output's element type by the card's ``output``.
GRAPH_INPUTS = {"mantissanet": ("m",), "unmodnet": ("m", "winding")}
GRAPH_OUTPUT_TYPES = {"winding": "tensor(int64)", "jumps": "tensor(float)"}
#: The encodings the nets decode (trained on; a clipped frame has nothing to unwrap).
LEARNED_ENCODINGS = ("mantissa", "modulo")
#: A card's counts and the least each may be: the px a frame is padded to a multiple of,
#: the side of the largest run (px; more than the tiles' :data:`OVERLAP`, so that tiles
#: advance), and UnModNet's most passes. At the first decode a multiple of 0 divided by
#: zero and text failed in int(); a tile of the overlap or less decoded only the last
#: tile, leaving the rest of a large frame at W = 0.
CARD_COUNTS = {"multiple": 1, "tile": OVERLAP + 1, "max_passes": 1}


def read_card(path: Path) -> dict[str, Any]:
    """The model card at ``path``, or :class:`InvalidInputError` naming the file when it
    is not one (not JSON text, not an object, or without :data:`CARD_FIELDS`) or is not
    usable (:func:`card_problems`), or cannot be read (a directory in its place, no read
    permission)."""
    try:
        card = json.loads(path.read_text())
    except OSError as exc:
        raise InvalidInputError(
            f"{path} cannot be read as a model card ({exc.strerror}): restore it, or move "
            "it out of the models folder"
        ) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidInputError(
            f"{path} is not a model card (JSON text, models/onnx/<name>.json): {exc}"
        ) from None
    missing = [name for name in CARD_FIELDS if not isinstance(card, dict) or name not in card]
    if missing:
        raise InvalidInputError(
            f"{path} is not a model card: it lacks {', '.join(missing)} "
            "(cards are models/onnx/<name>.json, written by mcam train export)"
        )
    problems = card_problems(card)
    if problems:
        raise InvalidInputError(
            f"{path} is not a usable model card: {'; '.join(problems)} (cards are written by "
            "mcam train export: restore it, or export its model again)"
        )
    return card


def card_problems(card: dict[str, Any]) -> list[str]:
    """What makes a card with :data:`CARD_FIELDS` unusable: an encoding, family or output
    the runtime does not run, a file not named for the card's encoding
    (:func:`encoding_problem`), an UnModNet card without ``max_passes``, or a count out
    of range (:data:`CARD_COUNTS`)."""
    problems = []
    if card["encoding"] not in LEARNED_ENCODINGS:
        problems.append(f"encoding {card['encoding']!r} is not one of {LEARNED_ENCODINGS}")
    elif problem := encoding_problem(card):
        problems.append(problem)
    if card["family"] not in GRAPH_INPUTS:
        problems.append(f"family {card['family']!r} is not one of {tuple(GRAPH_INPUTS)}")
    if card.get("output", "winding") not in GRAPH_OUTPUT_TYPES:
        problems.append(f"output {card['output']!r} is not one of {tuple(GRAPH_OUTPUT_TYPES)}")
    if card["family"] == "unmodnet" and "max_passes" not in card:
        problems.append("an unmodnet card needs max_passes")
    for name, least in CARD_COUNTS.items():
        value = card.get(name, least)
        if type(value) is not int or value < least:
            problems.append(f"{name} must be a whole number >= {least}, got {value!r}")
    return problems


def encoding_problem(card: dict[str, Any]) -> str | None:
    """Why the card's ``encoding`` is not that of its ``file``, or None. An export names
    a model's file ``<name>-<encoding>.onnx`` after the encoding it was trained on
    (:attr:`models.training.config.TrainConfig.name`, also for int8 models), and the
    sha256 only ties the file to the card: a card whose encoding was edited, or pointed
    at the file of another encoding with that file's sha256, was served as the card's
    encoding without an error. (Decoding cannot tell them apart: on val-256, 2026-11-28,
    the shipped small and tiny-s2d mantissa and modulo nets scored within half a point of
    winding accuracy of each other on either encoding's frames.)"""
    if Path(str(card["file"])).stem.endswith(f"-{card['encoding']}"):
        return None
    return (
        f"its encoding is {card['encoding']!r} but its file {card['file']!r} is not named "
        f"<name>-{card['encoding']}.onnx, as the export of a model trained on "
        f"{card['encoding']} frames is: the card's encoding or file was changed"
    )


def read_cards(
    onnx_dir: Path = ONNX_DIR, with_file: bool = True
) -> list[tuple[Path, dict[str, Any]]]:
    """Every model card (``*.json``) whose ONNX file exists (``with_file``, else whose
    file is missing), with its path, sorted by file name."""
    found = []
    for path in sorted(onnx_dir.glob("*.json")):
        card = read_card(path)
        if (onnx_dir / card["file"]).exists() == with_file:
            found.append((path, card))
    return found


def load_cards(onnx_dir: Path = ONNX_DIR) -> list[dict[str, Any]]:
    """Every model card (``*.json``) whose ONNX file exists, sorted by file name, with
    ``path`` set to its ONNX file. Each (decoder, encoding) has one model: two cards that
    claim the same are an InvalidInputError naming both, rather than one chosen silently."""
    claimed: dict[tuple[str, str], Path] = {}
    cards = []
    for path, card in read_cards(onnx_dir):
        key = (card["decoder"], card["encoding"])
        if key in claimed:
            raise InvalidInputError(
                f"model cards {claimed[key]} and {path} both serve decoder {key[0]!r} on "
                f"{key[1]} frames; remove (or move out of {onnx_dir}) the one that should "
                "not be used, with its .onnx"
            )
        claimed[key] = path
        cards.append({**card, "path": str(onnx_dir / card["file"])})
    return cards


class ModelFileError(OSError):
    """A model's ONNX file is missing, or not the file its card describes (cut short,
    corrupt, replaced, a Git LFS pointer, or a graph of another family). A fault of the
    installation, not of the caller (so not a :class:`McamError`): the CLI prints it as
    one line, as any file it cannot use, and a job that meets it fails at once as
    ``model_unavailable`` (no retry mends a file), dead-lettered with this error's text
    for the operator (:mod:`worker.job_processor`)."""


#: What to do about a model file that is not its card's.
RESTORE_ADVICE = (
    "restore it (git checkout -- models/onnx, or git lfs pull for LFS pointers), or "
    "export it again (mcam train export --force)"
)


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file (read in chunks)."""
    with path.open("rb") as file:
        return hashlib.file_digest(file, "sha256").hexdigest()


def check_model_file(card: dict[str, Any]) -> None:
    """A :class:`ModelFileError` naming the card's ONNX file (``card["path"]``) and what
    to do when it is gone or its sha256 is not the card's."""
    path = Path(card["path"])
    try:
        digest = sha256_of(path)
    except FileNotFoundError:
        raise ModelFileError(
            f"model file {path} (decoder {card['decoder']!r}, {card['encoding']} frames) is "
            f"missing; {RESTORE_ADVICE}"
        ) from None
    if digest != card["sha256"]:
        raise ModelFileError(
            f"model file {path} is not the one its card describes (sha256 {digest[:12]}..., "
            f"the card's {str(card['sha256'])[:12]}...): it is cut short, corrupt, replaced "
            f"or a Git LFS pointer; {RESTORE_ADVICE}"
        )


def check_graph(session: ort.InferenceSession, card: dict[str, Any]) -> None:
    """A :class:`ModelFileError` when the session's inputs and output type are not those
    of the card's family and ``output`` (:data:`GRAPH_INPUTS`, :data:`GRAPH_OUTPUT_TYPES`)."""
    output = card.get("output", "winding")
    expected = (GRAPH_INPUTS.get(card["family"]), GRAPH_OUTPUT_TYPES.get(output))
    found = (tuple(item.name for item in session.get_inputs()), session.get_outputs()[0].type)
    if found != expected:
        raise ModelFileError(
            f"model file {card['path']} takes inputs {list(found[0])} and gives a {found[1]}, "
            f"but its card describes a {card['family']} net with {output} output, which "
            f"takes {list(expected[0] or ())} and gives a {expected[1]}: the card does not "
            f"belong to this file; {RESTORE_ADVICE}"
        )


def open_model(card: dict[str, Any]) -> ort.InferenceSession:
    """The session of a card's ONNX file, checked to be the file the card describes
    (:func:`check_model_file`, :func:`check_graph`) so that a broken install is one clear
    error rather than onnxruntime's parse error or a wrong decode."""
    check_model_file(card)
    session = make_session(card["path"], worker_threads())
    check_graph(session, card)
    return session


def make_session(
    path: str | bytes, threads: int, profile_prefix: str | None = None
) -> ort.InferenceSession:
    """A CPU onnxruntime session of a model file (or its bytes) with ``threads`` intra-op
    threads (profiling to files starting with ``profile_prefix`` when given).

    Idle intra-op threads sleep unless ``MCAM_ORT_SPIN=1`` (:func:`ort_spinning`).
    Spinning pays only on cores nothing else uses. Measured on val-256 (2026-11-25, 2
    AMD EPYC cores, 2 threads), sleeping against spinning: quiet, mantissanet-small-s2d
    9.5 against 8.3 ms and auto-fast 11.9 against 10.7 ms; with the other core busy,
    10.8 against 17.6 ms and 14.3 against 21.3 ms (a spinning thread steals the core
    from the one doing the work)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry(
        "session.intra_op.allow_spinning", "1" if ort_spinning() else "0"
    )
    if profile_prefix is not None:
        options.enable_profiling = True
        options.profile_file_prefix = profile_prefix
    return ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])


def pad_to_multiple(m: NDArray[np.float32], multiple: int) -> NDArray[np.float32]:
    """Reflect-pad (edge-pad when too small to reflect) bottom/right to a multiple."""
    pad = [(0, -size % multiple) for size in m.shape]
    mode = "reflect" if all(p[1] < s for p, s in zip(pad, m.shape, strict=True)) else "edge"
    return np.pad(m, pad, mode=mode)


def tile_starts(size: int, tile: int, overlap: int) -> list[int]:
    """Start offsets of tiles of ``tile`` px covering ``size`` px with >= ``overlap`` overlap."""
    if size <= tile:
        return [0]
    stride = tile - overlap
    starts = list(range(0, size - tile, stride))
    return [*starts, size - tile]


def tiles(shape: tuple[int, int], tile: int, overlap: int) -> Iterator[tuple[slice, slice]]:
    """Row and column slices of overlapping tiles in raster order."""
    for top in tile_starts(shape[0], tile, overlap):
        for left in tile_starts(shape[1], tile, overlap):
            yield slice(top, min(top + tile, shape[0])), slice(left, min(left + tile, shape[1]))


def stitch_overlapping(
    shape: tuple[int, int], tile: int, overlap: int, predict: Any
) -> NDArray[np.int64]:
    """Run ``predict(rows, cols) -> W`` per tile and stitch with integer offsets.

    Each tile is shifted by the median of (its W - the decoded W) over the
    pixels already written; then only unwritten pixels are filled.
    """
    winding = np.zeros(shape, np.int64)
    written = np.zeros(shape, bool)
    for rows, cols in tiles(shape, tile, overlap):
        predicted = predict(rows, cols)
        seen = written[rows, cols]
        if seen.any():
            offset = np.median(predicted[seen] - winding[rows, cols][seen])
            predicted = predicted - int(np.round(offset))
        winding[rows, cols] = np.where(seen, winding[rows, cols], predicted)
        written[rows, cols] = True
    return winding


class OnnxWindingModel:
    """One ONNX file (``m -> W``) with its card; the session is created on first use."""

    def __init__(self, card: dict[str, Any]) -> None:
        self.card = card
        self._session: ort.InferenceSession | None = None

    @property
    def session(self) -> ort.InferenceSession:
        if self._session is None:
            self._session = open_model(self.card)
        return self._session

    def run(self, m: NDArray[np.float64]) -> NDArray[np.int64]:
        """W (int64, H x W) for a map of m no larger than the tile."""
        padded = pad_to_multiple(m.astype(np.float32), int(self.card["multiple"]))
        out = self.session.run(None, {"m": padded[None, None]})[0]
        return out[0, 0, : m.shape[0], : m.shape[1]].astype(np.int64)

    @property
    def top_winding(self) -> int | None:
        """The highest W one run outputs (:data:`TOP_CLASS`; None: unbounded)."""
        return TOP_CLASS

    def predict(self, m: NDArray[np.float64]) -> NDArray[np.int64]:
        """W for a frame of any size: tiled with reconciled offsets when large (see
        :data:`WHOLE_RUN_SLACK`)."""
        if self.runs_whole(m.shape):
            return self.run(m)
        tile = int(self.card["tile"])
        return stitch_overlapping(m.shape, tile, OVERLAP, lambda r, c: self.run(m[r, c]))

    def runs_whole(self, shape: tuple[int, ...]) -> bool:
        """Whether :meth:`predict` runs a frame of ``shape`` in one run (its longer side
        is at most the card's tile plus :data:`WHOLE_RUN_SLACK`), else in tiles."""
        return max(shape) <= int(self.card["tile"]) + WHOLE_RUN_SLACK

    def run_windows(self, shape: tuple[int, int]) -> list[tuple[slice, slice]]:
        """The rows and columns of each run :meth:`predict` makes on a frame of ``shape``."""
        if self.runs_whole(shape):
            return [(slice(0, shape[0]), slice(0, shape[1]))]
        return list(tiles(shape, int(self.card["tile"]), OVERLAP))

    def run_pixels(self, shape: tuple[int, int]) -> list[int]:
        """Pixels of each run :meth:`predict` makes on a frame of ``shape`` (each tile
        padded to the net's multiple)."""
        multiple = int(self.card["multiple"])
        runs = [(rows.stop - rows.start, cols.stop - cols.start)
                for rows, cols in self.run_windows(shape)]  # fmt: skip
        return [-(-h // multiple) * multiple * (-(-w // multiple) * multiple) for h, w in runs]


class OnnxRolloverModel(OnnxWindingModel):
    """UnModNet (``(m, W) -> rollover``): W grows by the predicted rollovers, pass by pass,
    until no pixel rolls over or ``max_passes`` is reached. A pass rolls only pixels that
    rolled in the previous one: the true sets ``W > k`` are nested, and without that the
    nets kept rolling bright regions on (val-256 at 15 passes, the tiny nets of
    2026-11-25 05:41: mantissa 18.91 -> 19.21 dB, modulo 18.75 -> 18.87 dB)."""

    @property
    def top_winding(self) -> int | None:
        return int(self.card["max_passes"])

    def run(self, m: NDArray[np.float64]) -> NDArray[np.int64]:
        padded = pad_to_multiple(m.astype(np.float32), int(self.card["multiple"]))[None, None]
        winding = np.zeros_like(padded)
        rolling = np.ones(padded.shape, bool)
        for _ in range(int(self.card["max_passes"])):
            rolling &= self.session.run(None, {"m": padded, "winding": winding})[0] > 0
            if not rolling[0, 0, : m.shape[0], : m.shape[1]].any():
                break
            winding += rolling
        return winding[0, 0, : m.shape[0], : m.shape[1]].astype(np.int64)


def winding_from_jumps(jumps: NDArray[np.floating]) -> NDArray[np.int64]:
    """Relative W (minimum 0) from per-neighbour jumps (``2 x H x W``: to the right and
    to the lower neighbour, in wraps): their least-squares integral, rounded."""
    relative = integrate_gradient(jumps[0].astype(np.float64), jumps[1].astype(np.float64))
    return np.round(relative - relative.min()).astype(np.int64)


class OnnxJumpsModel(OnnxWindingModel):
    """A winding net trained on per-neighbour jumps (``m -> jumps``, 2 channels): W is
    integrated from the predicted jumps (relative; anchored later)."""

    @property
    def top_winding(self) -> int | None:
        return None

    def run(self, m: NDArray[np.float64]) -> NDArray[np.int64]:
        padded = pad_to_multiple(m.astype(np.float32), int(self.card["multiple"]))
        jumps = self.session.run(None, {"m": padded[None, None]})[0][0]
        return winding_from_jumps(jumps[:, : m.shape[0], : m.shape[1]])


def onnx_model(card: dict[str, Any]) -> OnnxWindingModel:
    """The runtime wrapper of a card: one-pass winding net (W or jumps), or iterative
    UnModNet."""
    if card["family"] == "unmodnet":
        return OnnxRolloverModel(card)
    if card.get("output") == "jumps":
        return OnnxJumpsModel(card)
    return OnnxWindingModel(card)


class LearnedDecoder(Decoder):
    """A learned decoder with one ONNX model per encoding (the frame's encoding picks it)."""

    def __init__(self, name: str, cards: list[dict[str, Any]]) -> None:
        self.name = name  # type: ignore[misc]
        self.models = {card["encoding"]: onnx_model(card) for card in cards}
        self.version = ",".join(sorted(card["sha256"][:12] for card in cards))

    def unwraps(self, params: SensorParams) -> bool:
        return params.encoding in self.models

    def model_for(self, params: SensorParams) -> OnnxWindingModel:
        """The model trained for ``params.encoding``; a clear error when there is none,
        naming the model file when its card is installed without it."""
        if params.encoding not in self.models:
            missing = missing_model_files(self.name, params.encoding)
            cause = f": {files_missing(missing)}" if missing else ""
            raise InvalidInputError(
                f"decoder {self.name!r} has no model for the {params.encoding!r} encoding"
                f"{cause}; it supports: {', '.join(sorted(self.models))}"
            )
        return self.models[params.encoding]

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.explain_winding(m, params)[0]

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """The net's W, anchored, and facts (none when the net decoded the frame).

        A frame without a wrap edge (no neighbour differs by half a wrap or more: a
        uniform frame, a smooth unwrapped ramp) holds no evidence of where one W ends
        and another begins, so it gets one W, anchored to 0 as every decoder anchors
        (the nets alone answered W 0..2 on an all-zero frame, UnModNet 0..15 on all-max
        codes, and up to W = 5 on a smooth ramp below x = 1: an invented image).

        A frame with wrap edges but no residue (every 2x2 loop of jumps closes) is
        integrated instead (exact up to the constant, which anchoring sets, as ``auto``
        does), and the facts say so (``integrated``): the nets got 7-27% of W right on
        a linear ramp of 4 (mantissa) or 15 (modulo) wraps at 256x256, 9-18% on a
        2 x 513 one, where every classical decoder and ``auto`` are exact. None of the
        val-256 frames is without residues.

        A frame of which more than :data:`FALLBACK_SHARE` lies beyond the W the net can
        output (:func:`share_beyond`) is decoded by :data:`FALLBACK` instead, and the
        facts say so (``fallback``); a smaller share beyond gets the net's W and a
        ``warning``. On a log ramp of 1e-12 .. 1e30 (mantissa, alpha 2; W up to 100)
        the nets answered W 0..5 and got 30% of W right at 512x512, and
        ``<net>+puma`` then spent 80-110 s (2 cores) lifting the ramp's columns one
        wrap per min-cut. A frame without pixels is refused."""
        refuse_empty(m)
        model = self.model_for(params)
        along_cols, along_rows = neighbour_jumps(m)
        if not (along_cols.any() or along_rows.any()):
            return np.zeros(m.shape, np.int64), {}
        if not residue_map(along_cols, along_rows).any():
            winding = anchor_winding(integrate_jumps(along_cols, along_rows), params)
            return winding, {"integrated": NO_RESIDUE}
        share = share_beyond(model, m, params)
        if share > FALLBACK_SHARE:
            reason = beyond_classes(share, model, f"{FALLBACK.name} decoded it")
            fallback = {"decoder": FALLBACK.name, "reason": reason}
            return FALLBACK.predict_winding(m, params), {"fallback": fallback}
        winding = anchor_winding(model.predict(m), params)
        if share:
            return winding, {"warning": beyond_classes(share, model, "the net's W is short there")}
        return winding, {}

    def run_pixels(self, shape: tuple[int, int], params: SensorParams) -> list[int]:
        return self.model_for(params).run_pixels(shape)


def share_beyond(model: OnnxWindingModel, m: NDArray[np.float64], params: SensorParams) -> float:
    """The share (0 .. 1) of the pixels of ``m`` (wraps) whose W is beyond what ``model``
    outputs: more than its :attr:`~OnnxWindingModel.top_winding` wraps above the darkest
    pixels of their run (the :data:`~models.decoders.base.ANCHOR_PERCENTILE` percentile,
    what anchoring sets to W = 0), by the least-squares unwrapping (itoh's, about 1 ms
    at 256x256; it smooths across residues, so it errs low). 0, at no cost, when the
    params' bound on W (:func:`models.formation.max_winding`) is within the net's
    range, as on every benchmark frame (``max_wraps`` 16)."""
    top, bound = model.top_winding, max_winding(params)
    if top is None or (bound is not None and bound <= top):
        return 0.0
    u = least_squares_unwrap(m)
    beyond = np.zeros(m.shape, bool)
    for window in model.run_windows(m.shape):
        run = u[window]
        beyond[window] |= run - np.percentile(run, ANCHOR_PERCENTILE) >= top + 1
    return float(beyond.mean())


def beyond_classes(share: float, model: OnnxWindingModel, outcome: str) -> str:
    """What is wrong with a frame of which ``share`` lies beyond ``model``'s classes
    (:func:`share_beyond`), what became of it (``outcome``), and what to use instead."""
    return (
        f"{share:.1%} of the frame lies more than {model.top_winding} wraps above its "
        f"darkest pixels, beyond what this net can output (W 0..{model.top_winding}): "
        f"{outcome}; for such frames choose itoh, herraez or auto"
    )


def describe(name: str, cards: list[dict[str, Any]]) -> str:
    """One-line description of a learned decoder from its cards."""
    card = cards[0]
    encodings = "/".join(sorted(c["encoding"] for c in cards))
    return (
        f"{card['family']} {card.get('tier', '')} learned decoder ({encodings}), "
        f"{card['parameters']} parameters, {card['gflops_256']} GFLOPs at 256x256"
        + (f" per pass (up to {card['max_passes']} passes)" if "max_passes" in card else "")
    )


def figures(cards: list[dict[str, Any]]) -> dict[str, Any]:
    """Measured facts from the cards, per encoding (val-256 metrics, size, cost)."""
    return {
        card["encoding"]: {
            "parameters": card["parameters"],
            "gflops_256": card["gflops_256"],
            "val256": card.get("val256", {}),
            "val256_refined": card.get("val256_refined", {}),
        }
        for card in cards
    }


def figures_source(cards: list[dict[str, Any]]) -> str:
    """Where :func:`figures` come from: the cards' files (val-256 measured at export)."""
    files = ", ".join(f"models/onnx/{Path(card['file']).stem}.json" for card in cards)
    return (
        f"model cards {files}: size, cost and val-256 figures measured at export "
        "(mcam train measure re-measures them)"
    )


@cache
def _grouped_cards() -> dict[str, list[dict[str, Any]]]:
    groups: dict[str, list[dict[str, Any]]] = {}
    for card in load_cards():
        groups.setdefault(card["decoder"], []).append(card)
    return groups


@cache
def _cards_without_files() -> tuple[tuple[Path, dict[str, Any]], ...]:
    return tuple(read_cards(with_file=False))


def missing_model_files(name: str, encoding: str | None = None) -> list[Path]:
    """The ONNX files, missing, of decoder ``name``'s installed model cards (of
    ``encoding``'s card only, when given)."""
    return [path.with_name(card["file"]) for path, card in _cards_without_files()
            if card["decoder"] == name and encoding in (None, card["encoding"])]  # fmt: skip


def files_missing(missing: list[Path]) -> str:
    """What is wrong, and what to do, when model cards are installed without their
    ``missing`` ONNX files."""
    return (
        f"its model card is installed but its model file {', '.join(map(str, missing))} "
        f"is missing; {RESTORE_ADVICE}"
    )


def resolve(name: str) -> DecoderSpec | None:
    """None: the learned decoders are all listed (:func:`specs`). But a decoder whose
    model cards are installed without their ONNX files (so it is not listed) is an
    InvalidInputError naming the missing files and what to do, not an unknown decoder."""
    missing = missing_model_files(name)
    if missing:
        raise InvalidInputError(f"decoder {name!r} is not available: {files_missing(missing)}")
    return None


def specs() -> list[DecoderSpec]:
    """One spec per learned decoder found in ``models/onnx`` (none when no models ship)."""
    return [
        DecoderSpec(
            name=name,
            kind="learned",
            description=describe(name, cards),
            factory=lambda name=name, cards=cards: LearnedDecoder(name, cards),
            figures=figures(cards),
            figures_source=figures_source(cards),
        )
        for name, cards in _grouped_cards().items()
    ]
