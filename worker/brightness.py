"""Brightness compensation for temporal unwrapping: a global exposure change between frames.

Under a global brightness ramp (a sunrise, auto-exposure, a light dimming) every
pixel's ``x`` is multiplied by the same gain ``k`` from one frame to the next. For
the modulo encoding ``u = x`` grows by ``(k - 1) x``: bright pixels move by more
than half a wrap per frame even on a slow ramp, and the temporal rule
``W_t = round(u_{t-1} - m_t)`` aliases. So the previous frame is first brightened:
``u'_{t-1} = u(min(k x_{t-1}, max_wraps))`` (through :mod:`models.formation`), with
the gain ``k`` that best explains the current ``m``.

Estimate: ``k = 2^s`` for ``s`` on a grid of ``step`` stops within ``[-search,
search]`` stops; on every ``stride``-th pixel of each row and column, the mean
misfit (:func:`worker.motion.misfit`, the temporal rule's own) between the
brightened previous ``u`` and the current ``m``. The least-misfit ``k`` is kept
only if its misfit is below ``switch`` times the misfit with no change; else
``k = 1`` (nothing is changed).

Failure modes: a change that is not one global gain (a light switched on in one
part of the frame, or a pan together with a ramp) is fitted by the gain that suits
most sampled pixels, and the rest are left to the temporal rule's safety checks;
the misfit of a modulo pixel is periodic in ``k`` (period ``1 / x``), so on a frame
of only very bright pixels a wrong gain can match by accident (``switch`` and the
dimmer pixels, which are smooth in ``k``, guard against it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from models.formation import SensorParams, from_unwrapped, to_unwrapped
from worker.config_checks import refuse_invalid
from worker.motion import misfit


@dataclass(frozen=True)
class BrightnessConfig:
    """Knobs of the gain estimate: ``search`` and ``step`` in stops per frame (search
    0 disables it), ``stride`` in pixels, ``switch`` the relative misfit to beat."""

    search: float = 0.5
    step: float = 0.02
    stride: int = 8
    switch: float = 0.8

    def __post_init__(self) -> None:
        refuse_invalid(
            "brightness",
            {
                "brightness search must be in [0, 4] stops": 0.0 <= self.search <= 4.0,
                "brightness step must be in (0, 1] stops": 0.0 < self.step <= 1.0,
                "brightness stride must be >= 1": self.stride >= 1,
                "brightness switch must be in (0, 1]": 0.0 < self.switch <= 1.0,
            },
        )


def _unwrapped_at(x: NDArray[np.float64], params: SensorParams) -> NDArray[np.float64]:
    """``u(min(x, max_wraps))``: what the sensor stores (before wrapping) for ``x``. An
    ``x`` past float64 (inf) is taken at float64's largest value, the most a frame
    that decodes holds: its ``u`` was inf, its misfit NaN."""
    top = float(np.finfo(np.float64).max) if params.max_wraps is None else params.max_wraps
    return to_unwrapped(np.minimum(x, top), params)


def _gained(gain: NDArray[np.float64] | float, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``gain * x`` (wrap units, broadcast), inf where it passes float64 (a gain tried on
    a pixel near the top), without numpy's overflow warning."""
    with np.errstate(over="ignore"):
        return np.multiply(gain, x)


def brighten(u: NDArray[np.float64], gain: float, params: SensorParams) -> NDArray[np.float64]:
    """``u(min(gain * x, max_wraps))`` for the ``x`` of ``u`` (any shape, wraps)."""
    if gain == 1.0:
        return u
    return _unwrapped_at(_gained(gain, from_unwrapped(u, params)), params)


def frame_gain(
    prev_u: NDArray[np.float64],
    m: NDArray[np.float64],
    params: SensorParams,
    config: BrightnessConfig,
) -> tuple[float, float]:
    """The global gain ``k`` from the previous frame's ``u`` to the current ``m`` (both
    H x W x C; see module doc), 1.0 when no gain explains ``m`` clearly better; and the
    mean misfit (wraps) of the sampled pixels with that gain."""
    count = int(round(config.search / config.step)) if params.encoding != "clip" else 0
    stops = config.step * np.arange(-count, count + 1)
    gains = 2.0 ** stops[np.argsort(np.abs(stops), kind="stable")]
    x = from_unwrapped(prev_u[:: config.stride, :: config.stride].ravel(), params)
    sample_m = m[:: config.stride, :: config.stride].ravel()
    tried = _unwrapped_at(_gained(gains[:, None], x[None]), params)
    costs = misfit(tried, sample_m[None]).mean(axis=1)
    best = int(np.argmin(costs))
    if costs[best] < config.switch * costs[0]:
        return float(gains[best]), float(costs[best])
    return 1.0, float(costs[0])
