"""Guided graph-cut refinement applied plane by plane to a stream's W (H x W x C).

:class:`worker.temporal.StreamDecoder` refines an anchoring keyframe whole (and fills
its clipped blobs again) and a moving camera's frame within a band round the pixels
that fell back; both go through :func:`refined_planes`, one channel at a time.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from models.decoders.band_moves import band_of
from models.decoders.guided_puma import GuidedPumaDecoder
from models.formation import SensorParams


def refined_planes(
    refiner: GuidedPumaDecoder,
    m: NDArray[np.float64],
    winding: NDArray[np.int64],
    params: SensorParams,
    bands: NDArray[np.bool_] | None = None,
    refill: bool = False,
    anchor: bool = False,
) -> NDArray[np.int64]:
    """Each plane of ``winding`` (H x W x C) refined by ``refiner`` on its plane of ``m``:
    whole, or only within its plane of ``bands`` (bool, H x W x C) when given. With
    ``refill``, a whole plane's clipped blobs are filled again, judged on ``winding``
    (:meth:`models.decoders.guided_puma.GuidedPumaDecoder.refilled`), and with
    ``anchor`` a whole plane is anchored as a spatial decode is
    (:meth:`models.decoders.guided_puma.GuidedPumaDecoder.refine_anchored`): both for
    an anchoring keyframe, see the module doc."""
    planes = []
    refine = refiner.refine_anchored if anchor else refiner.refine
    for c in range(m.shape[2]):
        if bands is None:
            plane = refine(m[:, :, c], winding[:, :, c], params)[0]
            if refill:
                plane = refiner.refilled(m[:, :, c], plane, winding[:, :, c], params)[0]
            planes.append(plane)
        elif bands[:, :, c].any():
            band = bands[:, :, c]
            planes.append(refiner.refine_within(m[:, :, c], winding[:, :, c], params, band)[0])
        else:
            planes.append(winding[:, :, c])
    return np.stack(planes, axis=2)


def grown(pixels: NDArray[np.bool_], reach: int) -> NDArray[np.bool_]:
    """``pixels`` (bool, H x W x C) grown by ``reach`` px (Chebyshev) within each plane."""
    return np.stack(
        [band_of(pixels[:, :, c], reach) for c in range(pixels.shape[2])], axis=2
    )
