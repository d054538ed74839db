"""Video files of reconstructed clips: HDR10 HEVC, an SDR H.264 preview, an EXR sequence.

Frames are linear reconstructions ``x_hat`` (wrap units), ``H x W`` (grey) or
``H x W x 3`` (Rec.709 primaries), all of one clip.

HDR10 (:func:`write_hdr10`): absolute luminance ``L = x / white_level *
reference_white`` cd/m^2 (default: ``x = 1``, a conventional pixel's saturation,
is the BT.2408 reference white of 203 cd/m^2), converted to BT.2020 primaries,
PQ-encoded (SMPTE ST 2084, clipped at 10000 cd/m^2), turned into BT.2020
non-constant-luminance Y'CbCr, 10-bit limited range, chroma averaged over 2 x 2
(4:2:0), and encoded with libx265 as HEVC Main10 in MP4 (``hvc1``). The colour tags
(primaries bt2020, transfer smpte2084, matrix bt2020nc, limited range) are set on
the codec context and in the bitstream (x265-params), with mastering-display (P3-D65
primaries, ``mastering_peak`` cd/m^2) and content-light-level (MaxCLL / MaxFALL
measured from the frames) SEI metadata. Odd sizes are padded by repeating the last
row / column; sides below ``MIN_HDR10_SIDE`` are refused (libx265 crashes on them), and
sides past what each MP4 output takes (:data:`MAX_MP4_SIDES`) by both videos.

The SDR preview (:func:`write_sdr_preview`) is Reinhard-tonemapped (one key for the
whole clip, from its middle frame, so the preview does not pump), sRGB-encoded,
8-bit 4:2:0 H.264. The EXR sequence (:func:`exr_sequence_zip`) is a zip of one
float32 (or half) EXR per frame, ``frame_00000.exr`` ... (:func:`exr_frame_name`), of the
values it is given
(the pipeline gives scene-referred ``x / gain`` when the gain is known, else wrap units)
and the header attributes it is given per frame.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import IO, Any

import av
import numpy as np
from av.video.reformatter import ColorPrimaries, ColorRange, Colorspace, ColorTrc
from numpy.typing import NDArray

from models.display import srgb8
from models.errors import InvalidInputError
from models.formation import to_scene
from models.hdr_io import DEFAULT_EXR_COMPRESSION, encode_exr
from models.metrics import reinhard
from models.output_range import ensure_fits, ensure_nonzero_kept

#: ITU-R BT.2408 reference (diffuse) white, cd/m^2.
REFERENCE_WHITE = 203.0
PQ_PEAK = 10_000.0
_PQ_M1, _PQ_M2 = 2610 / 16384, 2523 / 4096 * 128
_PQ_C1, _PQ_C2, _PQ_C3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
#: Linear Rec.709 RGB to linear BT.2020 RGB (ITU-R BT.2087).
BT709_TO_BT2020 = np.array(
    [[0.6274, 0.3293, 0.0433], [0.0691, 0.9195, 0.0114], [0.0164, 0.0880, 0.8956]]
)
BT2020_KR, BT2020_KB = 0.2627, 0.0593
#: 10-bit limited ("video") range: Y' in [64, 940], Cb/Cr in [64, 960] around 512.
LUMA_OFFSET, LUMA_SCALE, CHROMA_OFFSET, CHROMA_SCALE = 64, 876, 512, 896
#: libx265 corrupts its heap on frames smaller than this (pixels per side, measured).
MIN_HDR10_SIDE = 64
#: The longest side (pixels, once an odd side is padded) of each MP4 output: libx264
#: refuses frames past 16384 ("Generic error in an external library", measured at 16386)
#: and the MP4 track header holds sides below 65536 ("Invalid argument" at 65536).
MAX_MP4_SIDES = {"hdr10": 65534, "sdr": 16384}
#: What each MP4 output is called in messages.
MP4_OUTPUT_NAMES = {"hdr10": "HDR10 video", "sdr": "the SDR preview (H.264)"}
#: x265's B-frame delay with b-pyramid (frames): shorter clips need B-frames off (see below).
X265_BFRAME_DELAY = 2
#: Mastering display: P3-D65 primaries in x265's units of 0.00002.
MASTERING_PRIMARIES = "G(13250,34500)B(7500,3000)R(34000,16000)WP(15635,16450)"

#: Fewest digits of an EXR frame's number (``frame_00000.exr``, :func:`exr_frame_name`).
EXR_INDEX_DIGITS = 5

#: Frame rates a video may have (frames per second).
FPS_RANGE = (0.1, 1000.0)
#: NTSC rates n * 1000/1001 that a rounded rate (23.976, 29.97, 59.94) stands for.
NTSC_RATES = tuple(Fraction(n * 1000, 1001) for n in (24, 30, 48, 60, 120, 240))
#: How close (relative) a rate must be to an NTSC rate to be taken for it: 23.98, the
#: label editors show for 24000/1001, is 1.7e-4 off; 24 and 30 are 1e-3 off theirs.
NTSC_TOLERANCE = 5e-4
#: x265's quality scale (``crf``: lower is better) and its presets, fastest first.
CRF_RANGE = (0, 51)
X265_PRESETS = (
    "ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower",
    "veryslow", "placebo",
)  # fmt: skip
#: ``white_level`` (wrap units) a video may show at its reference white: from below a
#: 16-bit code step (x = 2^-16) to far past any wrap count a 16-bit code reaches.
WHITE_LEVEL_RANGE = (1e-6, 1e30)
#: Reference white (cd/m^2): PQ reaches 10000; under 1 cd/m^2 nothing is visible.
REFERENCE_WHITE_RANGE = (1.0, PQ_PEAK)

Target = str | IO[bytes]
Progress = Callable[[int], None]


def check_range(name: str, value: float, bounds: tuple[float, float], unit: str) -> None:
    """Refuse ``value`` outside ``bounds`` (inclusive; NaN is outside), naming ``unit``."""
    low, high = bounds
    if not low <= value <= high:  # False for NaN too
        raise InvalidInputError(f"{name} must be from {low:g} to {high:g} {unit}, got {value:g}")


@dataclass(frozen=True)
class Hdr10Settings:
    """HDR10 encoding choices. ``fps``: frames per second (:data:`FPS_RANGE`);
    ``white_level``: the ``x`` (wrap units, :data:`WHITE_LEVEL_RANGE`) shown at
    ``reference_white`` cd/m^2 (:data:`REFERENCE_WHITE_RANGE`); ``mastering_peak`` /
    ``mastering_floor`` in cd/m^2; ``crf``: x265 quality (lower is better); ``lossless``:
    x265 lossless mode; ``preset``: one of :data:`X265_PRESETS`. Values out of range (NaN,
    inf) are refused: they render a clip all black or all white, or no clip at all."""

    fps: float = 30.0
    white_level: float = 1.0
    reference_white: float = REFERENCE_WHITE
    mastering_peak: float = 1000.0
    mastering_floor: float = 0.0001
    crf: int = 16
    preset: str = "fast"
    lossless: bool = False

    def __post_init__(self) -> None:
        check_range("fps", self.fps, FPS_RANGE, "frames per second")
        check_range("white_level", self.white_level, WHITE_LEVEL_RANGE, "wrap units")
        check_range("reference_white", self.reference_white, REFERENCE_WHITE_RANGE, "cd/m^2")
        check_range("crf", self.crf, CRF_RANGE, "(x265 quality, lower is better)")
        if self.preset not in X265_PRESETS:
            raise InvalidInputError(
                f"preset must be one of {', '.join(X265_PRESETS)}, got {self.preset!r}"
            )
        if not 0 < self.mastering_floor < self.mastering_peak <= PQ_PEAK:
            raise InvalidInputError(
                f"mastering luminance must satisfy 0 < floor < peak <= {PQ_PEAK:g} cd/m^2"
            )


@dataclass(frozen=True)
class LightLevels:
    """Content light levels in cd/m^2: MaxCLL (brightest pixel, max of R, G, B) and
    MaxFALL (the largest frame-average of max(R, G, B)), both clipped to 10000; and the
    share of the clip's pixels past 10000 cd/m^2, which PQ shows all at its peak (raise
    ``white_level`` to keep them apart)."""

    max_cll: int
    max_fall: int
    clipped_share: float = 0.0


def pq_encode(nits: NDArray[np.floating]) -> NDArray[np.float64]:
    """SMPTE ST 2084 inverse EOTF: absolute luminance (cd/m^2) to the PQ signal in [0, 1]."""
    y = np.clip(np.asarray(nits, np.float64) / PQ_PEAK, 0.0, 1.0) ** _PQ_M1
    return ((_PQ_C1 + _PQ_C2 * y) / (1.0 + _PQ_C3 * y)) ** _PQ_M2


def pq_decode(signal: NDArray[np.floating]) -> NDArray[np.float64]:
    """SMPTE ST 2084 EOTF: PQ signal in [0, 1] to absolute luminance (cd/m^2)."""
    e = np.clip(np.asarray(signal, np.float64), 0.0, 1.0) ** (1.0 / _PQ_M2)
    return PQ_PEAK * (np.maximum(e - _PQ_C1, 0.0) / (_PQ_C2 - _PQ_C3 * e)) ** (1.0 / _PQ_M1)


def as_rgb(frame: NDArray[np.floating]) -> NDArray[np.float64]:
    """A frame as ``H x W x 3`` float64 (grey repeated), checked finite and non-negative."""
    arr = np.asarray(frame, np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 2:
        arr = np.repeat(arr[:, :, None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise InvalidInputError(f"a video frame is H x W or H x W x 3, got shape {arr.shape}")
    if not np.isfinite(arr).all() or (arr < 0).any():
        raise InvalidInputError("video frames must be finite and non-negative")
    return arr


def pad_even(image: NDArray[Any]) -> NDArray[Any]:
    """Repeat the last row / column so both sides are even (4:2:0 needs it)."""
    pad = [(0, image.shape[0] % 2), (0, image.shape[1] % 2)] + [(0, 0)] * (image.ndim - 2)
    return np.pad(image, pad, mode="edge") if any(p[1] for p in pad[:2]) else image


def to_nits(frame: NDArray[np.floating], settings: Hdr10Settings) -> NDArray[np.float64]:
    """Absolute luminance in BT.2020 primaries (``H x W x 3``, cd/m^2) of a frame; a
    value past float64's range is ``inf``, which the PQ curve and the light levels clip
    to :data:`PQ_PEAK` like any value above it."""
    with np.errstate(over="ignore"):
        rgb = as_rgb(frame) @ BT709_TO_BT2020.T
        return np.maximum(rgb, 0.0) * (settings.reference_white / settings.white_level)


@dataclass(frozen=True)
class FrameLight:
    """One frame's part of a clip's :class:`LightLevels`: its brightest pixel and its
    average of max(R, G, B) (cd/m^2, both clipped to 10000), and how many of its
    ``pixels`` are past 10000 cd/m^2 (``clipped``)."""

    brightest: float
    average: float
    clipped: int
    pixels: int


def frame_light(frame: NDArray[np.floating], settings: Hdr10Settings) -> FrameLight:
    """A frame's :class:`FrameLight` (a pipeline measures each as it is decoded)."""
    brightest = to_nits(frame, settings).max(axis=2)
    clipped = int(np.count_nonzero(brightest > PQ_PEAK))
    brightest = np.minimum(brightest, PQ_PEAK)
    return FrameLight(float(brightest.max()), float(brightest.mean()), clipped, brightest.size)


