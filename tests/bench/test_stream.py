"""Tests of bench/stream.py's frames and in-process decoder measurement (the link and
worker runs are exercised by tests/device and tests/worker; no timings asserted)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench import stream
from device.daemon import packet_params
from models.decoders.registry import get_decoder
from tests.bench.virtual_clock import LATER_NS, SlowFirstItoh, VirtualClock


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
    assert stream.bench_decoder(packets, "none", get_decoder("itoh"), repeat=2)["frames_per_s"] > 0


def test_the_in_process_decoder_is_timed_after_its_first_frame() -> None:
    """A net's first frame (its ONNX session) was counted in the decoder's frames/s."""
    clock = VirtualClock()
    packets = stream.template_packets("camera")[:2]
    timed = stream.bench_decoder(packets, "none", SlowFirstItoh(clock), repeat=3, clock=clock)
    assert timed["frames_per_s"] == pytest.approx(1e9 / LATER_NS)


@pytest.mark.parametrize("fps", ["0", "-5", "nan", "inf"])
def test_a_latency_rate_that_is_not_above_zero_is_a_usage_error(
    fps: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """0 or less paced nothing: the latency run became a flood run still named paced."""
    with pytest.raises(SystemExit) as exc:
        stream.parse_args(["--latency-fps", fps])
    assert exc.value.code == 2
    assert f"--latency-fps: must be a finite number above 0, got {fps}" in capsys.readouterr().err


def test_fewer_frames_than_workers_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    """Each of the flood run's devices got 0 frames and the run waited 300 s."""
    with pytest.raises(SystemExit) as exc:
        stream.parse_args(["--frames", "1", "--workers", "1", "2"])
    assert exc.value.code == 2
    assert "--frames 1 is fewer than --workers 2" in capsys.readouterr().err
    assert stream.parse_args(["--frames", "2", "--workers", "1", "2"]).frames == 2


def test_a_worker_count_given_twice_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    """The second run's rows replaced the first's under the same names."""
    with pytest.raises(SystemExit) as exc:
        stream.parse_args(["--workers", "1", "2", "1"])
    assert exc.value.code == 2
    assert "argument --workers: 1 given more than once; give each once" in capsys.readouterr().err


def test_the_report_records_the_paced_rate_and_its_markdown_names_date_host_and_load() -> None:
    args = stream.parse_args(["--latency-fps", "2.5", "--decoder", "herraez"])
    rows = {"e2e_1w_paced": {"frames_sent": 20, "latency_ms_p50": 72.4}}
    report = stream.report(args, rows)
    assert report["latency_fps"] == 2.5 and report["results"] == rows
    assert len(report["load_average"]) == 3
    head, _, *table = stream.markdown(report).splitlines()
    assert head.startswith(f"bench.stream, {report['date']}, {report['machine']['cpu']} (")
    assert "load average at the end [" in head and "paced runs at 2.5 frames/s" in head
    assert table[-1] == "| e2e_1w_paced | latency_ms_p50 | 72.400 |"
