"""The EXR header attributes of a reconstruction: how its frame was encoded and decoded.

Every reconstruction written as OpenEXR (a job's result by the worker, ``mcam
reconstruct``, a simulated frame's reference) records its sensor parameters
(:func:`sensor_attributes`) and, once decoded, its decoder and the decode's routing
facts (:func:`decode_attributes`), so a file read back says where it came from.
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
