"""Tests of models/decoders/learned.py: shipped ONNX decoders, tiling, sessions, errors."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import scenes
from models.decoders import learned
from models.decoders.registry import available_decoders, get_decoder, resolve
from models.errors import InvalidInputError
from models.formation import SensorParams, encode, from_unwrapped, simulate
from models.scenes import synthetic_scene, val256_frames


def test_shipped_cards_name_existing_files_with_their_hash() -> None:
    cards = learned.load_cards()
    assert {c["encoding"] for c in cards if c["decoder"] == "mantissanet-small"} == {
        "mantissa",
        "modulo",
    }
    for card in cards:
        digest = hashlib.sha256((learned.ONNX_DIR / card["file"]).read_bytes()).hexdigest()
        assert digest == card["sha256"]
        assert "forest" not in card["training"]["scenes"]


def test_registry_offers_the_learned_decoders_with_figures() -> None:
    specs = {s.name: s for s in available_decoders()}
    spec = specs["mantissanet-small"]
    assert spec.kind == "learned"
    assert set(spec.figures) == {"mantissa", "modulo"}


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_beats_not_unwrapping_on_one_crop_of_each_validation_scene(encoding: str) -> None:
    frames = val256_frames(encoding)[:: scenes.VAL256_CROPS_PER_SCENE]
    decoded, unwrapped = [], []
    for frame in frames:
        result = get_decoder("mantissanet-small").decode(frame.codes, frame.params)
        assert result.winding.shape == frame.codes.shape and result.winding.dtype == np.int64
        assert result.winding.min() >= 0 and np.isfinite(result.irradiance).all()
        decoded.append((result.winding == frame.winding).mean())
        unwrapped.append((frame.winding == 0).mean())
    assert np.mean(decoded) > np.mean(unwrapped)


def test_sessions_are_created_once_per_encoding() -> None:
    decoder = get_decoder("mantissanet-small")
    frame = val256_frames("mantissa")[0]
    decoder.decode(frame.codes[:32, :32], frame.params)
    session = decoder.models["mantissa"].session
    decoder.decode(frame.codes[:48, :40], frame.params)
    assert decoder.models["mantissa"].session is session


def test_large_odd_frames_are_tiled_into_one_consistent_map() -> None:
    scene = synthetic_scene(3, 160)
    big = np.tile(scene, (2, 3))[:300, :430]
    frame = simulate(big, SensorParams(encoding="mantissa", max_wraps=16), overexposed=0.2)
    result = get_decoder("mantissanet-small").decode(frame.codes, frame.params)
    assert result.winding.shape == (300, 430)
    assert result.winding.min() == 0 and result.winding.max() <= 5


def test_a_missing_encoding_model_is_a_clear_error() -> None:
    cards = [c for c in learned.load_cards() if c["encoding"] == "mantissa"]
    decoder = learned.LearnedDecoder("mantissanet-small", cards[:1])
    codes = np.zeros((16, 16), np.uint8)
    with pytest.raises(InvalidInputError, match="no model for the 'modulo' encoding"):
        decoder.decode(codes, SensorParams(encoding="modulo"))


def test_a_missing_encoding_model_file_is_named_with_what_to_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the modulo .onnx gone and its card still there, the error said only "no
    model for the 'modulo' encoding", naming neither the file nor what to do."""
    modulo = next(c for c in learned.read_cards() if c[1]["name"] == "mantissanet-small-modulo")
    (tmp_path / modulo[0].name).write_text(json.dumps(modulo[1]))
    monkeypatch.setattr(
        learned, "_cards_without_files", lambda: tuple(learned.read_cards(tmp_path, False))
    )
    cards = [c for c in learned.load_cards() if c["name"] == "mantissanet-small-mantissa"]
    decoder = learned.LearnedDecoder("mantissanet-small", cards)
    with pytest.raises(InvalidInputError, match="no model for the 'modulo' encoding") as caught:
        decoder.decode(np.zeros((16, 16), np.uint8), SensorParams(encoding="modulo"))
    assert str(tmp_path / "mantissanet-small-modulo.onnx") + " is missing" in caught.value.message
    assert learned.RESTORE_ADVICE in caught.value.message


