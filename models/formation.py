"""The image formation model of a wrapping sensor: the single source of truth.

Every other part of the system (simulator, training, worker, service, device,
tests) imports this module; nothing else implements a wrap.

Units and symbols
-----------------
- ``scene``: scene-referred linear irradiance (any positive scale, e.g. an EXR).
- ``x``: ``scene * gain`` in *wrap units*: ``x = 1`` is where a conventional pixel
  saturates (the pixel's wrap threshold I_max).
- ``u``: a continuous, monotonic "unwrapped" value ``u(x)``; the sensor stores its
  fractional part ``m = u - floor(u)`` and ``W = floor(u)`` is the winding number.
- ``code``: ``m`` quantized to ``bits`` bits, in DN (uint8 for bits <= 8, else uint16).

Encodings
---------
- ``modulo`` (ModuloCam): ``u = x``.
- ``mantissa`` (MantissaCam, supplement eq. 1-2): ``u = x`` for ``x < 1`` and
  ``u = 1 + log_alpha(x)`` for ``x >= 1``: linear until saturation, then one more
  wrap each time ``x`` is multiplied by ``alpha``. The paper's main-text eq. 4 writes
  a pure-log variant ``alpha^(I + W I_max)``; we implement the supplement's
  linear-then-log model, which is continuous at ``x = 1``.
- ``clip`` (a conventional sensor): stores ``min(x, 1)``; ``W`` is always 0.

All arithmetic is float64. Outputs that would overflow the requested float dtype
raise :class:`OutputOverflowError`; NaN, inf and negative inputs raise
:class:`InvalidInputError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
)
from pydantic_core import PydanticCustomError

from models.errors import (
    InvalidInputError,
    NegativeIrradianceError,
    OutputOverflowError,
    describe_validation_error,
)
from models.exposure import exposure_gain, luminance
from models.output_range import ensure_fits, ensure_nonzero_kept, overflow_remedy

Encoding = Literal["modulo", "mantissa", "clip"]
ENCODINGS: tuple[str, ...] = ("modulo", "mantissa", "clip")
#: Most bits a code has (codes are stored as uint8 or uint16).
MAX_BITS = 16
#: Largest winding number we represent (W is stored as int64).
MAX_WINDING = np.iinfo(np.int64).max
#: Largest noise seed a frame takes (:attr:`SensorParams.seed` is an int64).
MAX_NOISE_SEED = 2**63 - 1
#: Above this expected electron count, shot noise uses the Gaussian approximation.
_POISSON_LIMIT = 1e7
#: The smallest value of parameters that physics bounds below, its unit and why:
#: ``max_wraps`` (wrap units) clips x at or above the first wrap, and ``full_well``
#: (electrons at x = 1) counts at least one electron there (at 1e-300 every code was 0).
PHYSICAL_MINIMA: dict[str, tuple[float, str, str]] = {
    "max_wraps": (
        1.0, "wrap (x = 1, the first wrap)",
        "a sensor clipped below its first wrap never wraps and every W would be 0; for a "
        "conventional sensor give encoding clip",
    ),
    "full_well": (
        1.0, "electron (the charge at x = 1)",
        "a first wrap of less than one electron leaves no charge to count (far below it "
        "every code is 0); leave it unset for no shot noise",
    ),
}  # fmt: skip


class SensorParams(BaseModel):
    """Parameters of one wrapped frame: encoding, quantization, exposure and noise.

    ``gain`` maps scene irradiance to wrap units (``x = gain * scene``); it is
    ``None`` when unknown (the frame is then reconstructed in wrap units).
    ``read_noise`` is a Gaussian sigma in units of one wrap; ``full_well`` is the
    electron count at ``x = 1`` for Poisson shot noise; ``max_wraps`` clips ``x``. Both
    are at least 1 (:data:`PHYSICAL_MINIMA`: the first wrap, one electron).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    encoding: Encoding = "mantissa"
    alpha: float = Field(2.0, gt=1.0, le=1e6, allow_inf_nan=False)
    bits: int = Field(8, ge=1, le=MAX_BITS)
    gain: float | None = Field(None, gt=0.0, allow_inf_nan=False)
    max_wraps: float | None = Field(None, allow_inf_nan=False, json_schema_extra={"minimum": 1})
    read_noise: float = Field(0.0, ge=0.0, le=1.0, allow_inf_nan=False)
    full_well: float | None = Field(None, allow_inf_nan=False, json_schema_extra={"minimum": 1})
    seed: int | None = Field(None, ge=0, le=MAX_NOISE_SEED)

    @field_validator("max_wraps", "full_well")
    @classmethod
    def _at_least_the_physical_minimum(
        cls, value: float | None, info: ValidationInfo
    ) -> float | None:
        """Refuse a ``max_wraps`` or ``full_well`` below :data:`PHYSICAL_MINIMA`, saying why."""
        name = str(info.field_name)
        least, unit, why = PHYSICAL_MINIMA[name]
        if value is not None and value < least:
            raise PydanticCustomError(
                f"{name}_range",
                f"must be at least {least:g} {unit} or unset, got {value:g}: {why}",
            )
        return value

    @classmethod
    def parse(cls, values: dict[str, Any]) -> SensorParams:
        """Build from a mapping (CLI flags, form fields, JSON), with a readable error."""
        try:
            return cls.model_validate(values)
        except ValidationError as exc:
            problems = describe_validation_error(exc, "parameters")
            raise InvalidInputError(f"invalid sensor parameters: {problems}") from None

    def differences(self, other: SensorParams) -> list[str]:
        """Names of the parameters whose values differ from ``other``'s, leaving out the
        noise seed: frames of one stream or video share a sensor and an exposure, while
        each frame's noise is its own draw."""
        mine, theirs = self.model_dump(exclude={"seed"}), other.model_dump(exclude={"seed"})
        return [name for name, value in mine.items() if theirs[name] != value]

    @property
    def code_dtype(self) -> type[np.unsignedinteger]:
        """Storage dtype of the codes: uint8 for bits <= 8, else uint16."""
        return np.uint8 if self.bits <= 8 else np.uint16

    @property
    def levels(self) -> int:
        """Number of code values, ``2 ** bits``."""
        return 1 << self.bits