def clip_light(lights: Sequence[FrameLight]) -> LightLevels:
    """The :class:`LightLevels` of a clip whose frames measured ``lights``."""
    cll = max((light.brightest for light in lights), default=0.0)
    fall = max((light.average for light in lights), default=0.0)
    pixels = sum(light.pixels for light in lights)
    clipped = sum(light.clipped for light in lights) / max(pixels, 1)
    return LightLevels(int(np.ceil(cll)), int(np.ceil(fall)), clipped)


def light_levels(frames: Sequence[NDArray[np.floating]], settings: Hdr10Settings) -> LightLevels:
    """MaxCLL and MaxFALL of a clip (see :class:`LightLevels`)."""
    return clip_light([frame_light(frame, settings) for frame in frames])


def hdr10_yuv(
    frame: NDArray[np.floating], settings: Hdr10Settings
) -> list[NDArray[np.uint16]]:
    """One frame as 10-bit limited-range planes: Y (H x W), Cb and Cr (H/2 x W/2)."""
    signal = pad_even(pq_encode(to_nits(frame, settings)))
    r, g, b = signal[:, :, 0], signal[:, :, 1], signal[:, :, 2]
    y = BT2020_KR * r + (1.0 - BT2020_KR - BT2020_KB) * g + BT2020_KB * b
    cb = (b - y) / (2.0 * (1.0 - BT2020_KB))
    cr = (r - y) / (2.0 * (1.0 - BT2020_KR))
    height, width = y.shape

    def subsample(c: NDArray[np.float64]) -> NDArray[np.float64]:
        return c.reshape(height // 2, 2, width // 2, 2).mean(axis=(1, 3))

    luma = np.rint(LUMA_OFFSET + LUMA_SCALE * y).astype(np.uint16)
    chroma = [np.rint(CHROMA_OFFSET + CHROMA_SCALE * subsample(c)).astype(np.uint16)
              for c in (cb, cr)]
    return [luma, *chroma]


def yuv_frame(planes: list[NDArray[np.uint16]]) -> av.VideoFrame:
    """A yuv420p10le frame holding the planes (rows copied into FFmpeg's padded lines)."""
    height, width = planes[0].shape
    video = av.VideoFrame(width, height, "yuv420p10le")
    for target, plane in zip(video.planes, planes, strict=True):
        padded = np.zeros((plane.shape[0], target.line_size // 2), np.uint16)
        padded[:, : plane.shape[1]] = plane
        target.update(padded.astype("<u2").tobytes())
    video.color_primaries = ColorPrimaries.BT2020
    video.color_trc = ColorTrc.SMPTE2084
    video.colorspace = Colorspace.BT2020
    video.color_range = ColorRange.MPEG
    return video


def x265_params(settings: Hdr10Settings, levels: LightLevels, frame_count: int) -> str:
    """The x265-params string: HDR10 signalling, colour tags, mastering and light levels.

    A clip of at most ``X265_BFRAME_DELAY`` frames is encoded without B-frames: x265 derives
    the decode timestamps of its first packets from the pts of frame number
    ``X265_BFRAME_DELAY``, and when that frame never comes it hands out uninitialised dts
    values, which the MP4 muxer then refuses at random."""
    peak = int(round(settings.mastering_peak * 10_000))
    floor = max(int(round(settings.mastering_floor * 10_000)), 1)
    params = [
        "hdr10=1",
        "hdr10-opt=1",
        "repeat-headers=1",
        "colorprim=bt2020",
        "transfer=smpte2084",
        "colormatrix=bt2020nc",
        "range=limited",
        "chromaloc=1",  # chroma averaged over 2 x 2 blocks sits at their centre (type 1)
        f"master-display={MASTERING_PRIMARIES}L({peak},{floor})",
        f"max-cll={levels.max_cll},{levels.max_fall}",
        "log-level=error",
    ]
    if settings.lossless:
        params.append("lossless=1")
    if frame_count <= X265_BFRAME_DELAY:
        params.append("bframes=0")
    return ":".join(params)


def _check_clip(frames: Sequence[NDArray[np.floating]]) -> tuple[int, int]:
    """Even-padded (height, width) of a non-empty clip whose frames all share one shape."""
    if len(frames) == 0:
        raise InvalidInputError("the clip has no frames; give at least one")
    shapes = {np.shape(frame) for frame in frames}
    if len(shapes) != 1:
        raise InvalidInputError(f"all frames of a clip must have one shape, got {sorted(shapes)}")
    height, width = np.shape(frames[0])[:2]
    return height + height % 2, width + width % 2


def mp4_size_problem(output: str, height: int, width: int) -> str | None:
    """Why the encoder of MP4 ``output`` (``hdr10`` or ``sdr``) does not take frames of
    ``height`` x ``width`` px once an odd side is padded by a pixel (as the writers do):
    smaller than :data:`MIN_HDR10_SIDE` for HDR10, or a side past :data:`MAX_MP4_SIDES`;
    None when it does."""
    padded = (height + height % 2, width + width % 2)
    if output == "hdr10" and min(padded) < MIN_HDR10_SIDE:
        return (
            f"HDR10 video needs frames of at least {MIN_HDR10_SIDE} x {MIN_HDR10_SIDE} pixels, "
            f"got {height} x {width}"
        )
    if max(padded) > MAX_MP4_SIDES[output]:
        return (
            f"{MP4_OUTPUT_NAMES[output]} takes frames of at most {MAX_MP4_SIDES[output]} "
            f"pixels a side, got {height} x {width}"
        )
    return None


def padding_note(outputs: Iterable[str], height: int, width: int) -> str | None:
    """What the MP4 videos among ``outputs`` (names of :data:`MAX_MP4_SIDES`; others are
    not padded) of frames ``height`` x ``width`` px are padded to, and why, when a side
    is odd (:func:`pad_even`); None when both sides are even or no output is an MP4."""
    if not (height % 2 or width % 2) or not set(MAX_MP4_SIDES) & set(outputs):
        return None
    return (
        f"the MP4 videos are {height + height % 2} x {width + width % 2}: 4:2:0 video "
        f"needs even sides, so the last row / column of the {height} x {width} frames "
        "is repeated (EXR frames keep their size)"
    )


def check_mp4_frame_size(output: str, height: int, width: int, remedy: str) -> None:
    """Refuse frames (px) that MP4 ``output`` does not take (:func:`mp4_size_problem`);
    ``remedy`` says what the caller can ask for instead."""
    if problem := mp4_size_problem(output, height, width):
        raise InvalidInputError(f"{problem}; {remedy}")


def write_hdr10(
    frames: Sequence[NDArray[np.floating]],
    target: Target,
    settings: Hdr10Settings | None = None,
    progress: Progress | None = None,
    levels: LightLevels | None = None,
) -> LightLevels:
    """Encode a clip as HDR10 HEVC Main10 MP4 to a path or binary file; returns its light
    levels (``levels`` when the caller measured them, else measured here from all frames
    before the first is encoded). ``progress(n)`` is called after each of the n frames
    written."""
    settings = settings or Hdr10Settings()
    height, width = _check_clip(frames)
    check_mp4_frame_size("hdr10", *np.shape(frames[0])[:2], "ask for the EXR sequence instead")
    levels = levels or light_levels(frames, settings)
    with av.open(target, mode="w", format="mp4") as container:
        stream = add_hdr10_stream(container, settings, levels, (height, width), len(frames))
        for index, frame in enumerate(frames):
            container.mux(stream.encode(yuv_frame(hdr10_yuv(frame, settings))))
            if progress:
                progress(index + 1)
        container.mux(stream.encode(None))
    return levels


def add_hdr10_stream(
    container: av.container.OutputContainer,
    settings: Hdr10Settings,
    levels: LightLevels,
    size: tuple[int, int],
    frame_count: int,
) -> av.VideoStream:
    """Add the libx265 HEVC Main10 stream of an HDR10 clip of ``frame_count`` frames of
    ``size`` (even height, width in pixels) to an MP4 container, colour tags on its context."""
    stream = container.add_stream("libx265", rate=frame_rate(settings.fps))
    stream.height, stream.width = size
    stream.pix_fmt = "yuv420p10le"
    stream.codec_tag = "hvc1"
    context = stream.codec_context
    context.color_primaries = ColorPrimaries.BT2020
    context.color_trc = ColorTrc.SMPTE2084
    context.colorspace = Colorspace.BT2020
    context.color_range = ColorRange.MPEG
    stream.options = {
        "crf": str(settings.crf),
        "preset": settings.preset,
        "x265-params": x265_params(settings, levels, frame_count),
    }
    return stream


def frame_rate(fps: float) -> Fraction:
    """``fps`` as the exact fraction PyAV takes: an NTSC rate (24000/1001, 30000/1001, ...)
    for its rounded value (23.976, 29.97, ...), else the nearest fraction over <= 1001."""
    for rate in NTSC_RATES:
        if abs(fps / rate - 1) < NTSC_TOLERANCE:
            return rate
    return Fraction(fps).limit_denominator(1001)


def sdr_frames(frames: Sequence[NDArray[np.floating]]) -> Iterator[NDArray[np.uint8]]:
    """8-bit sRGB previews: Reinhard on luminance keyed on the middle frame, colour kept.
    Each is made when the next is asked for: made all first, they held the preview's
    progress (and a cancel) at its start for 80% of its time, and all its frames at once."""
    key = as_rgb(frames[len(frames) // 2])
    for frame in frames:
        rgb = as_rgb(frame)
        lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
        tone = reinhard(rgb, key)
        yield pad_even(srgb8(rgb * (tone / np.maximum(lum, 1e-12))[:, :, None]))


def write_sdr_preview(
    frames: Sequence[NDArray[np.floating]],
    target: Target,
    fps: float = 30.0,
    crf: int = 20,
    progress: Progress | None = None,
) -> None:
    """Encode the tonemapped clip as 8-bit H.264 (yuv420p, BT.709 tags) MP4 at ``fps``
    (:data:`FPS_RANGE`) and x264 quality ``crf`` (:data:`CRF_RANGE`)."""
    check_range("fps", fps, FPS_RANGE, "frames per second")
    check_range("crf", crf, CRF_RANGE, "(x264 quality, lower is better)")
    height, width = _check_clip(frames)
    check_mp4_frame_size("sdr", *np.shape(frames[0])[:2], "ask for the EXR sequence instead")
    with av.open(target, mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=frame_rate(fps))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": str(crf), "preset": "fast"}
        context = stream.codec_context
        context.color_primaries = ColorPrimaries.BT709
        context.color_trc = ColorTrc.IEC61966_2_1
        context.colorspace = Colorspace.ITU709
        context.color_range = ColorRange.MPEG
        for index, image in enumerate(sdr_frames(frames)):
            video = av.VideoFrame.from_ndarray(image, format="rgb24").reformat(
                format="yuv420p", dst_colorspace=Colorspace.ITU709, dst_color_range=ColorRange.MPEG
            )
            container.mux(stream.encode(video))
            if progress:
                progress(index + 1)
        container.mux(stream.encode(None))


def exr_sequence_zip(
    frames: Sequence[NDArray[np.floating]],
    target: Target,
    *,
    half: bool = False,
    compression: str = DEFAULT_EXR_COMPRESSION,
    attributes: Sequence[dict[str, str]] | None = None,
    scene_gain: float | None = None,
    checked: bool = False,
    progress: Progress | None = None,
) -> None:
    """A zip of one EXR per frame (:func:`exr_frame_name`) of reconstructed ``frames``
    (wrap units ``x``; stored as scene units ``x / scene_gain`` when the gain is known,
    converted a frame at a time), each compressed as ``compression``
    (:data:`models.hdr_io.EXR_COMPRESSIONS`), with ``frameIndex`` and that frame's
    ``attributes`` (string header attributes, one mapping per frame) in its header.
    Refused, before anything is written, as :func:`check_exr_sequence` says (unless
    ``checked``: the caller ran that check on these frames already). ``progress(n)`` is
    called after each of the n frames stored."""
    if not checked:
        check_exr_sequence(frames, half=half, scene_gain=scene_gain)
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_STORED) as archive:
        for index, frame in enumerate(frames):
            header = {"frameIndex": str(index)} | (attributes[index] if attributes else {})
            stored = frame if scene_gain is None else to_scene(frame, scene_gain)
            data = encode_exr(stored, header, half=half, compression=compression)
            archive.writestr(exr_frame_name(index, len(frames)), data)
            if progress:
                progress(index + 1)


def exr_frame_name(index: int, count: int) -> str:
    """The zip entry of frame ``index`` of a clip of ``count`` frames: ``frame_`` and the
    index padded with zeros to :data:`EXR_INDEX_DIGITS` digits, or to as many as the last
    index has, so that the names of a longer clip still sort in frame order."""
    digits = max(EXR_INDEX_DIGITS, len(str(count - 1)))
    return f"frame_{index:0{digits}d}.exr"


def check_exr_sequence(
    frames: Sequence[NDArray[np.floating]], *, half: bool, scene_gain: float | None
) -> None:
    """Raise :class:`models.errors.OutputOverflowError` or
    :class:`models.errors.OutputUnderflowError` if a pixel of ``frames`` (wrap units,
    stored divided by ``scene_gain`` when given) would be stored as inf or 0 in float32
    (or float16 with ``half``), and :class:`InvalidInputError` for a value that is not
    finite or is negative. A pipeline calls it before encoding any other output, so a
    clip that cannot be stored fails before minutes of video encoding. Half floats keep
    values below 6.1e-5 (their subnormals) to an absolute 3e-8, not to their relative
    precision."""
    _check_clip(frames)
    for index, frame in enumerate(frames):
        check_exr_frame(frame, index, half=half, scene_gain=scene_gain)


def check_exr_frame(
    frame: NDArray[np.floating], index: int, *, half: bool, scene_gain: float | None
) -> None:
    """:func:`check_exr_sequence` for frame ``index`` of a clip (wrap units ``x``): a
    pipeline runs it on each frame as soon as it is decoded, so that a clip whose EXR
    frames cannot be stored fails at its first such frame."""
    values = np.asarray(frame)
    if not np.isfinite(values).all() or (values < 0).any():
        raise InvalidInputError(
            f"video frame {index} has values that are not finite or are negative; "
            "reconstructions are finite and non-negative"
        )
    dtype = np.float16 if half else np.float32
    stored = frame if scene_gain is None else to_scene(frame, scene_gain)
    ensure_fits(stored, dtype, f"video frame {index}", scene_gain)
    ensure_nonzero_kept(stored, dtype, f"video frame {index}", scene_gain)