def test_thread_setting_is_validated(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(learned.THREADS_ENV, "3")
    assert learned.worker_threads() == 3
    monkeypatch.setenv(learned.THREADS_ENV, "zero")
    with pytest.raises(InvalidInputError, match="MCAM_WORKER_THREADS"):
        learned.worker_threads()


def test_spin_setting_is_validated_and_reaches_the_session(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    path = next(card["path"] for card in learned.load_cards())
    for raw, spinning in (("1", True), ("0", False)):
        monkeypatch.setenv(learned.SPIN_ENV, raw)
        assert learned.ort_spinning() is spinning
        options = learned.make_session(path, 1).get_session_options()
        entry = options.get_session_config_entry("session.intra_op.allow_spinning")
        assert entry == raw
    monkeypatch.delenv(learned.SPIN_ENV)
    assert learned.ort_spinning() is False
    for raw, spinning in (("TRUE", True), ("off", False)):
        monkeypatch.setenv(learned.SPIN_ENV, raw)
        assert learned.ort_spinning() is spinning
    monkeypatch.setenv(learned.SPIN_ENV, "maybe")
    with pytest.raises(InvalidInputError, match="MCAM_ORT_SPIN must be 0 or 1"):
        learned.ort_spinning()


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 70), w=st.integers(1, 70), multiple=st.sampled_from([8, 16]))
def test_padding_reaches_the_multiple_and_keeps_the_frame(h: int, w: int, multiple: int) -> None:
    m = np.random.default_rng(h * w).random((h, w)).astype(np.float32)
    padded = learned.pad_to_multiple(m, multiple)
    assert padded.shape[0] % multiple == 0 and padded.shape[1] % multiple == 0
    np.testing.assert_array_equal(padded[:h, :w], m)


@settings(max_examples=40, deadline=None)
@given(size=st.integers(1, 1200), tile=st.sampled_from([128, 256]))
def test_tiles_cover_the_frame_with_the_overlap(size: int, tile: int) -> None:
    starts = learned.tile_starts(size, tile, 64)
    covered = np.zeros(size, bool)
    for start in starts:
        covered[start : start + tile] = True
    assert covered.all() and starts[0] == 0
    assert all(b - a <= tile - 64 for a, b in zip(starts, starts[1:], strict=False))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 1000))
def test_stitching_removes_per_tile_offsets(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.integers(0, 2, size=(300, 500)), axis=1) // 40
    offsets: dict[tuple[int, int], int] = {}

    def predict(rows: slice, cols: slice) -> np.ndarray:
        key = (rows.start, cols.start)
        offsets.setdefault(key, int(rng.integers(-5, 6)))
        return truth[rows, cols] + offsets[key]

    stitched = learned.stitch_overlapping(truth.shape, 128, 64, predict)
    difference = stitched - truth
    assert (difference == difference.flat[0]).all()


def test_unmodnet_unwraps_iteratively_within_its_pass_limit() -> None:
    decoder = get_decoder("unmodnet")
    frame = val256_frames("mantissa")[scenes.VAL256_CROPS_PER_SCENE]
    result = decoder.decode(frame.codes[:128, :128], frame.params)
    card = decoder.models["mantissa"].card
    assert card["family"] == "unmodnet" and card["max_passes"] == 15
    assert 0 <= result.winding.min() and result.winding.max() <= 5
    assert (result.winding == frame.winding[:128, :128]).mean() > 0.5


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 40), st.integers(2, 40), st.integers(0, 2**31 - 1))
def test_exact_jumps_integrate_back_to_the_winding(rows: int, cols: int, seed: int) -> None:
    winding = np.random.default_rng(seed).integers(0, 17, (rows, cols))
    jumps = np.zeros((2, rows, cols))
    jumps[0, :, :-1] = np.diff(winding, axis=1)
    jumps[1, :-1, :] = np.diff(winding, axis=0)
    np.testing.assert_array_equal(learned.winding_from_jumps(jumps), winding - winding.min())


def test_noisy_jumps_round_to_the_winding() -> None:
    winding = np.repeat(np.arange(8), 8)[None, :].repeat(16, axis=0)
    jumps = np.zeros((2, *winding.shape))
    jumps[0, :, :-1] = np.diff(winding, axis=1)
    jumps += np.random.default_rng(1).normal(0, 0.1, jumps.shape)
    np.testing.assert_array_equal(learned.winding_from_jumps(jumps), winding)


