"""The live-frame decoding hook: independent and temporal modes on per-device state."""

from __future__ import annotations

import numpy as np
import pytest

from models.decoders import cost_model
from models.decoders.registry import get_decoder
from models.errors import InvalidInputError
from tests.worker.conftest import break_model_file
from worker.device_state import DeviceState, make_frame_decoder, warm_up
from worker.frame_message import FrameMessage


def messages(make_frame, count: int) -> list[FrameMessage]:
    frames = [make_frame(peak=5.0 + 0.05 * t) for t in range(count)]
    return [FrameMessage("cam", t, t * 1000, f.codes, f.params) for t, f in enumerate(frames)]


@pytest.mark.parametrize("mode", ["independent", "temporal"])
def test_modes_decode_a_slow_clip_exactly(make_frame, mode: str) -> None:
    decode = make_frame_decoder(mode, "itoh")
    state = DeviceState("cam")
    for t, message in enumerate(messages(make_frame, 4)):
        frame = decode(state, message)
        truth = make_frame(peak=5.0 + 0.05 * t).winding
        np.testing.assert_array_equal(frame.winding, truth)
        assert frame.info["decoder"] == "itoh" and frame.timings_ns["decode"] > 0
    assert (state.temporal is None) == (mode == "independent")


def test_temporal_state_starts_with_a_keyframe(make_frame) -> None:
    decode = make_frame_decoder("temporal", "itoh")
    clip = messages(make_frame, 3)
    state = DeviceState("cam")
    kinds = [decode(state, message).info["keyframe"] for message in clip]
    assert kinds[0] == "first" and kinds[1:] == [None, None]
    fresh = DeviceState("cam")
    assert decode(fresh, clip[2]).info["keyframe"] == "first"


def test_unknown_mode_and_decoder() -> None:
    with pytest.raises(InvalidInputError, match="frame mode"):
        make_frame_decoder("psychic", "itoh")
    with pytest.raises(InvalidInputError, match="unknown decoder"):
        make_frame_decoder("independent", "nope")


def test_warm_up_decodes_each_supported_encoding() -> None:
    took = warm_up("itoh")
    assert set(took) == {"modulo", "mantissa"} and all(ms > 0 for ms in took.values())
    with pytest.raises(InvalidInputError, match="unknown decoder"):
        warm_up("nope")


def test_warm_up_calibrates_a_latency_budget() -> None:
    """After warming an ``auto-<N>ms`` stream decoder its costs for 256x256 frames are
    measured: the first live frame does not pay for that."""
    costs = cost_model
    for cached in (costs.call_cost, costs.refinement_ns_per_pixel, costs.overhead_ns_per_pixel):
        cached.cache_clear()
    warm_up("auto-50ms")
    assert costs.call_cost.cache_info().currsize >= 2
    assert costs.refinement_ns_per_pixel.cache_info().currsize == 2 * len(costs.QUALITIES)
    assert costs.overhead_ns_per_pixel.cache_info().currsize == 2 * len(costs.QUALITIES)


def test_warm_up_warms_each_encoding_whose_model_file_is_sound(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """With mantissanet-small's modulo model file not its card's, warm-up raised
    ModelFileError at that first encoding, so the mantissa model was never warmed: a job
    child's first mantissa job paid the session's creation, and a worker with devices
    did not start. Each encoding is now warmed on its own, the broken one logged."""
    break_model_file(monkeypatch, "mantissanet-small", "modulo")
    decoder = get_decoder("mantissanet-small")
    took = warm_up("mantissanet-small")
    assert set(took) == {"mantissa"} and decoder.models["mantissa"]._session is not None
    assert "mantissanet-small-modulo.onnx is not the one its card describes" in caplog.text
