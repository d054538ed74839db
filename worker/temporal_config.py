"""The knobs of temporal decoding (:mod:`worker.temporal`) and its modes.

:class:`TemporalConfig` gathers the rule's own settings and those of each step it
runs (motion and brightness compensation, the crop vote, arrival refinement, clip
tracking); every value is checked when the config is made, so a bad setting is
refused before a stream starts.
"""

from __future__ import annotations

from dataclasses import dataclass

from worker.arrivals import ArrivalConfig
from worker.brightness import BrightnessConfig
from worker.clip_tracking import ClipTrackConfig
from worker.config_checks import refuse_invalid
from worker.crop_vote import CropConfig
from worker.motion import MotionConfig

#: How a stream's frames are decoded: each on its own, or along time.
MODES: tuple[str, ...] = ("independent", "temporal")
#: The longest period of keyframes (frames): the most frames a video job holds, 2 x 2
#: frames of ``2 * MAX_RECORDING_SAMPLES`` code values (the largest
#: ``MCAM_MAX_VIDEO_SAMPLES``, :mod:`worker.recordings`): a longer one never comes (0
#: says "no periodic keyframes").
MAX_KEYFRAME_INTERVAL = 2**25


@dataclass(frozen=True)
class TemporalConfig:
    """Knobs of the temporal rule (see the module docstring). ``margin`` in wraps,
    ``still`` in wraps, ``motion_radius`` in pixels, ``keyframe_interval`` in frames
    (0: no periodic keyframes), ``local_limit`` a fraction of the frame's pixels,
    ``refine_moves`` the min-cuts of the final refinement (0: none), ``refine_reach``
    how far (px) from the fallback pixels it may change W, ``refine_whole_every`` every
    how many frames it refines the whole frame instead (0: never, 1: every frame), at
    first and again after a whole refinement that changed W beyond that reach, and
    ``refine_whole_max`` the longest wait (frames) it doubles to while they change nothing,
    ``refine_keyframes`` whether a stream's anchoring keyframes are refined,
    ``cut_misfit`` the mean misfit (wraps) of the moved, brightened previous frame
    above which a frame is a cut and anchors the stream anew (also above
    ``cut_sigmas`` sigmas of the sensor's frame-to-frame noise; 0.5: never),
    ``motion`` / ``brightness`` / ``crop`` the knobs of motion and brightness
    compensation, of the crop vote, of arrival refinement and of clip tracking
    (:class:`worker.motion.MotionConfig`, :class:`worker.brightness.BrightnessConfig`,
    :class:`worker.crop_vote.CropConfig`, :class:`worker.arrivals.ArrivalConfig`,
    :class:`worker.clip_tracking.ClipTrackConfig`)."""

    margin: float = 0.1
    motion_radius: int = 1
    still: float = 0.05
    steady_sigmas: float = 3.0
    keyframe_interval: int = 30
    local_limit: float = 0.5
    local_passes: int = 4
    refine_moves: int = 2
    refine_reach: int = 4
    refine_whole_every: int = 4
    refine_whole_max: int = 16
    refine_keyframes: bool = True
    cut_misfit: float = 0.1
    cut_sigmas: float = 2.4
    motion: MotionConfig = MotionConfig()
    brightness: BrightnessConfig = BrightnessConfig()
    crop: CropConfig = CropConfig()
    arrival: ArrivalConfig = ArrivalConfig()
    clip: ClipTrackConfig = ClipTrackConfig()

    def __post_init__(self) -> None:
        refuse_invalid(
            "temporal",
            {
                "margin must be in [0, 0.5)": 0.0 <= self.margin < 0.5,
                "still must be in [0, 0.5]": 0.0 <= self.still <= 0.5,
                "steady_sigmas must be >= 0": self.steady_sigmas >= 0.0,
                "motion_radius must be >= 0": self.motion_radius >= 0,
                f"keyframe_interval must be from 0 (no periodic keyframes) to "
                f"{MAX_KEYFRAME_INTERVAL} frames (the most a video holds), got "
                f"{self.keyframe_interval}": 0 <= self.keyframe_interval <= MAX_KEYFRAME_INTERVAL,
                "local_limit must be in [0, 1]": 0.0 <= self.local_limit <= 1.0,
                "local_passes must be >= 1": self.local_passes >= 1,
                "refine_moves must be >= 0": self.refine_moves >= 0,
                "refine_reach must be >= 0": self.refine_reach >= 0,
                "refine_whole_every must be >= 0": self.refine_whole_every >= 0,
                "cut_misfit must be in (0, 0.5]": 0.0 < self.cut_misfit <= 0.5,
                "cut_sigmas must be >= 0": self.cut_sigmas >= 0.0,
                "refine_whole_max must be >= refine_whole_every": (
                    self.refine_whole_max >= self.refine_whole_every
                ),
            },
        )
