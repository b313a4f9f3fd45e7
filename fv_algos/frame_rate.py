"""Frame rates: a trial model judges frames at the rate it was trained at.

The trial network (:mod:`fv_algos.trial_net`) reads its descriptors frame by frame, and three of
them are per-frame rates: a camera twice as fast shows the same grasp as twice as many frames, each
with half the motion. A trial model therefore records its training frame rate (``fps``), and the
frames of a faster camera are picked at that rate by :class:`FramePicker`: from the grasp's first
frame on, the frame nearest to every model period, which is what a camera at the model's rate would
have filmed (to within half a frame of the faster camera). The picker works from stamps, so the
slip detector uses it on live frames (whatever their jitter or gaps) and ``fv eval`` on a video's
nominal stamps, with the same result. A camera slower than the model cannot be made faster: up to the
model's training time stretch (``TrialNetConfig.stretch``) it is taken as it is, beyond that
:func:`check_rate` refuses it.
"""
from __future__ import annotations

import collections
import math
import statistics
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from fv_algos.real_trials import Trial, VideoKey

T = TypeVar("T")
RATE_COLUMN = "fps"  # optional column of labels.csv: the trial's frame rate, Hz (else the video's own)


class FramePicker:
    """Keeps, of frames arriving at any rate, those a camera at ``fps`` Hz would have filmed. While the
    frames come no faster than that (the median of the last ``INTERVALS`` intervals at least the
    model's period, to ``FASTER``), every frame is kept: jitter, late or bunched frames of a camera
    at the model's rate never drop one. A faster camera has its grasp's first frame kept, then at every
    model period the frame nearest to it (kept when it is later than half the median interval ahead
    of the period); after a gap of more than a period the periods start again from the frame kept.
    Intervals longer than ``stretch`` model periods (a camera slower than a model trained with that
    time stretch takes, or frames lost) are counted in ``slow_gaps``, over every grasp."""

    INTERVALS = 9
    FASTER = 1.05  # a camera up to 5% faster than the model is taken as it is

    def __init__(self, fps: float, stretch: float = 1.0) -> None:
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"frame rate {fps} Hz must be finite and > 0")
        self.period_ns = 1e9 / fps
        self.longest_ns = stretch * self.period_ns
        self.slow_gaps = 0
        self.reset()

    def reset(self) -> None:
        """Forget the grasp: the next frame is its first, and kept."""
        self._due = 0.0  # stamp of the next period, ns
        self._last: int | None = None  # stamp of the last frame seen, ns
        self._intervals: collections.deque[int] = collections.deque(maxlen=self.INTERVALS)  # ns

    def accept(self, stamp_ns: int) -> bool:
        """Whether the frame of ``stamp_ns`` (ns, not before the frame before it) is kept."""
        last, self._last = self._last, stamp_ns
        if last is None:
            self._due = stamp_ns + self.period_ns
            return True
        self._intervals.append(stamp_ns - last)
        self.slow_gaps += stamp_ns - last > self.longest_ns
        interval = statistics.median(self._intervals)
        if interval * self.FASTER >= self.period_ns:  # not faster than the model: every frame counts
            self._due = stamp_ns + self.period_ns
            return True
        if stamp_ns + interval / 2 < self._due:
            return False
        self._due += self.period_ns
        if self._due <= stamp_ns:  # a gap: start the periods again from this frame
            self._due = stamp_ns + self.period_ns
        return True


def pick(frames: Iterable[T], video_fps: float, model_fps: float) -> Iterator[T]:
    """The ``frames`` (the grasp's, filmed at ``video_fps`` Hz: frame i at i / video_fps s) that
    :class:`FramePicker` keeps for a model of ``model_fps`` Hz: all of them when the video is not
    faster than the model."""
    picker = FramePicker(model_fps)
    return (frame for i, frame in enumerate(frames) if picker.accept(round(i * 1e9 / video_fps)))


def picked_frames(count: int, video_fps: float, model_fps: float) -> np.ndarray:
    """(K,) int64 indices of the frames :func:`pick` keeps of ``count`` frames."""
    return np.fromiter(pick(range(count), video_fps, model_fps), np.int64)


def video_rate(path: str | Path) -> float:
    """Frame rate (Hz) a video file's container gives; ValueError naming the file when it gives none
    (or not a finite rate > 0)."""
    capture = cv2.VideoCapture(str(path))
    try:
        fps = float(capture.get(cv2.CAP_PROP_FPS)) if capture.isOpened() else 0.0
    finally:
        capture.release()
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{path}: the video gives no frame rate (got {fps}); give it in the "
                         f"{RATE_COLUMN!r} column of labels.csv")
    return fps


def trial_rate(trial: Trial, camera: str) -> float:
    """Frame rate (Hz) of one camera of ``trial``: the ``fps`` column of labels.csv when the table has
    one, else the video's own (:func:`video_rate`); ValueError naming the trial for a rate that is
    not a number > 0."""
    given = trial.extra.get(RATE_COLUMN, "").strip()
    if not given:
        return video_rate(trial.videos[camera])
    try:
        fps = float(given)
    except ValueError:
        fps = math.nan
    if not (math.isfinite(fps) and fps > 0):
        where = f"{trial.row}: " if trial.row else ""
        raise ValueError(f"{where}trial {trial.name}: {RATE_COLUMN} {given!r} is not a frame rate > 0 (Hz)")
    return fps


def check_rate(name: str, video_fps: float, model_fps: float, stretch: float, advice: str) -> None:
    """ValueError naming ``name`` when a video of ``video_fps`` Hz is slower than a model of
    ``model_fps`` Hz trained with time stretch ``stretch`` (>= 1) can take: its frames would show
    more motion each than any training trial's. ``advice`` ends the error."""
    if video_fps * stretch < model_fps * (1 - 1e-6):
        raise ValueError(f"{name}: {video_fps:g} fps is slower than the model's {model_fps:g} fps allows "
                         f"(its training stretched time by up to {stretch:g}x, so {model_fps / stretch:.3g} fps at "
                         f"least): {advice}")


def judged_rates(trials: Sequence[Trial], fps: float | None = None,
                 stretch: float = 1.0) -> tuple[float, dict[VideoKey, float]]:
    """(the rate the descriptors of ``trials`` are taken at, the videos faster than it: (trial name,
    camera) -> their rate), all in Hz. ``fps``: a model's rate (None: the rate most of the videos
    have, for training); :func:`check_rate` refuses, naming the first, videos too slow for it."""
    rates = {(t.name, camera): trial_rate(t, camera) for t in trials for camera in t.videos}
    advice = "record faster, or train a model on recordings at this rate (fv real train)"
    if fps is None:
        fps = collections.Counter(rates.values()).most_common(1)[0][0]
        advice = (f"the training takes the rate most of its videos have; --fps {min(rates.values()):g} trains at the "
                  f"slowest (the faster videos' frames picked at it), or leave the slower videos out")
    for (name, camera), rate in rates.items():
        check_rate(f"trial {name} {camera}", rate, fps, stretch, advice)
    return fps, {key: rate for key, rate in rates.items() if rate > fps}
