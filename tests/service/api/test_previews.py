"""Tests of service/api/previews.py: the viewer's 8-bit PNG previews."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from service.api.previews import codes_png, tonemap_png, winding_png


def test_previews_of_an_h_x_w_x_1_frame_are_grey_or_colour_pngs() -> None:
    """A frame stored H x W x 1 (an npy frame): its codes and tonemapped previews raised
    Pillow's TypeError ("Cannot handle this data type: (1, 1, 1), |u1"), a 500."""
    codes = np.arange(12, dtype=np.uint8).reshape(4, 3, 1)
    previews = {
        "codes": codes_png(codes, 8),
        "image": tonemap_png(codes / 255.0, 0.0),
        "winding": winding_png(codes.astype(np.int64)),
    }
    shapes = {part: np.asarray(Image.open(io.BytesIO(png))).shape for part, png in previews.items()}
    assert shapes == {"codes": (4, 3), "image": (4, 3), "winding": (4, 3, 3)}
