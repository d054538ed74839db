"""Tests of models/decoders/guided_puma.py: a decoder's W refined by guided PUMA."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray

from models.decoders import learned
from models.decoders.band_moves import best_band_move
from models.decoders.base import Decoder
from models.decoders.graphcut import PumaEnergy, best_pixel_move, minimise
from models.decoders.guided_puma import (
    RESIDUE_WEIGHT,
    WHOLE_FRAME_PIXELS,
    WINDOW,
    GuidedPumaDecoder,
    curvature,
    pair_weights,
)
from models.decoders.registry import available_decoders, get_decoder, resolve
from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize, encode
from models.scene_analysis import residue_pixels
from models.video_clips import DEFAULT_FRAMES, make_clip


def _hill(size: int = 96, peak: float = 24.0, width: int | None = None) -> np.ndarray:
    """A smooth scene (wrap units) from 0.1 to ``peak``, ``size`` rows by ``width``
    (default ``size``) columns: several wraps, no aliasing."""
    yy, xx = np.mgrid[0:size, 0 : width or size] / size
    centre = 0.5 * (width or size) / size
    return 0.1 + peak * np.exp(-((xx - centre) ** 2 + (yy - 0.45) ** 2) / 0.05)


class CappedGuide(Decoder):
    """A guide that is right up to ``cap`` wraps and never counts higher (as the nets):
    the frame's true W capped, so the refinement has whole rings to put back."""

    name = "capped"  # type: ignore[assignment]

    def __init__(self, truth: NDArray[np.int64], cap: int) -> None:
        self.truth = truth
        self.cap = cap

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return np.minimum(self.truth, self.cap)


@pytest.mark.parametrize(("encoding", "peak"), [("modulo", 8.0), ("mantissa", 24.0)])
def test_rings_the_guide_missed_are_put_back(encoding: str, peak: float) -> None:
    params = SensorParams(encoding=encoding, max_wraps=64)
    frame = encode(_hill(peak=peak), params)
    assert frame.winding.max() >= 4
    result = GuidedPumaDecoder(CappedGuide(frame.winding, 2)).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    details = result.info["details"]
    assert details["guide"] == "capped"
    assert details["changed_fraction"] == pytest.approx(np.mean(frame.winding > 2))


class LoweredGuide(Decoder):
    """A guide one wrap short on the first ``rows`` rows (a sky the net put at W = 0)."""

    name = "lowered"  # type: ignore[assignment]

    def __init__(self, truth: NDArray[np.int64], rows: int) -> None:
        self.guess = truth.copy()
        self.guess[:rows] = np.maximum(self.guess[:rows] - 1, 0)

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.guess.copy()


def test_a_sky_behind_a_sharp_edge_is_raised_through_its_smooth_side() -> None:
    """The pan/zoom case: a sky one wrap up (x 1.45) meets dark ground (x 0.1) along a
    sharp edge that looks like a 0.35-wrap step, and only a smooth ramp on one side shows
    the wrap. With every pair weighing 1 the wrong sky has the lower energy (fewer
    unwrapped jumps across the long sharp edge); weighted by reliability the true one
    has, and the refinement raises the sky the guide left at W = 0."""
    size, sky, band = 64, 20, 32
    scene = np.full((size, size), 0.1)
    scene[:sky] = 1.45 + 0.05 * np.sin(np.arange(size) / 3.0)[None, :]
    scene[sky : 2 * sky + 1, :band] = np.linspace(1.45, 0.1, sky + 1)[:, None]
    params = SensorParams(encoding="modulo", max_wraps=16)
    frame = encode(scene, params)
    m = dequantize(frame.codes, params.bits)
    guide = LoweredGuide(frame.winding, sky)
    wrong = guide.predict_winding(m, params)
    unit, weighted = PumaEnergy(1.0), PumaEnergy(1.0, pair_weights(m))
    assert unit(wrong, m) < unit(frame.winding, m)
    assert weighted(frame.winding, m) < weighted(wrong, m)
    result = GuidedPumaDecoder(guide).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding[:sky], frame.winding[:sky])
    assert np.mean(result.winding == frame.winding) > 0.999