@settings(max_examples=15, deadline=None)
@given(rows=st.integers(2, 700), cols=st.integers(2, 700))
def test_run_pixels_counts_the_runs_predict_makes(rows: int, cols: int) -> None:
    """What the latency budget charges a net for a frame: one entry per ONNX run, each
    the run's padded size; frames up to the tile plus the slack run whole."""
    decoder = get_decoder("mantissanet-small-s2d")
    model = decoder.models["mantissa"]
    calls: list[tuple[int, ...]] = []
    real_run = model.run

    def counted(m: np.ndarray) -> np.ndarray:
        calls.append(m.shape)
        return real_run(m)

    model.run = counted  # type: ignore[method-assign]
    try:
        model.predict(np.zeros((rows, cols)))
    finally:
        model.run = real_run  # type: ignore[method-assign]
    pixels = decoder.run_pixels((rows, cols), SensorParams(encoding="mantissa"))
    step = int(model.card["multiple"])
    assert pixels == [-(-h // step) * step * (-(-w // step) * step) for h, w in calls]
    whole = max(rows, cols) <= int(model.card["tile"]) + learned.WHOLE_RUN_SLACK
    assert (len(pixels) == 1) == whole == model.runs_whole((rows, cols))


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
@pytest.mark.parametrize("code", [0, 255])
def test_a_uniform_frame_decodes_to_a_uniform_image(encoding: str, code: int) -> None:
    """No decoder invents structure where every code is the same."""
    params = SensorParams(encoding=encoding, bits=8, alpha=2.0)
    codes = np.full((48, 40), code, np.uint8)
    for spec in learned.specs():
        decoder = get_decoder(spec.name)
        if not decoder.supports(params):
            continue
        winding = decoder.decode(codes, params).winding
        assert np.ptp(winding) == 0, f"{spec.name}: W {winding.min()}..{winding.max()}"


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_a_frame_without_a_wrap_edge_decodes_to_w_zero(encoding: str) -> None:
    """A smooth ramp below x = 1: no neighbour pair wraps, so W is one constant, 0, as
    the classical decoders find (the nets alone answered up to W = 5 on it)."""
    params = SensorParams(encoding=encoding, bits=8, alpha=2.0)
    x = np.tile(np.linspace(0.0, 0.99, 64), (64, 1))
    frame = encode(x, params)
    assert not frame.winding.any()
    for spec in learned.specs():
        decoder = get_decoder(spec.name)
        if decoder.supports(params):
            winding = decoder.decode(frame.codes, params).winding
            assert not winding.any(), f"{spec.name}: W {winding.min()}..{winding.max()}"


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
@pytest.mark.parametrize("shape", [(256, 256), (2, 513), (513, 2)])
def test_a_frame_without_residues_is_integrated_and_says_so(
    encoding: str, shape: tuple[int, int]
) -> None:
    """A linear ramp of 15 wraps (W up to 4 in mantissa, 15 in modulo): every 2x2 loop
    closes, so integration is exact; the nets got 7-27% of W right at 256x256 and 9-18%
    on 2 x 513, where itoh and auto are exact."""
    params = SensorParams(encoding=encoding, bits=8, max_wraps=16.0)
    rows, cols = shape
    ramp = np.linspace(0.01, 15.0, max(shape))
    x = np.tile(ramp, (rows, 1)) if rows <= cols else np.tile(ramp[:, None], (1, cols))
    frame = encode(x, params)
    assert frame.winding.max() >= 4
    for spec in learned.specs():
        decoder = get_decoder(spec.name)
        if decoder.supports(params):
            result = decoder.decode(frame.codes, params)
            np.testing.assert_array_equal(result.winding, frame.winding, err_msg=spec.name)
            assert result.info["details"]["integrated"] == learned.NO_RESIDUE


def with_residues(u: np.ndarray) -> np.ndarray:
    """``u`` (48 rows, dark at 0.1 in columns 6..9) with a step up by 0.65 wrap in those
    columns' upper half and 0.35 in their lower half: two residues where the step falls
    below half a wrap (a frame without any is integrated, the net not run)."""
    u = u.copy()
    u[:24, 6:10] = 0.75
    u[24:, 6:10] = 0.45
    return u


def steep_ramp(params: SensorParams) -> tuple[np.ndarray, np.ndarray]:
    """Codes and true W of a 48 x 96 frame, dark on its left sixth, then rising 0.4 wrap
    a pixel along its rows (W 0 .. 31, no aliasing): more wraps than a net outputs;
    with residues (:func:`with_residues`)."""
    u = with_residues(np.tile(0.1 + 0.4 * np.clip(np.arange(96) - 16, 0, None), (48, 1)))
    frame = encode(from_unwrapped(u, params), params)
    return frame.codes, frame.winding


@pytest.mark.parametrize("encoding", ["mantissa", "modulo"])
def test_a_frame_beyond_the_nets_classes_goes_to_herraez_and_says_so(encoding: str) -> None:
    """The nets answered W 0..5 on a 1e-12 .. 1e30 log ramp (W up to 100), 30% right;
    each now hands such a frame to herraez, exact on it, and says why."""
    params = SensorParams(encoding=encoding, bits=8, alpha=2.0)
    codes, truth = steep_ramp(params)
    assert truth.max() > learned.TOP_CLASS
    for spec in learned.specs():
        decoder = get_decoder(spec.name)
        if not decoder.supports(params):
            continue
        result = decoder.decode(codes, params)
        np.testing.assert_array_equal(result.winding, truth, err_msg=spec.name)
        fallback = result.info["details"]["fallback"]
        assert fallback["decoder"] == "herraez"
        assert "beyond what this net can output" in fallback["reason"]
        assert "choose itoh, herraez or auto" in fallback["reason"]


def test_a_few_pixels_beyond_the_nets_classes_are_a_warning() -> None:
    """A frame dark but for a ramp up to 20 wraps in its last 46 columns (3% of it
    beyond W 16): the net decodes it, and its details say its W is short there."""
    params = SensorParams(encoding="modulo", bits=8)
    u = with_residues(np.tile(0.1 + 0.45 * np.clip(np.arange(256) - 210, 0, None), (48, 1)))
    result = get_decoder("mantissanet-tiny").decode(encode(u, params).codes, params)
    details = result.info["details"]
    assert "fallback" not in details
    assert details["warning"].startswith("3.1% of the frame lies more than 16 wraps")
    assert "the net's W is short there" in details["warning"]


def test_a_frame_whose_bound_fits_the_classes_stays_with_the_net() -> None:
    """With ``max_wraps`` bounding W within the classes (every benchmark frame), the net
    decodes the frame and nothing is estimated."""
    bounded = SensorParams(encoding="modulo", bits=8, max_wraps=16)
    codes, _ = steep_ramp(SensorParams(encoding="modulo", bits=8))
    result = get_decoder("mantissanet-tiny").decode(codes, bounded)
    assert "details" not in result.info
    assert result.winding.max() <= 16


def test_two_cards_of_one_decoder_and_encoding_are_refused_naming_both(tmp_path: Path) -> None:
    """The runtime picked whichever sorted last; now neither, with a clear error."""
    [shipped] = [c for c in learned.load_cards() if c["name"] == "mantissanet-tiny-modulo"]
    for name in ("mantissanet-tiny-mantissa", "mantissanet-tiny-ce-risk-mantissa"):
        (tmp_path / f"{name}.onnx").write_bytes(b"")
        card = {**shipped, "name": name, "file": f"{name}.onnx", "encoding": "mantissa"}
        (tmp_path / f"{name}.json").write_text(json.dumps(card))
    with pytest.raises(InvalidInputError, match="both serve decoder 'mantissanet-tiny'") as caught:
        learned.load_cards(tmp_path)
    assert "mantissanet-tiny-mantissa.json" in caught.value.message
    assert "mantissanet-tiny-ce-risk-mantissa.json" in caught.value.message
    (tmp_path / "mantissanet-tiny-mantissa.onnx").unlink()
    assert [c["file"] for c in learned.load_cards(tmp_path)] == [
        "mantissanet-tiny-ce-risk-mantissa.onnx"
    ]


@pytest.mark.parametrize(
    ("text", "reason"),
    [("notjson", "JSON text"), ("[1, 2]", "lacks file"), ('{"file": "a.onnx"}', "lacks decoder"),
     ('{"file": "a.onnx", "decoder": "n", "encoding": "mantissa"}', "lacks family, sha256"),
     (b"\xff\xfe", "JSON text")],
)
def test_a_file_that_is_not_a_model_card_is_named_with_what_is_wrong(
    tmp_path: Path, text: str | bytes, reason: str
) -> None:
    path = tmp_path / "card.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(InvalidInputError, match=f"card.json is not a model card.*{reason}"):
        learned.read_card(path)
    with pytest.raises(InvalidInputError, match="is not a model card"):
        learned.read_cards(tmp_path)


def test_a_directory_named_like_a_card_is_named_not_raised(tmp_path: Path) -> None:
    """A directory ``*.json`` in the models folder raised IsADirectoryError from every
    listing of the cards (a 500 from /health/ready) instead of naming it."""
    (tmp_path / "card.json").mkdir()
    with pytest.raises(InvalidInputError, match="card.json cannot be read as a model card"):
        learned.read_cards(tmp_path)


def test_every_shipped_card_reads() -> None:
    assert all(learned.read_card(path) == card for path, card in learned.read_cards())


def shipped_card(name: str) -> dict[str, Any]:
    """The loaded card (``path`` set to its ONNX file) of shipped model ``name``."""
    return next(card for card in learned.load_cards() if card["name"] == name)


def test_a_cut_short_model_file_is_named_at_session_creation(tmp_path: Path) -> None:
    """onnxruntime's 'INVALID_PROTOBUF : Protobuf parsing failed' reached the job."""
    card = shipped_card("mantissanet-tiny-modulo")
    cut = tmp_path / card["file"]
    cut.write_bytes(Path(card["path"]).read_bytes()[:5000])
    model = learned.onnx_model({**card, "path": str(cut)})
    with pytest.raises(learned.ModelFileError, match="cut short.*git lfs pull") as caught:
        model.run(np.zeros((32, 32)))
    assert str(cut) in str(caught.value)


def test_a_missing_model_file_is_named_at_session_creation(tmp_path: Path) -> None:
    card = {**shipped_card("mantissanet-tiny-modulo"), "path": str(tmp_path / "gone.onnx")}
    with pytest.raises(learned.ModelFileError, match="gone.onnx .*is missing; restore it"):
        learned.onnx_model(card).run(np.zeros((32, 32)))


def test_a_card_of_another_family_than_its_file_is_refused() -> None:
    """An UnModNet file under a MantissaNet card failed in onnxruntime with 'Required
    inputs (['winding']) are missing from input feed'."""
    unmodnet = shipped_card("unmodnet-tiny-modulo")
    card = {**shipped_card("mantissanet-tiny-modulo"), "path": unmodnet["path"],
            "sha256": unmodnet["sha256"]}  # fmt: skip
    with pytest.raises(learned.ModelFileError, match=r"takes inputs \['m', 'winding'\].*does not"):
        learned.onnx_model(card).run(np.zeros((32, 32)))


@pytest.mark.parametrize(
    ("change", "reason"),
    [({"multiple": 0}, "multiple must be a whole number >= 1, got 0"),
     ({"tile": 32}, "tile must be a whole number >= 65, got 32"),
     ({"tile": "256"}, "tile must be a whole number >= 65, got '256'"),
     ({"family": "unmodnet"}, "an unmodnet card needs max_passes"),
     ({"encoding": "clip"}, "encoding 'clip' is not one of"),
     ({"family": "resnet"}, "family 'resnet' is not one of"),
     ({"output": "mask"}, "output 'mask' is not one of"),
     ({"encoding": "mantissa"}, "encoding is 'mantissa' but its file 'mantissanet-tiny-modulo"),
     ({"file": "mantissanet-tiny-s2d-mantissa.onnx"}, "is not named <name>-modulo.onnx")],
)
def test_a_card_with_values_the_runtime_cannot_use_is_refused_naming_them(
    tmp_path: Path, change: dict[str, object], reason: str
) -> None:
    """Each was read, then failed at the first decode (ZeroDivisionError, int() of text,
    KeyError 'max_passes') or, with a tile of the overlap or less, decoded only the last
    tile of a large frame, the rest W = 0; a card whose encoding was edited, or that
    names the file of another encoding, served that file for its encoding unnoticed."""
    card = {**shipped_card("mantissanet-tiny-modulo"), **change}
    path = tmp_path / "card.json"
    path.write_text(json.dumps(card))
    expected = f"card.json is not a usable model card: .*{reason}"
    with pytest.raises(InvalidInputError, match=expected):
        learned.read_card(path)


def test_a_decoder_whose_model_file_is_missing_is_named_with_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its card without its .onnx made it 'unknown decoder 'mantissanet-gone'; choose one
    of: ...', which named neither the file nor what to do."""
    card = {**shipped_card("mantissanet-tiny-modulo"), "decoder": "mantissanet-gone",
            "file": "mantissanet-gone-modulo.onnx"}  # fmt: skip
    (tmp_path / "mantissanet-gone-modulo.json").write_text(json.dumps(card))
    monkeypatch.setattr(
        learned, "_cards_without_files", lambda: tuple(learned.read_cards(tmp_path, False))
    )
    expected = "decoder 'mantissanet-gone' is not available: .*gone-modulo.onnx is missing"
    with pytest.raises(InvalidInputError, match=expected):
        resolve("mantissanet-gone+puma")
    with pytest.raises(InvalidInputError, match="unknown decoder 'mantissanet-other'"):
        resolve("mantissanet-other")
