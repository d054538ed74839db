"""Whether output values survive the float type they are stored in, and what to do if not.

A reconstruction is written as float32 or half-float EXR (or float64 in memory): values
past the type's finite range would be stored as inf (:func:`ensure_fits`), and nonzero
values below its smallest subnormal as 0, an image gone black in silence
(:func:`ensure_nonzero_kept`). Both raise a clear error whose remedy knows whether the
values are wrap units or scene-referred ``x / gain`` (``scene_gain``): a tiny gain makes
scene values huge, a huge one makes them tiny.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from models.errors import InvalidInputError, OutputOverflowError, OutputUnderflowError


def _scene_gain_remedy(scene_gain: float, change: str) -> str:
    return (
        f"the output is scene-referred x / gain with gain {scene_gain:.4g}: if that gain is "
        f"not the frame's, give the right one ({change})"
    )


def overflow_remedy(
    dtype: type[np.floating], scene_gain: float | None = None, float32_holds: bool = True
) -> str:
    """What a user can do about values too large for ``dtype``: ``scene_gain`` is the
    gain a scene-referred output was divided by (a tiny one makes it huge), None for
    wrap units (where fewer wraps, from a lower capture gain or alpha, help);
    ``float32_holds`` whether float32 would hold the values (asked of half floats)."""
    if scene_gain is not None:
        fix = _scene_gain_remedy(scene_gain, "a higher gain gives smaller values")
    else:
        fix = "lower the gain or alpha"
    if np.finfo(dtype).bits == 32:
        return f"float32, the widest EXR pixel type, cannot hold them: {fix}"
    return _or_float32(dtype, fix, float32_holds, "cannot hold them either")


def underflow_remedy(
    dtype: type[np.floating], scene_gain: float | None = None, float32_holds: bool = True
) -> str:
    """What a user can do about nonzero values too small for ``dtype`` (``scene_gain``
    as for :func:`overflow_remedy`: a huge one makes a scene-referred output tiny;
    ``float32_holds`` whether float32 would keep them nonzero)."""
    if scene_gain is not None:
        fix = _scene_gain_remedy(scene_gain, "lower the gain for larger values")
    else:
        fix = "values this small are below any code step: check the winding numbers"
    return _or_float32(dtype, fix, float32_holds, "would store them as 0 too")


def _or_float32(dtype: type[np.floating], fix: str, float32_holds: bool, fails: str) -> str:
    """``fix``, offered after float32 output when ``dtype`` is half floats and float32
    holds the values, else after saying that float32 output ``fails`` as well."""
    if np.finfo(dtype).bits >= 32:
        return fix
    if float32_holds:
        return f"ask for float32 output instead of half floats, or {fix}"
    return f"float32 output {fails}: {fix}"


def _beyond(values: NDArray[np.floating], dtype: type[np.floating]) -> NDArray[np.bool_]:
    """Where ``values`` exceed ``dtype``'s finite range (inf and NaN included)."""
    return ~(np.abs(values) <= float(np.finfo(dtype).max))


def _lost(values: NDArray[np.floating], dtype: type[np.floating]) -> int:
    """How many nonzero ``values`` round to 0 in ``dtype`` (none when their own type
    is no wider)."""
    if values.dtype.itemsize <= np.dtype(dtype).itemsize:
        return 0
    half_tiny = float(np.finfo(dtype).smallest_subnormal) / 2  # at most this rounds to 0
    return int(np.count_nonzero((values != 0) & (np.abs(values) <= half_tiny)))


def ensure_fits(
    values: NDArray[np.floating],
    dtype: type[np.floating],
    what: str,
    scene_gain: float | None = None,
) -> None:
    """Raise :class:`OutputOverflowError` if ``values`` exceed ``dtype``'s finite range
    (:class:`InvalidInputError` if any is NaN: no number at all); ``scene_gain`` as for
    :func:`overflow_remedy`."""
    undefined = int(np.isnan(values).sum())
    if undefined:
        raise InvalidInputError(f"{undefined} pixels of the {what} are NaN (not a number)")
    over = _beyond(values, dtype)
    if over.any():
        remedy = overflow_remedy(dtype, scene_gain, not _beyond(values, np.float32).any())
        raise OutputOverflowError(
            f"{int(over.sum())} pixels of the {what} exceed the {np.dtype(dtype).name} limit "
            f"{float(np.finfo(dtype).max):.4g}; {remedy}"
        )


def ensure_nonzero_kept(
    values: NDArray[np.floating],
    dtype: type[np.floating],
    what: str,
    scene_gain: float | None = None,
) -> None:
    """Raise :class:`OutputUnderflowError` if nonzero ``values`` would round to zero in
    ``dtype``. A reconstruction is never zero (codes decode at their bin centre), so a
    zero in its file is an image gone black in silence: a huge gain dividing it into
    scene units (``scene_gain``, as for :func:`overflow_remedy`), or half floats for
    tiny values."""
    source = np.asarray(values)
    lost = _lost(source, dtype)
    if lost:
        remedy = underflow_remedy(dtype, scene_gain, not _lost(source, np.float32))
        raise OutputUnderflowError(
            f"{lost} nonzero pixels of the {what} are below the smallest "
            f"{np.dtype(dtype).name} ({float(np.finfo(dtype).smallest_subnormal):.4g}) "
            f"and would be stored as 0; {remedy}"
        )
