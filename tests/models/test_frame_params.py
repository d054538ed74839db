"""Tests of models/frame_params.py: a frame's stored parameters merged with the caller's."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
from PIL import Image, PngImagePlugin

from models.errors import InvalidInputError, MissingParameterError
from models.frames import FRAME_FORMATS, PNG_KEYWORD, decode_frame, encode_frame
from models.stored_params import MAX_PARAMS_TEXT
from tests.models.test_frames import NESTED, OVERLONG, PARAMS_8, png_storing, random_codes


def test_overrides_win_and_none_is_ignored() -> None:
    data = encode_frame(random_codes((4, 4), 8), PARAMS_8, "tiff")
    frame = decode_frame(data, "tiff", {"alpha": 4.0, "gain": 2.0, "bits": None, "encoding": None})
    assert frame.params.alpha == 4.0
    assert frame.params.gain == 2.0
    assert frame.params.bits == 8
    assert frame.params.encoding == "mantissa"
    assert frame.params.seed == PARAMS_8.seed


@pytest.mark.parametrize("fmt", FRAME_FORMATS)
def test_missing_params_name_the_flags_and_fields(fmt: str) -> None:
    data = encode_frame(random_codes((4, 4), 8), None, fmt)
    with pytest.raises(MissingParameterError, match="--encoding mantissa --bits 8") as err:
        decode_frame(data, fmt)
    assert err.value.code == "missing_parameter"
    assert "form fields encoding=mantissa, bits=8" in str(err.value)
    assert "a mantissa frame also needs its alpha" in str(err.value)  # not a 2nd refusal
    with pytest.raises(MissingParameterError, match="--alpha 2; HTTP: the form fields alpha=2"):
        decode_frame(data, fmt, {"encoding": "mantissa", "bits": 8})
    frame = decode_frame(data, fmt, {"encoding": "modulo", "bits": 8})
    assert frame.params.encoding == "modulo"


@pytest.mark.parametrize(
    ("stored", "flag"),
    [('"gain": 1e999', "--gain <value>; HTTP: the form fields gain=<value>"),
     ('"max_wraps": 0.5', "--max-wraps <value>; HTTP: the form fields max_wraps=<value>")],
)
def test_a_bad_value_the_frame_stores_is_named_as_the_frames(stored: str, flag: str) -> None:
    """A frame storing an out-of-range value (an infinite gain written by other software)
    was refused with 'invalid sensor parameters: gain: Input should be a finite number',
    as if the caller had given it, and without saying that a parameter overrides it."""
    data = png_storing('{"encoding": "mantissa", "alpha": 2, "bits": 8, ' + stored + "}")
    with pytest.raises(InvalidInputError, match=f"the frame stores .*{re.escape(flag)}"):
        decode_frame(data, "png")
    frame = encode_frame(np.zeros((4, 4), np.uint8), PARAMS_8, "png")
    with pytest.raises(InvalidInputError) as given:
        decode_frame(frame, "png", {"gain": -1.0})
    assert "the frame stores" not in given.value.message


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "not an object"),
        ('{"encoding": "mantissa", "alpha": 2.0, "bits": 8, "foo": 1}', r"unknown .*\['foo'\]"),
        (OVERLONG, rf"holds {len(OVERLONG)} characters, more than .* \(at most {MAX_PARAMS_TEXT}"),
        (NESTED, "not valid JSON"),
        ('{"encoding": "modulo", "bits": true}', "stores bits as true, not a number"),
        ('{"encoding": "modulo", "bits": 8, "gain": true}', "stores gain as true, not a"),
        ('{"encoding": "modulo", "bits": "8"}', 'stores bits as "8", not a number'),
        ('{"encoding": "modulo", "bits": ' + "9" * 5000 + "}", "not valid JSON"),
    ],
)
def test_a_damaged_png_chunk_gives_way_to_the_callers_parameters(
    text: str, problem: str, caplog: pytest.LogCaptureFixture
) -> None:
    info = PngImagePlugin.PngInfo()
    info.add_text(PNG_KEYWORD, text)
    buffer = io.BytesIO()
    Image.fromarray(random_codes((4, 4), 8)).save(buffer, format="PNG", pnginfo=info)
    with pytest.raises(InvalidInputError, match=f"{problem}.*--encoding mantissa --bits 8"):
        decode_frame(buffer.getvalue(), "png", {"alpha": 2.0})
    given = {"encoding": "modulo", "bits": 8}
    assert decode_frame(buffer.getvalue(), "png", given).params.encoding == "modulo"
    assert "ignored it: decoding with the parameters given" in caplog.text