@dataclass(frozen=True)
class SensorFrame:
    """A simulated frame: codes (DN), true winding numbers and the exact ``x``."""

    codes: NDArray[np.unsignedinteger]
    winding: NDArray[np.int64]
    irradiance: NDArray[np.float64]
    params: SensorParams


def validate_irradiance(
    values: NDArray[Any], *, clip_negative: bool = False
) -> tuple[NDArray[np.float64], int]:
    """Return ``values`` as float64 after checking they are finite and non-negative.

    Negative values (lossy EXR compression leaves some) are set to 0 only when
    ``clip_negative`` is true; the second return value is how many were clipped.
    A float64 array with nothing clipped is returned as it is, not copied (a 4096 x
    4096 RGB scene is 400 MB; the simulate path checked it three times, a copy each).
    """
    arr = np.asarray(values)
    if arr.size == 0:
        raise InvalidInputError("the image is empty; give an image with at least one pixel")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise InvalidInputError(f"irradiance must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        raise InvalidInputError(
            f"irradiance has {arr.size - int(np.count_nonzero(np.isfinite(arr)))} NaN or "
            "infinite values; replace them (e.g. with the neighbouring value) before encoding"
        )
    negative = arr < 0
    n_negative = int(negative.sum())
    if n_negative:
        if not clip_negative:
            raise NegativeIrradianceError(
                f"irradiance has {n_negative} negative values (min {arr.min():.3g}); "
                "irradiance is non-negative: pass clip_negative / --clip-negative to set them to 0"
            )
        arr = np.where(negative, 0.0, arr)
    return arr, n_negative


def to_unwrapped(x: NDArray[np.floating], params: SensorParams) -> NDArray[np.float64]:
    """``u(x)``: the continuous value whose fractional part the sensor stores."""
    x = np.asarray(x, dtype=np.float64)
    if params.encoding == "modulo":
        return x.copy()
    if params.encoding == "clip":
        return np.minimum(x, 1.0)
    above = x >= 1.0
    u = np.where(above, x, 1.0)  # 1 + log_alpha(x) above saturation, x below; in place
    np.log(u, out=u)
    u /= np.log(params.alpha)
    u += 1.0
    np.copyto(u, x, where=~above)
    return u


