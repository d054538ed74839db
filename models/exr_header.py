"""The EXR header attributes of a reconstruction: how its frame was encoded and decoded.

Every reconstruction written as OpenEXR (a job's result by the worker, ``mcam
reconstruct``, a video's EXR frames, a simulated frame's reference) records its sensor
parameters (:func:`sensor_attributes`) and, once decoded, its decoder and the decode's
routing facts (:func:`decode_attributes`); ``mcam reconstruct`` and video frames add
the units of their values in ``comments`` (:func:`reconstruction_attributes`) and video
frames how the stream decoded them (:func:`stream_attributes`), so a file read back says
where it came from.
"""

from __future__ import annotations

import json
from typing import Any

from models.formation import SensorParams

#: The decode's facts written to the ``routing`` attribute (JSON): per channel
#: (``details`` for one, ``channels`` for several), a colour frame's joined channels
#: (``colour``) and a latency budget shared by its channels (``budget``).
ROUTING_FACTS = ("details", "channels", "colour", "budget")


def sensor_attributes(params: SensorParams) -> dict[str, str]:
    """A frame's encoding, alpha, bits and (when known) gain, as EXR string attributes."""
    attributes = {
        "encoding": params.encoding,
        "alpha": repr(params.alpha),
        "bits": str(params.bits),
    }
    if params.gain is not None:
        attributes["gain"] = repr(params.gain)
    return attributes


def values_unit(params: SensorParams, scene_referred: bool = True) -> str:
    """The unit of a reconstruction: ``x / gain`` when written scene-referred with the
    gain known, else wrap units ``x``."""
    if params.gain is None:
        return "wrap units x (gain unknown)"
    return "scene-referred x / gain" if scene_referred else "wrap units x"


def values_scene_referred(attributes: dict[str, Any]) -> bool | None:
    """Whether an EXR written here holds scene-referred values (``x / gain``: True) or wrap
    units (the gain unknown: False), from its ``comments``: the unit after its last
    ``values in`` (:func:`reconstruction_attributes`; the source's name before it may
    hold any words), else anywhere in it; None for any other file."""
    comments = str(attributes.get("comments", ""))
    _, found, unit = comments.rpartition("values in ")
    text = unit if found else comments
    if "scene-referred" in text:
        return True
    if "wrap units" in text:
        return False
    return None


def reconstruction_attributes(
    params: SensorParams, info: dict[str, Any], source: str, scene_referred: bool = True
) -> dict[str, str]:
    """Sensor and decode attributes of a reconstruction of ``source`` (a file name,
    ``video frame 3``), with a ``comments`` line stating its units (see
    :func:`values_unit`)."""
    unit = values_unit(params, scene_referred)
    return (
        sensor_attributes(params)
        | decode_attributes(info)
        | {"comments": f"MantissaCam reconstruction of {source}; values in {unit}"}
    )


def stream_attributes(mode: str, frame: dict[str, Any]) -> dict[str, str]:
    """A video frame's decode along its stream: ``temporal`` holds the mode, why the frame
    was a keyframe (None for a temporal step) and the fraction of pixels per path
    (``worker.stream_state.FrameDecode.summary``), as JSON."""
    facts = {"mode": mode, "keyframe": frame["keyframe"], "paths": frame["paths"]}
    return {"temporal": json.dumps(facts, sort_keys=True)}


def decode_attributes(info: dict[str, Any]) -> dict[str, str]:
    """A decode's decoder, its version and its routing facts (``DecodeResult.info``)."""
    attributes = {
        "decoder": str(info.get("decoder", "")),
        "decoderVersion": str(info.get("version", "")),
    }
    routing = {key: info[key] for key in ROUTING_FACTS if key in info}
    if routing:
        attributes["routing"] = json.dumps(routing, sort_keys=True)
    return attributes
