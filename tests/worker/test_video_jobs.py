"""Tests of worker/video_jobs.py: a video job's options, checked before any decoding."""

from __future__ import annotations

import pytest

from models.errors import InvalidInputError
from models.hdr_io import EXR_COMPRESSIONS
from worker.video_jobs import DEFAULT_OPTIONS, video_options


def test_defaults_give_every_output_and_zip_compressed_exrs() -> None:
    options, outputs = video_options("itoh", {})
    assert outputs == list(DEFAULT_OPTIONS["outputs"])
    assert options.decoder == "itoh" and options.exr_compression == "zip"


@pytest.mark.parametrize("compression", sorted(EXR_COMPRESSIONS))
def test_exr_compression_is_passed_on(compression: str) -> None:
    options, _ = video_options("itoh", {"exr_compression": compression})
    assert options.exr_compression == compression


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        ({"exr_compression": "lzw"}, "exr_compression must be one of zip, none"),
        ({"colour": "red"}, "unknown video options ['colour']"),
        ({"outputs": []}, "non-empty subset"),
    ],
)
def test_bad_options_are_refused_with_the_choices(options: dict, fragment: str) -> None:
    with pytest.raises(InvalidInputError) as caught:
        video_options("itoh", options)
    assert fragment in caught.value.message
