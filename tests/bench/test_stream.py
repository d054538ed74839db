"""Tests of bench/stream.py's frames and in-process decoder measurement (the link and
worker runs are exercised by tests/device and tests/worker; no timings asserted)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench import stream
from device.daemon import packet_params


@pytest.mark.parametrize(("scenes", "encoding"), [("camera", "modulo"), ("val256", "mantissa")])
def test_template_packets_are_distinct_256px_frames_with_their_parameters(
    scenes: str, encoding: str
) -> None:
    packets = stream.template_packets(scenes)
    assert len(packets) == stream.DISTINCT
    assert [p.sequence for p in packets] == list(range(stream.DISTINCT))
    assert {p.codes.shape for p in packets} == {(256, 256)}
    assert {p.encoding for p in packets} == {encoding}
    assert len({p.codes.tobytes() for p in packets}) == stream.DISTINCT
    assert {packet_params(p).encoding for p in packets} == {encoding}


def test_the_in_process_decoder_uses_each_packet_s_own_parameters() -> None:
    """10-bit codes (above 255) decode only with the packet's own bit depth."""
    packets = [
        replace(p, bits=10, codes=p.codes.astype(np.uint16) * 4 + 3)
        for p in stream.template_packets("val256")[:2]
    ]
    assert packets[0].codes.max() > 255
    assert stream.bench_decoder(packets, "none", "itoh", repeat=2)["frames_per_s"] > 0