@pytest.mark.parametrize("guide", ["mantissanet-small-s2d", "mantissanet-tiny", "itoh"])
def test_a_wide_sky_the_guide_left_a_wrap_short_is_raised(guide: str) -> None:
    """The first frame of the pan/zoom clip (mantissa, as bench.video makes it): each
    guide puts a sky of 28% of the frame, one wrap up and reached only through its cloud
    contours, at W = 0. Its border is weak evidence (curvature) against a prior that
    grows with the area: at ``lam`` 0.01 small-s2d's refinement kept the sky (73.7% of
    W right, at an energy below the truth's). With tiny and itoh as guides the least
    energy put the dark ground at W = -1 under the sky at 0, and clipping that to 0
    afterwards lowered the sky again (71.6%): W is now confined to 0..max during the
    moves."""
    clip = make_clip("pan_zoom", frames=DEFAULT_FRAMES, encodings=("mantissa",))
    enc = clip.encodings["mantissa"]
    decoder = get_decoder(f"{guide}+puma")
    result = decoder.decode(enc.codes[0], enc.params)
    assert np.mean(result.winding == enc.winding[0]) > 0.99


class LiftedHalfGuide(Decoder):
    """A guide one wrap high on the right half of a frame that never wraps (as itoh on a
    dark frame: its least squares half 0, half 1)."""

    name = "lifted-half"  # type: ignore[assignment]

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        winding = np.zeros(m.shape, np.int64)
        winding[:, m.shape[1] // 2 :] = 1
        return winding


def test_a_refined_frame_is_anchored_as_its_guide_is() -> None:
    """Raising a region costs half as much as lowering one, so from a guide half 0 and
    half 1 the least energy lifts the whole frame to W = 1: the moves keep W within the
    encoding's range, not its constant. The darkest pixels are put back at W = 0."""
    params = SensorParams(encoding="mantissa")
    frame = encode(_hill(peak=0.8), params)
    assert not frame.winding.any()
    decoder = GuidedPumaDecoder(LiftedHalfGuide())
    m = dequantize(frame.codes, params.bits)
    lifted, _ = decoder.refine(m, decoder.guide.predict_winding(m, params), params)
    assert lifted.min() == 1
    result = decoder.decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    assert result.info["details"]["anchor_shift"] == 1


def test_a_dark_first_frame_is_anchored_after_itoh_is_refined() -> None:
    """The sunrise clip's first frame (mantissa, as bench.video makes it) never wraps
    but for a few bright pixels; itoh puts 56% of it at W = 1 and the refinement raised
    the rest to match (0.2% of W right, and the temporal stream from it 16.27 dB)."""
    clip = make_clip("sunrise", frames=DEFAULT_FRAMES, encodings=("mantissa",))
    enc = clip.encodings["mantissa"]
    result = get_decoder("itoh+puma").decode(enc.codes[0], enc.params)
    assert np.mean(result.winding == enc.winding[0]) > 0.99


@pytest.mark.parametrize(
    ("height", "width", "windows"),
    [
        (WINDOW + 44, WINDOW + 44, 1),
        (WINDOW + 44, WHOLE_FRAME_PIXELS // (WINDOW + 44) + 1, 10),
    ],
)
def test_frames_are_refined_whole_up_to_a_size_then_in_stitched_windows(
    height: int, width: int, windows: int
) -> None:
    params = SensorParams(encoding="mantissa", max_wraps=64)
    frame = encode(_hill(size=height, width=width), params)
    result = GuidedPumaDecoder(CappedGuide(frame.winding, 2)).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    assert result.info["details"]["windows"] == windows


def test_a_move_budget_stops_the_refinement_early() -> None:
    params = SensorParams(encoding="mantissa", max_wraps=64)
    frame = encode(_hill(), params)
    capped = CappedGuide(frame.winding, 2)
    full = GuidedPumaDecoder(capped, region_moves=0).decode(frame.codes, params)
    one = GuidedPumaDecoder(capped, max_moves=1, region_moves=0).decode(frame.codes, params)
    assert full.info["details"]["moves"] > 1
    assert one.info["details"]["moves"] == 1
    assert one.info["details"]["region_moves"] == 0
    right_after_one = np.mean(one.winding == frame.winding)
    assert np.mean(np.minimum(frame.winding, 2) == frame.winding) < right_after_one < 1.0


def test_budgeted_refinements_after_region_moves_cut_on_a_band() -> None:
    """Band moves finish a budgeted refinement that starts with region moves, and it
    still reaches the true W; without region moves (whole regions left for the pixel
    cuts) or run to convergence, the pixel cuts are full ones."""
    params = SensorParams(encoding="mantissa", max_wraps=64)
    frame = encode(_hill(), params)
    capped = CappedGuide(frame.winding, 2)
    assert GuidedPumaDecoder(capped).pixel_move is best_pixel_move
    assert GuidedPumaDecoder(capped, max_moves=2, region_moves=0).pixel_move is best_pixel_move
    banded = GuidedPumaDecoder(capped, max_moves=4)
    assert banded.pixel_move is best_band_move
    np.testing.assert_array_equal(banded.decode(frame.codes, params).winding, frame.winding)


def test_region_moves_come_first_and_are_counted_apart() -> None:
    """The capped guide misses three rings, each a consistent region: the first region
    cut puts one back whole, so fewer pixel cuts remain than without the region phase."""
    params = SensorParams(encoding="mantissa", max_wraps=64)
    frame = encode(_hill(), params)
    capped = CappedGuide(frame.winding, 2)
    hybrid = GuidedPumaDecoder(capped).decode(frame.codes, params)
    pixels_only = GuidedPumaDecoder(capped, region_moves=0).decode(frame.codes, params)
    np.testing.assert_array_equal(hybrid.winding, frame.winding)
    np.testing.assert_array_equal(pixels_only.winding, frame.winding)
    assert hybrid.info["details"]["region_moves"] == 2
    assert hybrid.info["details"]["moves"] < pixels_only.info["details"]["moves"]


def test_a_right_guide_is_kept_on_a_smooth_scene() -> None:
    params = SensorParams(encoding="mantissa", max_wraps=64)
    frame = encode(_hill(), params)
    result = GuidedPumaDecoder(CappedGuide(frame.winding, 99)).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    assert result.info["details"]["changed_fraction"] == 0.0


def _square_with_rough_border(side: int, size: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """A flat square 3 wraps above a flat surround, its border a 4-px band of rough
    texture (true steps up to 0.8 wrap: residues all along it); and the interior mask."""
    scene = np.full((size, size), 0.3)
    low, high = (size - side) // 2, (size + side) // 2
    scene[low:high, low:high] = 3.3
    band = np.zeros((size, size), bool)
    band[low - 2 : high + 2, low - 2 : high + 2] = True
    band[low + 2 : high - 2, low + 2 : high - 2] = False
    scene[band] += 0.8 * np.random.default_rng(5).random(int(band.sum()))
    interior = np.zeros((size, size), bool)
    interior[low + 2 : high - 2, low + 2 : high - 2] = True
    return scene, interior


@pytest.mark.parametrize(("side", "kept"), [(8, False), (64, True)])
def test_border_against_area_rule(side: int, kept: bool) -> None:
    """A right guide on a region bounded by residues is kept when the region is large
    (prior lam * area above the border's weight, RESIDUE_WEIGHT times its reliability
    factor: side > 18 px) and overridden by the smaller jump when it is small (the
    documented failure mode)."""
    scene, interior = _square_with_rough_border(side)
    params = SensorParams(encoding="modulo", max_wraps=16)
    frame = encode(scene, params)
    result = GuidedPumaDecoder(CappedGuide(frame.winding, 99)).decode(frame.codes, params)
    right = np.array_equal(result.winding[interior], frame.winding[interior])
    assert right == kept


def test_residues_and_their_weights() -> None:
    m = np.zeros((8, 8))
    # A loop that climbs 0 -> 0.3 -> 0.6 -> 0.9 and falls back to 0: one wrap jump
    # around it, so its circulation is non-zero (a residue).
    m[2:4, 2:4] = [[0.0, 0.3], [0.9, 0.6]]
    assert not residue_pixels(np.zeros((8, 8)), reach=2).any()
    near = residue_pixels(m, reach=0)
    assert near[2:4, 2:4].all()
    assert not near[6:, 6:].any()
    assert residue_pixels(m, reach=1).sum() > near.sum()
    right, down = pair_weights(m)
    assert right.shape == (8, 7) and down.shape == (7, 8)
    assert 0.0 < right[2, 2] <= RESIDUE_WEIGHT and right[7, 6] == 1.0 and down[6, 7] == 1.0
    assert np.all((right > 0.0) & (right <= 1.0)) and np.all((down > 0.0) & (down <= 1.0))


@settings(max_examples=30, deadline=None)
@given(
    slope=st.tuples(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4)),
    offset=st.floats(0.0, 0.999),
)
def test_curvature_is_zero_on_any_wrapped_plane(slope: tuple[float, float], offset: float) -> None:
    """A plane's wrapped second differences vanish inside the frame whatever its wraps
    (steps below half a wrap along every line, diagonals included: the slopes stay under
    0.25 in sum). Border pixels see their missing neighbour as themselves."""
    yy, xx = np.mgrid[0:12, 0:12]
    u = offset + slope[0] * yy / 2 + slope[1] * xx / 2
    assert curvature(u - np.floor(u))[1:-1, 1:-1].max() < 1e-5


def test_curvature_marks_a_step_and_its_pairs_weigh_less() -> None:
    """A step of 0.3 wrap (a smooth-looking aliased edge) has curvature on both sides of
    it, and pairs across it weigh less than pairs in the flat parts."""
    m = np.full((6, 10), 0.1)
    m[:, 5:] = 0.4
    bent = curvature(m)
    assert np.all(bent[:, 4:6] > 0.2) and bent[:, :3].max() == 0.0
    right, _ = pair_weights(m)
    assert np.all(right[:, 4] < right[:, 0]) and right[0, 0] == 1.0


@settings(max_examples=25, deadline=None)
@given(
    m=arrays(np.float64, (2, 2), elements=st.floats(0.0, 0.999)),
    prior=arrays(np.int64, (2, 2), elements=st.integers(0, 2)),
    weight=st.floats(0.01, 2.0),
    above=st.floats(0.0, 2.0),
    bounded=st.booleans(),
)
def test_moves_reach_the_global_minimum(
    m: np.ndarray, prior: np.ndarray, weight: float, above: float, bounded: bool
) -> None:
    """The guided energy is convex in K, whatever the prior's cost above the guide: +1/-1
    moves from the prior reach the minimum a brute-force search finds (K in -2..4 per
    pixel covers it); with bounds, the minimum over K within them, never leaving them."""
    bounds = (0, 2) if bounded else None
    pairs = (np.full((2, 1), 0.3), np.ones((1, 2)))
    energy = PumaEnergy(1.0, pairs, prior, weight, above, bounds)
    result = minimise(m, prior.copy(), energy, (1, -1), 100)
    levels = range(0, 3) if bounded else range(-2, 5)
    brute = min(
        energy(np.array(k).reshape(2, 2), m) for k in itertools.product(levels, repeat=4)
    )
    assert result.energies[-1] == pytest.approx(brute, abs=1e-9)
    assert all(b < a for a, b in itertools.pairwise(result.energies))
    if bounded:
        assert result.winding.min() >= 0 and result.winding.max() <= 2


def test_registry_lists_the_refined_tiers_and_resolves_any_guide() -> None:
    names = {spec.name for spec in available_decoders()}
    refined = {name for name in names if name.endswith("+puma")}
    assert all(name.removesuffix("+puma") in names for name in refined)
    spec = resolve("itoh+puma")
    assert spec.kind == "refined"
    decoder = spec.factory()
    assert decoder.name == "itoh+puma"
    frame = encode(_hill(48, 6.0), SensorParams(encoding="mantissa"))
    result = decoder.decode(frame.codes, SensorParams(encoding="mantissa"))
    np.testing.assert_array_equal(result.winding, frame.winding)


def test_a_net_guide_beyond_its_classes_needs_no_wrap_by_wrap_lifting() -> None:
    """A 1e-12 .. 1e30 log ramp along the rows (alpha 2: W up to 100): the small net
    answered W 0..2, and its refinement lifted the ramp's columns one wrap per min-cut
    (51 cuts, 80-110 s at 512x512) to 30% of W right. The net now integrates the frame
    (it has no residue: exact), so the refinement starts at the minimum: every move
    fails. (A frame with residues goes to herraez: test_learned.)"""
    params = SensorParams(encoding="mantissa", alpha=2.0, bits=8)
    frame = encode(np.tile(1e-12 * 1e42 ** np.linspace(0.0, 1.0, 320), (64, 1)), params)
    assert frame.winding.max() == 100
    result = get_decoder("mantissanet-small+puma").decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    details = result.info["details"]
    assert details["guide_details"] == {"integrated": learned.NO_RESIDUE}
    assert (details["moves"], details["changed_fraction"]) == (2, 0.0)


def test_a_move_budget_in_the_name_bounds_the_min_cuts() -> None:
    params = SensorParams(encoding="mantissa", max_wraps=64)
    frame = encode(_hill(peak=24.0), params)
    decoder = resolve("itoh+puma1").factory()
    assert isinstance(decoder, GuidedPumaDecoder)
    assert (decoder.name, decoder.max_moves) == ("itoh+puma1", 1)
    assert decoder.decode(frame.codes, params).info["details"]["moves"] == 1


@pytest.mark.parametrize("name", ["nonsense+puma", "+puma", "nonsense+puma2"])
def test_unknown_guides_are_a_clear_error(name: str) -> None:
    with pytest.raises(InvalidInputError, match="unknown decoder"):
        resolve(name)


@pytest.mark.parametrize(
    ("name", "moves"),
    [
        ("auto-fast+puma0", "0"),
        ("itoh+puma-1", "-1"),
        ("itoh+puma02", "02"),
        ("itoh+puma0+colour", "0"),
    ],
)
def test_a_move_count_below_1_says_what_k_takes(name: str, moves: str) -> None:
    """It was "unknown decoder 'auto-fast+puma0'; choose one of: ..." listing every
    decoder, with no word that K counts min-cuts and must be at least 1."""
    with pytest.raises(InvalidInputError) as caught:
        get_decoder(name)
    message = caught.value.message
    assert "unknown decoder" not in message
    guide = name.split("+puma")[0]
    assert f"must be a whole number of at least 1 (e.g. '{guide}+puma2'), not '{moves}'" in message


def test_windows_without_doubtful_pixels_keep_the_guide() -> None:
    params = SensorParams(encoding="mantissa", max_wraps=64)
    height, width = WINDOW + 44, WHOLE_FRAME_PIXELS // (WINDOW + 44) + 1
    frame = encode(_hill(size=height, width=width), params)
    decoder = GuidedPumaDecoder(CappedGuide(frame.winding, 2))
    m = frame.codes / 255.0
    guide = np.minimum(frame.winding, 2)
    doubtful = np.zeros(m.shape, bool)
    doubtful[:8, :8] = True
    winding, facts = decoder.refine(m, guide, params, doubtful)
    assert facts["windows"] == 1
    np.testing.assert_array_equal(winding[:, WINDOW:], guide[:, WINDOW:])


PARAMS = SensorParams(encoding="mantissa", max_wraps=64)


def _two_hills() -> tuple[np.ndarray, np.ndarray, np.ndarray, GuidedPumaDecoder]:
    """A 96 x 256 mantissa frame with two hills of several wraps, 128 px apart: its true
    W, its m, a guide capped at 2 wraps, and the refinement around that guide."""
    scene = np.concatenate([_hill(size=96, width=128), _hill(size=96, width=128)], axis=1)
    frame = encode(scene, PARAMS)
    decoder = GuidedPumaDecoder(CappedGuide(frame.winding, 2))
    return frame.winding, frame.codes / 255.0, np.minimum(frame.winding, 2), decoder


def test_only_boxes_around_doubtful_pixels_are_refined() -> None:
    """Each group of doubtful pixels is refined on its own box; the rest keeps the guide."""
    truth, m, guide, decoder = _two_hills()
    left = np.zeros(m.shape, bool)
    left[:, :128] = truth[:, :128] > 0
    winding, facts = decoder.refine(m, guide, PARAMS, left)
    np.testing.assert_array_equal(winding[:, :128], truth[:, :128])
    np.testing.assert_array_equal(winding[:, 128:], guide[:, 128:])
    assert facts["windows"] == 1
    winding, facts = decoder.refine(m, guide, PARAMS, truth > 2)
    np.testing.assert_array_equal(winding, truth)
    assert facts["windows"] == 2
    assert facts["changed_fraction"] == pytest.approx(np.mean(truth > 2))


def test_no_doubtful_pixel_keeps_the_guide_and_all_doubtful_refines_whole() -> None:
    _, m, guide, decoder = _two_hills()
    kept, facts = decoder.refine(m, guide, PARAMS, np.zeros(m.shape, bool))
    np.testing.assert_array_equal(kept, guide)
    assert facts == {"windows": 0, "region_moves": 0, "moves": 0, "changed_fraction": 0.0}
    whole, _ = decoder.refine(m, guide, PARAMS, np.ones(m.shape, bool))
    np.testing.assert_array_equal(whole, decoder.refine(m, guide, PARAMS)[0])


@pytest.mark.parametrize("shape", [(0, 5), (5, 0)])
def test_a_frame_without_pixels_is_refused_by_each_refinement(shape: tuple[int, int]) -> None:
    """Refined whole or within a band, an empty frame was a numpy padding error."""
    decoder = get_decoder("itoh+puma")
    assert isinstance(decoder, GuidedPumaDecoder)
    m, guide = np.zeros(shape), np.zeros(shape, np.int64)
    with pytest.raises(InvalidInputError, match="holds no pixels"):
        decoder.refine(m, guide, PARAMS)
    with pytest.raises(InvalidInputError, match="holds no pixels"):
        decoder.refine_within(m, guide, PARAMS, np.ones(shape, bool))


def test_a_refinement_within_a_band_changes_only_the_band() -> None:
    """Confined to the left hill, the pixel moves put its rings back and leave the right
    hill as the guide had it; a band over the whole frame reaches the true W."""
    truth, m, guide, _ = _two_hills()
    decoder = GuidedPumaDecoder(CappedGuide(truth, 2), region_moves=0)
    left = np.zeros(m.shape, bool)
    left[:, :128] = True
    winding, facts = decoder.refine_within(m, guide, PARAMS, left)
    np.testing.assert_array_equal(winding[:, :128], truth[:, :128])
    np.testing.assert_array_equal(winding[:, 128:], guide[:, 128:])
    assert facts["windows"] == 1 and facts["region_moves"] == 0 and facts["moves"] > 1
    assert facts["changed_fraction"] == pytest.approx(np.mean(winding != guide))
    whole, _ = decoder.refine_within(m, guide, PARAMS, np.ones(m.shape, bool))
    np.testing.assert_array_equal(whole, truth)
    kept, facts = decoder.refine_within(m, guide, PARAMS, np.zeros(m.shape, bool))
    np.testing.assert_array_equal(kept, guide)
    assert facts["changed_fraction"] == 0.0