def split_unwrapped(
    u: NDArray[np.floating], params: SensorParams
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Split ``u`` into the winding number ``W = floor(u)`` and ``m = u - W`` in [0, 1]."""
    u = np.asarray(u, dtype=np.float64)
    if params.encoding == "clip":
        return np.zeros(u.shape, np.int64), np.clip(u, 0.0, 1.0)
    if not np.isfinite(u).all():
        raise InvalidInputError(
            f"{int((~np.isfinite(u)).sum())} pixels have no finite unwrapped value; the "
            "irradiance must be finite (check the gain)"
        )
    floor = np.floor(u, out=np.empty_like(u))  # an array even for a 0-d u: m is made in it
    too_many = floor > float(MAX_WINDING) / 2
    if too_many.any():
        raise InvalidInputError(
            f"{int(too_many.sum())} pixels wrap more than {MAX_WINDING // 2} times, beyond int64 "
            f"winding numbers; {_fewer_wraps(params)}"
        )
    winding = floor.astype(np.int64)
    return winding, np.subtract(u, floor, out=floor)


def _fewer_wraps(params: SensorParams) -> str:
    """How to bring a frame of ``params`` within int64 winding numbers: a ``max_wraps``
    already given must come down (asking to set it was no help)."""
    if params.max_wraps is None:
        return "lower the gain, set max_wraps, or use the mantissa encoding"
    return (
        f"lower the gain, or max_wraps ({params.max_wraps:g}) to at most {MAX_WINDING // 2}, "
        "or use the mantissa encoding"
    )


def quantize(m: NDArray[np.floating], bits: int) -> NDArray[np.unsignedinteger]:
    """Codes in DN: ``min(floor(m * 2^bits), 2^bits - 1)``, uint8 or uint16."""
    levels = 1 << bits
    scaled = np.array(m, np.float64)  # a copy, scaled, floored and clipped in place
    scaled *= levels
    np.floor(scaled, out=scaled)
    np.clip(scaled, 0, levels - 1, out=scaled)
    return scaled.astype(np.uint8 if bits <= 8 else np.uint16)


def validate_codes(codes: NDArray[Any], bits: int) -> NDArray[np.unsignedinteger]:
    """Check codes are unsigned integers below ``2^bits``; return them unchanged."""
    arr = np.asarray(codes)
    if arr.size == 0:
        raise InvalidInputError("the frame is empty; give a frame with at least one pixel")
    if arr.dtype.kind not in "ui":
        raise InvalidInputError(
            f"codes must be integers (uint8 or uint16), got dtype {arr.dtype}; "
            "a wrapped frame stores the raw sensor codes, not normalized floats"
        )
    if arr.dtype.kind == "i" and int(arr.min()) < 0:
        n_bad = int((arr < 0).sum())
        raise InvalidInputError(
            f"codes must be non-negative, found {n_bad} below 0 (min {int(arr.min())}); "
            f"send the sensor's raw codes, 0 to 2^{bits} - 1, as read (uint8 or uint16), "
            "not with a black level or other offset subtracted"
        )
    top = int(arr.max())
    if top >= 1 << bits:
        n_bad = int((arr >= (1 << bits)).sum())
        remedy = (
            f"the frame is not {bits}-bit: set bits to the sensor's real bit depth"
            if top < 1 << MAX_BITS
            else f"codes have {MAX_BITS} bits at most, so these are not the sensor's raw "
            "codes: send them as read (uint8 or uint16), not scaled or summed"
        )
        raise InvalidInputError(
            f"{n_bad} codes are >= 2^{bits} = {1 << bits} (max {top}); {remedy}"
        )
    return arr


def dequantize(codes: NDArray[Any], bits: int) -> NDArray[np.float64]:
    """``m`` at the bin centre: ``(code + 0.5) / 2^bits``."""
    arr = validate_codes(codes, bits)
    return (arr.astype(np.float64) + 0.5) / (1 << bits)


def from_unwrapped(
    u: NDArray[np.floating], params: SensorParams, dtype: type[np.floating] = np.float64
) -> NDArray[np.floating]:
    """Invert ``u(x)``: ``x = u`` (modulo, clip) or ``alpha^(u - 1)`` for ``u >= 1`` (mantissa).

    Raises :class:`OutputOverflowError` where ``x`` would not fit ``dtype``.
    """
    u = np.asarray(u, dtype=np.float64)
    if params.encoding != "mantissa":
        ensure_fits(u, dtype, "reconstruction")
        return u.astype(dtype)
    above = u >= 1.0
    log_x = np.where(above, (u - 1.0) * np.log(params.alpha), 0.0)
    over = log_x > np.log(float(np.finfo(dtype).max))
    if over.any():
        float32_holds = bool(log_x.max() <= np.log(float(np.finfo(np.float32).max)))
        raise OutputOverflowError(
            f"{int(over.sum())} pixels of the reconstruction exceed the {np.dtype(dtype).name} "
            f"limit {float(np.finfo(dtype).max):.4g} (alpha^(u-1) with u up to {u.max():.6g}); "
            f"{overflow_remedy(dtype, float32_holds=float32_holds)}, or check the winding numbers"
        )
    return np.where(above, np.exp(log_x), u).astype(dtype)


def unwrapped_noise_sigma(u: NDArray[np.floating], params: SensorParams) -> NDArray[np.float64]:
    """Standard deviation (wraps) of ``u`` at unwrapped value ``u`` from the params' noise:
    read noise plus shot noise (``sqrt(x / full_well)`` in ``x``) carried through ``u(x)``
    (``du/dx`` is 1 below saturation and ``1 / (x ln alpha)`` above it for mantissa)."""
    u = np.asarray(u, dtype=np.float64)
    if not params.full_well:
        return np.full(u.shape, params.read_noise)
    x = np.maximum(from_unwrapped(np.maximum(u, 0.0), params), 0.0)
    shot = np.sqrt(x / params.full_well)
    if params.encoding == "mantissa":
        above = x >= 1.0
        # divided in turn: x * ln(alpha) overflows float64 for x near its top
        shot = np.where(above, shot / np.where(above, x, 1.0) / np.log(params.alpha), shot)
    return np.sqrt(params.read_noise**2 + shot**2)


def largest_noise_sigma(top: float, params: SensorParams) -> float:
    """The largest standard deviation (wraps) :func:`unwrapped_noise_sigma` gives any
    unwrapped value from 0 to ``top`` (wraps): a bound on a pixel's noise when its own
    ``u`` may be wrong by whole wraps (sampled on 65 levels plus ``u = 1``, where the
    mantissa encoding's noise peaks)."""
    top = max(float(top), 0.0)
    levels = np.append(np.linspace(0.0, top, 65), min(1.0, top))
    return max(float(unwrapped_noise_sigma(levels, params).max()), params.read_noise)


def apply_shot_noise(
    x: NDArray[np.float64], full_well: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Poisson shot noise for ``full_well`` electrons at ``x = 1`` (Gaussian for huge counts).

    The Gaussian is applied relative to ``x`` (``x (1 + z / sqrt(electrons))``): a count
    that overflows float64 (``x`` near 1e300) leaves ``x`` as it is, where ``inf +
    sqrt(inf) z`` was NaN."""
    with np.errstate(over="ignore"):
        electrons = x * full_well
    small = electrons < _POISSON_LIMIT
    noisy = np.empty_like(electrons)
    noisy[small] = rng.poisson(electrons[small]) / full_well
    big = electrons[~small]
    noisy[~small] = x[~small] * (1.0 + rng.standard_normal(big.shape) / np.sqrt(big))
    return np.maximum(noisy, 0.0)


def encode(x: NDArray[np.floating], params: SensorParams) -> SensorFrame:
    """Encode wrap-unit irradiance ``x`` into codes, with the params' noise (seeded).

    Read noise is added to the stored value and wrapped with it (a modulo pixel
    wraps its noise too), so the returned ``winding`` is the count the pixel
    actually made: ``W = floor(max(u + n, 0))``.
    """
    x, _ = validate_irradiance(x)
    if params.max_wraps is not None:
        x = np.minimum(x, params.max_wraps)
    winding, m = split_unwrapped(_noisy_unwrapped(x, params), params)
    return SensorFrame(quantize(m, params.bits), winding, x, params)


def _noisy_unwrapped(x: NDArray[np.float64], params: SensorParams) -> NDArray[np.float64]:
    """``u`` of wrap units ``x`` with the params' shot noise (on ``x``) and read noise (on
    ``u``, ``max(u + n, 0)``), drawn from a generator seeded with ``params.seed``. Its
    own function so that :func:`encode` holds ``u`` (a full-size array) only while it is
    split."""
    rng = np.random.default_rng(params.seed)
    noisy_x = apply_shot_noise(x, params.full_well, rng) if params.full_well else x
    u = to_unwrapped(noisy_x, params)
    if params.read_noise > 0:
        noise = rng.standard_normal(u.shape)
        noise *= params.read_noise
        u = np.maximum(np.add(u, noise, out=noise), 0.0, out=noise)
        if params.encoding == "clip":
            np.minimum(u, 1.0, out=u)
    return u


def simulate(
    scene: NDArray[np.floating],
    params: SensorParams,
    *,
    overexposed: float | None = None,
    gray: bool = False,
    clip_negative: bool = False,
) -> SensorFrame:
    """Expose and encode a scene-referred image (``H x W`` or ``H x W x 3``).

    The gain is ``params.gain`` if set, else chosen from ``overexposed`` (see
    :func:`exposure_gain`), else 1 (the scene is already in wrap units). RGB is
    encoded per channel unless ``gray`` converts it to Rec.709 luminance first.
    The returned params carry the gain used.
    """
    scene, _ = validate_irradiance(scene, clip_negative=clip_negative)
    if scene.ndim == 3 and scene.shape[2] == 1:
        scene = scene[:, :, 0]
    if gray:
        scene = luminance(scene)
    if scene.ndim not in (2, 3) or (scene.ndim == 3 and scene.shape[2] != 3):
        raise InvalidInputError(f"expected an H x W or H x W x 3 image, got shape {scene.shape}")
    if params.gain is not None and overexposed is not None:
        raise InvalidInputError("give either gain or overexposed, not both")
    gain = params.gain
    if gain is None:
        gain = exposure_gain(scene, overexposed) if overexposed is not None else 1.0
    with np.errstate(over="ignore"):  # counted and refused by ensure_fits
        x = scene * gain
    ensure_fits(x, np.float64, "exposed irradiance")
    return encode(x, params.model_copy(update={"gain": gain}))


def to_scene(x: NDArray[np.floating], gain: float) -> NDArray[np.float64]:
    """Scene-referred values ``x / gain`` of wrap units ``x``; an overflow to inf is left
    for the caller's :func:`ensure_fits` to count and refuse (no numpy warning)."""
    with np.errstate(over="ignore"):
        return np.asarray(x, np.float64) / gain


def reconstruct(
    codes: NDArray[Any],
    winding: NDArray[np.integer],
    params: SensorParams,
    dtype: type[np.floating] = np.float64,
    *,
    scene_referred: bool = False,
) -> NDArray[np.floating]:
    """Invert the encoding given the winding numbers: ``x_hat`` from ``u = W + m``.

    With ``scene_referred`` and a known gain, returns ``x_hat / gain``.
    """
    m = dequantize(codes, params.bits)
    winding = np.asarray(winding)
    if winding.shape != m.shape:
        raise InvalidInputError(
            f"winding map shape {winding.shape} does not match the frame {m.shape}"
        )
    rescale = scene_referred and params.gain is not None
    x = from_unwrapped(winding.astype(np.float64) + m, params, np.float64 if rescale else dtype)
    scene_gain = params.gain if rescale else None
    if scene_gain is not None:
        x = to_scene(x, scene_gain)
    ensure_fits(x, dtype, "reconstruction", scene_gain)
    ensure_nonzero_kept(x, dtype, "reconstruction", scene_gain)
    return x.astype(dtype)


@lru_cache(maxsize=64)
def max_winding(params: SensorParams) -> int | None:
    """Upper bound on ``W`` from the encoding and ``max_wraps``, six standard deviations
    of read and shot noise above it (shot noise is drawn after the ``max_wraps`` clip);
    None when unbounded, or bounded past ``MAX_WINDING / 2`` wraps (a modulo
    ``max_wraps`` of 2^62 and more): :func:`encode` refuses a pixel wrapped that often,
    and W compared with a bound past int64 raised OverflowError (guided graph cuts,
    temporal decoding). Cached per (frozen) ``params``: a temporal step of a pan asks
    3-4 times a frame, at 0.1 ms each (2026-11-27, AMD EPYC)."""
    if params.encoding == "clip":
        return 0
    if params.max_wraps is None:
        return None
    u_max = float(to_unwrapped(np.array(params.max_wraps), params))
    bound = np.floor(u_max + 6 * largest_noise_sigma(u_max, params))
    return int(bound) if bound <= float(MAX_WINDING) / 2 else None


def clip_winding(winding: NDArray[np.integer], params: SensorParams) -> NDArray[np.int64]:
    """``winding`` clamped to the encoding's range: 0 (x >= 0) to :func:`max_winding`."""
    return np.clip(winding, 0, max_winding(params))


def narrow_winding(winding: NDArray[np.integer]) -> NDArray[np.signedinteger]:
    """``winding`` in the narrowest signed integer type that holds it (int16 for any W a
    16-bit code can wrap to): 4x less to copy between processes than int64."""
    bound = max(abs(int(winding.min(initial=0))), int(winding.max(initial=0)))
    return winding.astype(np.min_scalar_type(-bound - 1), copy=False)
