"""Numerical stability at the extremes, through the whole pipeline (issue 7).

Each row of :data:`EXTREMES` is one extreme case and what the system must do
with it: ``finite`` (every decoder returns finite W and x_hat, never NaN/inf),
``exact`` (finite, and W equals the truth), ``exact for all`` (the same, claimed by
every decoder) or ``zero`` (finite, and W = 0). Every installed decoder runs every row
but the ``exact`` ones, which only the classical decoders and ``auto`` claim (the others
are held to ``finite`` where the table says ``W = 0``). Each case's frame is built
before its decoder runs, outside any ``pytest.raises``: a case whose encoding raised
would pass without decoding at all.

| case | what the system does |
|---|---|
| 1e-12 .. 1e30 dynamic range, mantissa alpha 2 | every decoder decodes it exactly (u peaks |
| | near 101); a net, whose W stops at 16 (UnModNet 15), hands it to herraez and says so |
| | in its details, so ``<net>+puma`` starts at the minimum (it took minutes lifting W) |
| W beyond a net's classes on at most 5% of a frame | the net's W, and a warning in its |
| | details that its W is short there (tests/models/decoders/test_learned) |
| 1e-12 .. 1e30, modulo | rejected at encoding, W would pass int64 (tests/models/test_formation) |
| alpha 1.01, 1e6 range | decodes (u up to ~1390 wraps), finite |
| alpha 100, 1e30 range | decodes exactly (u peaks near 16) |
| bits 1, 2, 12, 16 on a ramp | finite at every bit depth |
| all-dark frame (all codes 0) | W = 0 (classical, auto: passed through); networks: finite |
| every code at the maximum | W = 0 (classical, auto: passed through); networks: finite, and |
| | mantissanet-small predicts W = 1 on a few border pixels of this uniform frame |
| all-wrapped (uniform random codes) | finite, W >= 0 |
| random codes, alpha 1000 | finite or a clear output-overflow error |
| 1 x 1 and 1 x N frames | a clear error: spatial decoders need 2 x 2 |
| the same, encoding clip | W = 0 at every pixel: a clipped sensor never wraps |
| codes >= 2^bits, float codes | a clear invalid-input error |
| an encoding the decoder has no model for | a clear invalid-input error naming it |
| each case above as a colour frame (3 channels) | the same outcome through the decoders |
| | that join a colour frame's channels (``auto``, ``<decoder>+colour``, a budget) |
| a tinted colour ramp, 1e-6 .. 1e6 | finite through those decoders |
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from models.decoders import available_decoders, get_decoder
from models.errors import InvalidInputError, OutputOverflowError
from models.formation import SensorParams, encode, quantize

SIZE = 32
EXACT_SIZE = 160


@dataclass(frozen=True)
class Extreme:
    """One extreme case: a frame builder and the expected outcome."""

    name: str
    build: Callable[[], tuple[np.ndarray, np.ndarray | None, SensorParams]]
    expect: str


def log_ramp(
    low: float, high: float, params: SensorParams, size: int = SIZE
) -> tuple[np.ndarray, np.ndarray, SensorParams]:
    """A smooth diagonal ramp in log space from ``low`` to ``high`` (wrap units).

    At ``EXACT_SIZE`` the 42-decade ramp steps less than half a wrap per pixel.
    """
    rows, cols = np.mgrid[0:size, 0:size]
    t = (rows + cols) / (2 * size - 2)
    frame = encode(low * (high / low) ** t, params)
    return frame.codes, frame.winding, params


def constant_codes(code: int, bits: int) -> tuple[np.ndarray, None, SensorParams]:
    params = SensorParams(encoding="modulo", bits=bits)
    return np.full((SIZE, SIZE), code, params.code_dtype), None, params


def random_codes(params: SensorParams) -> tuple[np.ndarray, None, SensorParams]:
    m = np.random.default_rng(7).random((SIZE, SIZE))
    return quantize(m, params.bits), None, params


def mantissa(alpha: float = 2.0, bits: int = 8) -> SensorParams:
    return SensorParams(encoding="mantissa", alpha=alpha, bits=bits)


EXTREMES: tuple[Extreme, ...] = (
    Extreme(
        "range 1e-12..1e30 mantissa",
        lambda: log_ramp(1e-12, 1e30, mantissa(), EXACT_SIZE),
        "exact for all",
    ),
    Extreme("alpha 1.01", lambda: log_ramp(1e-3, 1e6, mantissa(alpha=1.01)), "finite"),
    Extreme(
        "alpha 100",
        lambda: log_ramp(1e-12, 1e30, mantissa(alpha=100.0), EXACT_SIZE),
        "exact",
    ),
    *(
        Extreme(f"bits {b}", lambda b=b: log_ramp(1e-3, 1e3, mantissa(bits=b)), "finite")
        for b in (1, 2, 12, 16)
    ),
    Extreme("all dark", lambda: constant_codes(0, 8), "zero"),
    Extreme("every code at max 8-bit", lambda: constant_codes(255, 8), "zero"),
    Extreme("every code at max 16-bit", lambda: constant_codes(65535, 16), "zero"),
    Extreme("all wrapped", lambda: random_codes(SensorParams(encoding="modulo")), "finite"),
    Extreme("random codes alpha 1000", lambda: random_codes(mantissa(alpha=1000.0)), "finite"),
)
#: Every installed decoder, plus a latency-budgeted auto (resolved from its name).
DECODERS = [spec.name for spec in available_decoders()] + ["auto-50ms"]
#: Name prefixes of the decoders that claim exactness (W equal to the truth, W = 0 on a
#: frame with no wrap edge).
EXACT_DECODERS = ("itoh", "herraez", "graphcut", "auto")


def claimed(decoder: str, case: Extreme) -> Extreme | None:
    """``case`` with the outcome claimed for ``decoder``: None where exactness on a
    synthetic log ramp is not claimed (only classical decoders and ``auto`` claim it,
    except on the ``exact for all`` rows), ``finite`` in place of ``zero`` for the others."""
    if case.expect == "exact for all":
        return Extreme(case.name, case.build, "exact")
    if decoder.startswith(EXACT_DECODERS) or case.expect not in ("exact", "zero"):
        return case
    if case.expect == "exact":
        return None
    return Extreme(case.name, case.build, "finite")


#: Every (decoder, case) pair with a claim to check: no pair is generated to be skipped.
EXTREME_RUNS = [
    pytest.param(decoder, run_case, id=f"{decoder}-{case.name}")
    for decoder in DECODERS
    for case in EXTREMES
    if (run_case := claimed(decoder, case)) is not None
]


def run(decoder: str, case: Extreme) -> None:
    codes, truth, params = case.build()
    if not get_decoder(decoder).supports(params):
        with pytest.raises(InvalidInputError, match=params.encoding):
            get_decoder(decoder).decode(codes, params)
        return
    try:
        result = get_decoder(decoder).decode(codes, params)
    except OutputOverflowError as exc:
        assert case.name == "random codes alpha 1000", exc.message
        assert "exceed" in exc.message
        return
    assert np.isfinite(result.irradiance).all()
    assert (result.winding >= 0).all()
    if case.expect == "zero":
        assert not result.winding.any()
    if case.expect in ("exact", "exact for all") and truth is not None:
        np.testing.assert_array_equal(result.winding, truth)


@pytest.mark.parametrize(("decoder", "case"), EXTREME_RUNS)
def test_extreme(decoder: str, case: Extreme) -> None:
    run(decoder, case)


@pytest.mark.parametrize("decoder", DECODERS)
@pytest.mark.parametrize("shape", [(1, 1), (1, 40), (40, 1)])
def test_degenerate_shapes_are_clear_errors(decoder: str, shape: tuple[int, int]) -> None:
    with pytest.raises(InvalidInputError, match="2 x 2"):
        get_decoder(decoder).decode(np.zeros(shape, np.uint8), SensorParams())


@pytest.mark.parametrize("decoder", [*DECODERS, "itoh+colour", "auto+puma"])
@pytest.mark.parametrize("shape", [(1, 1), (1, 40), (40, 1), (1, 40, 3)])
def test_degenerate_clip_frames_decode(decoder: str, shape: tuple[int, ...]) -> None:
    """A clipped sensor's frame one pixel high or wide needs no neighbours (W = 0):
    it was refused as having none to unwrap against."""
    codes = np.arange(np.prod(shape), dtype=np.uint8).reshape(shape)
    result = get_decoder(decoder).decode(codes, SensorParams(encoding="clip"))
    assert not result.winding.any()
    np.testing.assert_allclose(result.irradiance, (codes + 0.5) / 256)


@pytest.mark.parametrize("decoder", [*DECODERS, "itoh+colour", "auto+puma"])
@pytest.mark.parametrize("shape", [(0, 40), (40, 0), (0, 0)])
def test_empty_channels_are_clear_errors(decoder: str, shape: tuple[int, int]) -> None:
    """A channel without pixels handed to a decoder's own entry points (``decode``
    refuses it first): ``auto`` raised ZeroDivisionError, the learned decoders returned
    an empty W, ``+puma`` a numpy padding error."""
    params = SensorParams(encoding="mantissa", alpha=2.0)
    chosen = get_decoder(decoder)
    message = f"a {shape[0]} x {shape[1]}( x 3)? frame .*2 x 2 pixels"
    with pytest.raises(InvalidInputError, match=message):
        chosen.predict_winding(np.zeros(shape), params)
    with pytest.raises(InvalidInputError, match=message):
        chosen.explain_winding(np.zeros(shape), params)
    with pytest.raises(InvalidInputError, match=message):
        chosen.explain_planes(np.zeros((*shape, 3)), params)


@pytest.mark.parametrize("decoder", DECODERS)
def test_bad_codes_are_clear_errors(decoder: str) -> None:
    with pytest.raises(InvalidInputError, match="2\\^4"):
        get_decoder(decoder).decode(np.full((8, 8), 16, np.uint8), SensorParams(bits=4))
    with pytest.raises(InvalidInputError, match="integers"):
        get_decoder(decoder).decode(np.zeros((8, 8), np.float32), SensorParams())


@pytest.mark.parametrize("case", ["all dark", "every code at max 8-bit"])
def test_auto_passes_unwrapped_frames_through(case: str) -> None:
    codes, _, params = next(c for c in EXTREMES if c.name == case).build()
    routes = get_decoder("auto").decode(codes, params).info["details"]["routes"]
    assert routes == {"pass-through": 1.0}


#: Decoders that join a colour frame's channels (models/decoders/colour.py).
COLOUR_DECODERS = ["auto-balanced", "auto-best", "itoh+colour", "auto-600000ms"]


def three_channels(plane: np.ndarray) -> np.ndarray:
    return np.repeat(plane[:, :, None], 3, axis=2)


def as_colour(case: Extreme) -> Extreme:
    """``case`` with its frame repeated in three channels (its truth likewise)."""

    def build() -> tuple[np.ndarray, np.ndarray | None, SensorParams]:
        codes, truth, params = case.build()
        return three_channels(codes), None if truth is None else three_channels(truth), params

    return Extreme(case.name, build, case.expect)


@pytest.mark.parametrize("case", EXTREMES, ids=[c.name for c in EXTREMES])
@pytest.mark.parametrize("decoder", COLOUR_DECODERS)
def test_extreme_colour_frames(decoder: str, case: Extreme) -> None:
    run(decoder, as_colour(case))


@pytest.mark.parametrize("decoder", COLOUR_DECODERS)
def test_a_tinted_colour_ramp_stays_finite(decoder: str) -> None:
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    ramp = 1e-6 * 1e12 ** ((rows + cols) / (2 * SIZE - 2))
    red, blue = np.exp(0.5 * np.sin(cols / 5)), np.exp(-0.4 * rows / SIZE)
    tint = np.stack([red, np.ones_like(ramp), blue], axis=2)
    frame = encode(ramp[:, :, None] * tint, mantissa())
    result = get_decoder(decoder).decode(frame.codes, frame.params)
    assert np.isfinite(result.irradiance).all() and (result.winding >= 0).all()
