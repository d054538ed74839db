"""Tests of models/exr_header.py: a reconstruction's EXR attributes."""

from __future__ import annotations

import json

import numpy as np

from models.decoders import get_decoder
from models.exr_header import (
    decode_attributes,
    reconstruction_attributes,
    sensor_attributes,
    values_scene_referred,
)
from models.formation import SensorParams, encode


def test_sensor_attributes_record_the_encoding_and_a_known_gain() -> None:
    attributes = sensor_attributes(SensorParams(encoding="mantissa", alpha=2.5, bits=10, gain=3.0))
    assert attributes == {"encoding": "mantissa", "alpha": "2.5", "bits": "10", "gain": "3.0"}


def test_attributes_without_routing_or_gain() -> None:
    info = {"decoder": "itoh", "version": "1"}
    attributes = sensor_attributes(SensorParams()) | decode_attributes(info)
    assert attributes["decoder"] == "itoh"
    assert "routing" not in attributes and "gain" not in attributes


def test_a_colour_frames_joined_channels_are_recorded() -> None:
    rows, cols = np.mgrid[0:64, 0:64]
    x = 4.0 * np.exp(-((rows - 32) ** 2 + (cols - 32) ** 2) / 400)
    params = SensorParams(encoding="mantissa", bits=8)
    frame = encode(np.stack([x, 0.8 * x, 0.6 * x], axis=2), params)
    result = get_decoder("auto-best").decode(frame.codes, params)
    attributes = decode_attributes(result.info)
    routing = json.loads(attributes["routing"])
    assert len(routing["channels"]) == 3
    assert set(routing["colour"]) == {"anchors", "majority_fraction", "changed_fraction"}


def test_the_units_are_read_from_the_comments_not_the_sources_name() -> None:
    """A frame named scene-referred.npy, reconstructed without its gain, was taken for
    scene-referred: mcam evaluate compared its wrap units with a scene-referred
    reference (13 dB) instead of refusing the pair."""
    no_gain, gain = SensorParams(encoding="modulo"), SensorParams(encoding="modulo", gain=0.25)
    for source in ("scene-referred.npy", "wrap units.npy", "values in scene-referred.npy"):
        assert values_scene_referred(reconstruction_attributes(no_gain, {}, source)) is False
        assert values_scene_referred(reconstruction_attributes(gain, {}, source)) is True
    reference = {"comments": "scene-referred irradiance the simulated sensor saw (x / gain)"}
    assert values_scene_referred(reference) is True
    assert values_scene_referred({"comments": "written by MantissaCam"}) is None
