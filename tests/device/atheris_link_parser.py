"""atheris (libFuzzer) harness for the link parser; run by test_link_parser with -runs=N.

Each input is split into a chunk size and a byte stream around one valid packet; the
parser must not raise and must still emit that packet when it is not overlapped.
"""

from __future__ import annotations

import math
import sys

import atheris

with atheris.instrument_imports():
    from device import link_protocol as lp
    from device.link_parser import LinkParser

VALID = lp.encode_packet(lp.FrameRatePacket(30.0))


def one_input(data: bytes) -> None:
    if not data:
        return
    chunk = data[0] + 1
    stream = data[1:] + VALID
    parser = LinkParser(max_payload=4096)
    out = []
    for start in range(0, len(stream), chunk):
        out += parser.feed(stream[start : start + chunk])
    while parser.buffered:
        out += parser.expire(now=math.inf)
    for packet in out:
        assert lp.packet_crc_ok(lp.encode_packet(packet))
    assert lp.encode_packet(out[-1]) == VALID if out else False


if __name__ == "__main__":
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()
