"""Tests of worker/outputs.py: the EXR and W-map results of one decoded frame."""

from __future__ import annotations

import io
import json

import numpy as np
import OpenEXR
import pytest

from models.decoders import get_decoder
from models.errors import OutputOverflowError
from models.formation import SensorParams, encode
from models.hdr_io import EXR_COMPRESSIONS, read_hdr
from worker.outputs import check_video_storable, encode_outputs

PARAMS = SensorParams(encoding="modulo", bits=8, gain=2.0)


def test_outputs_hold_the_reconstruction_and_w() -> None:
    rows, cols = np.mgrid[0:64, 0:64]
    frame = encode(4.0 * np.exp(-((rows - 32) ** 2 + (cols - 32) ** 2) / 400), PARAMS)
    result = get_decoder("auto").decode(frame.codes, PARAMS)
    files = encode_outputs(frame.codes, result.winding, PARAMS, result.info, {})
    np.testing.assert_array_equal(np.load(io.BytesIO(files["winding"])), frame.winding)
    image = read_hdr(files["exr"])
    expected = (frame.winding + (frame.codes + 0.5) / 256) / PARAMS.gain
    np.testing.assert_allclose(image.pixels, expected, rtol=1e-6)
    assert image.attributes["decoder"] == "auto-balanced"
    routing = json.loads(image.attributes["routing"])
    assert routing["details"]["routes"] == {"integration": 1.0}


def test_the_exr_compression_option_reaches_the_file() -> None:
    frame = encode(np.linspace(0.0, 5.0, 48).reshape(6, 8), PARAMS)
    result = get_decoder("itoh").decode(frame.codes, PARAMS)
    files = {
        name: encode_outputs(
            frame.codes, result.winding, PARAMS, result.info, {"exr_compression": name}
        )["exr"]
        for name in EXR_COMPRESSIONS
    }
    for name, data in files.items():
        header = OpenEXR.File(io.BytesIO(data), header_only=True).header()
        assert header["compression"] == EXR_COMPRESSIONS[name]
    np.testing.assert_array_equal(read_hdr(files["none"]).pixels, read_hdr(files["zip"]).pixels)


def test_the_exr_says_which_units_its_values_are_in() -> None:
    """Scene-referred or not, a job's EXR said only 'written by MantissaCam': values a
    factor of the gain apart could not be told apart."""
    frame = encode(np.linspace(0.0, 5.0, 48).reshape(6, 8), PARAMS)
    result = get_decoder("itoh").decode(frame.codes, PARAMS)

    def comments(options: dict, params: SensorParams = PARAMS) -> str:
        files = encode_outputs(frame.codes, result.winding, params, result.info, options)
        return str(read_hdr(files["exr"]).attributes["comments"])

    assert comments({}).endswith("values in scene-referred x / gain")
    assert comments({"scene_referred": False}).endswith("values in wrap units x")
    no_gain = PARAMS.model_copy(update={"gain": None})
    assert comments({}, no_gain).endswith("values in wrap units x (gain unknown)")


def test_the_codes_are_kept_whatever_the_exr_can_carry_back() -> None:
    """16-bit codes a thousand wraps up do not survive a float32 EXR (24 bits hold W and
    16 bits of fraction only below 256 wraps): the codes are stored as they came."""
    params = SensorParams(encoding="modulo", bits=16)
    frame = encode(np.linspace(0.0, 1000.0, 4096).reshape(64, 64), params)
    files = encode_outputs(frame.codes, frame.winding, params, {}, {})
    np.testing.assert_array_equal(np.load(io.BytesIO(files["codes"])), frame.codes)


def test_a_clip_that_cannot_be_stored_names_its_first_such_frame() -> None:
    """Half floats at gain 1e-5 hold code 0 at W = 0 (x / gain about 200) but not code
    255 (about 99800): the frame of 255s is named, and one of 0s alone passes."""
    params = SensorParams(encoding="modulo", bits=8, gain=1e-5)
    clip = np.stack([np.zeros((4, 4), np.uint8), np.full((4, 4), 255, np.uint8)])
    check_video_storable(clip[:1], params, {"half": True})
    with pytest.raises(OutputOverflowError, match=r"^video frame 1: whatever winding") as exc:
        check_video_storable(clip, params, {"half": True})
    assert "16 pixels" in exc.value.message and "ask for float32 output" in exc.value.message
