"""Per-frame contact motion of a GelSight-type camera (imprint vs markers), cached per video.

Physics: slip is the object moving relative to the skin. A GelSight-type image shows two things
that move: the dark markers (the skin) and the shading of the object's imprint. Per frame pair
:class:`ContactMotion` measures, on a small image (``size_px``), the ``SERIES``:

- ``relative_px``: texture-weighted mean |flow of the marker-free image - flow of the raw image|,
  i.e. imprint motion not explained by skin motion (markers removed by a grey closing of
  ``close_px``), px/frame at ``size_px`` scale;
- ``marker_px``: mean optical-flow speed of the raw image (dominated by the markers), px/frame at
  ``size_px`` scale;
- ``contact_above_min``: mean high-pass energy of the marker-free colour image (imprint shading)
  minus that of the emptiest frame so far, grey levels;
- ``imprint_change``: mean |marker-free colour image - that of the emptiest frame so far| (summed
  over B, G, R), grey levels: how far the imprint is from the bare skin (an object that slips
  away or out of the grasp brings it back);
- ``imprint_step_rms``: root-mean-square change of the marker-free colour image against the previous
  frame (summed over B, G, R) above the camera's noise floor, grey levels per frame: sqrt(max(m - m0,
  0)) of the mean squared change m, where m0 is the least m of the grasp so far (this frame
  included). Independent pixel noise adds its power to every m alike, so it cancels: the mean
  absolute change used before doubled for noise of 2 grey levels per pixel, and most slips read as
  held grasps.

The emptiest frame is the one of least shading from the reference on (this frame included): a
camera's start-up frames, brighter or more textured than its bare skin, never become it, so a
stale reference does not shift the whole trial.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from fv_algos import frame_crop, frame_rate, real_trials
from fv_algos.atomic_file import write_atomically
from fv_algos.frame_rate import pick
from fv_algos.frame_crop import FrameCrop
from fv_algos.real_trials import (Trial, VideoKey, cache_folder, cache_stem, code_digest, map_videos, read_cached,
                                   read_frames, video_key)

SERIES = ("relative_px", "marker_px", "contact_above_min", "imprint_change", "imprint_step_rms")
SERIES_CACHE_VERSION = 5


@dataclass(frozen=True)
class ContactMotionParams:
    """size_px: (width, height) the frame is resized to (area averaging). close_px: diameter of the
    grey closing that removes the dark markers (> a marker's diameter at ``size_px``). sigma_px:
    Gaussian high-pass scale of the contact shading. texture_floor: high-pass energy (grey levels,
    summed over BGR) below which a pixel has no imprint texture and gets no weight."""

    size_px: tuple[int, int] = (80, 60)
    close_px: int = 7
    sigma_px: float = 4.0
    texture_floor: float = 4.0


@dataclass(frozen=True)
class _Prepared:
    """One frame at ``size_px``: grey and marker-free grey (h, w) uint8, marker-free colour
    (h, w, 3) float32, its texture energy (h, w) float32 and that energy's mean (the shading,
    grey levels)."""

    grey: np.ndarray
    closed_grey: np.ndarray
    closed: np.ndarray
    texture: np.ndarray
    shading: float


class ContactMotion:
    """Per-frame ``SERIES`` of one camera, online: ``reset`` with the reference image, then ``step``
    every frame; it keeps the previous frame, the emptiest one so far and the noise floor."""

    def __init__(self, params: ContactMotionParams = ContactMotionParams()) -> None:
        self.params = params
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.close_px, params.close_px))
        self._emptiest: _Prepared | None = None
        self._previous: _Prepared | None = None
        self._floor = np.inf  # least mean squared step of the grasp so far, grey levels² per frame²

    def _prepare(self, image: np.ndarray) -> _Prepared:
        small = cv2.resize(image, self.params.size_px, interpolation=cv2.INTER_AREA)
        closed = cv2.morphologyEx(small, cv2.MORPH_CLOSE, self._kernel)
        closed_f = closed.astype(np.float32)
        texture = np.abs(closed_f - cv2.GaussianBlur(closed_f, (0, 0), self.params.sigma_px)).sum(axis=-1)
        return _Prepared(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), cv2.cvtColor(closed, cv2.COLOR_BGR2GRAY),
                         closed_f, texture, float(texture.mean()))

    def reset(self, image: np.ndarray) -> np.ndarray:
        """Start from ``image`` (H, W, 3) BGR uint8, the first emptiest frame; returns its row, zeros (5,)
        float32."""
        self._emptiest = self._previous = self._prepare(image)
        self._floor = np.inf
        return np.zeros(len(SERIES), np.float32)

    def step(self, image: np.ndarray) -> np.ndarray:
        """``SERIES`` (5,) float32 of ``image`` against the previous frame and the emptiest one so
        far (this frame included)."""
        if self._previous is None or self._emptiest is None:
            return self.reset(image)
        now, old = self._prepare(image), self._previous
        if now.shading < self._emptiest.shading:
            self._emptiest = now
        raw_flow = _flow(old.grey, now.grey)
        imprint_flow = _flow(old.closed_grey, now.closed_grey)
        weight = np.clip(np.maximum(now.texture, old.texture) - self.params.texture_floor, 0.0, None)
        relative = float((np.linalg.norm(imprint_flow - raw_flow, axis=-1) * weight).sum() / (weight.sum() + 1e-6))
        squared_step = float(np.square(now.closed - old.closed).sum(axis=-1).mean())
        self._floor = min(self._floor, squared_step)
        self._previous = now
        return np.array([relative, np.linalg.norm(raw_flow, axis=-1).mean(), now.shading - self._emptiest.shading,
                         np.abs(now.closed - self._emptiest.closed).sum(axis=-1).mean(),
                         np.sqrt(squared_step - self._floor)], np.float32)


def _flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Farneback optical flow (h, w, 2) px/frame from grey ``a`` to ``b``."""
    return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 2, 9, 3, 5, 1.1, 0)


def contact_series(frames: Iterable[np.ndarray], params: ContactMotionParams = ContactMotionParams(),
                   reference_frame: int = 1, rates: tuple[float, float] | None = None) -> np.ndarray:
    """(F, 5) float32 ``SERIES`` of BGR ``frames`` from ``reference_frame`` on (the frames
    :func:`fv_algos.real_trials.video_fields` keeps); with ``rates`` (video fps, model fps), only those
    of them that :func:`fv_algos.frame_rate.pick` keeps. ValueError when there is no such frame."""
    grasp = itertools.islice(frames, reference_frame, None)
    core, rows = ContactMotion(params), []
    for k, frame in enumerate(grasp if rates is None else pick(grasp, *rates)):
        rows.append(core.reset(frame) if k == 0 else core.step(frame))
    if not rows:
        raise ValueError(f"no frame at reference_frame={reference_frame}")
    return np.stack(rows)


def _series_cache_path(cache_dir: Path, video: Path, reference_frame: int, params: ContactMotionParams,
                       rates: tuple[float, float] | None, crop: FrameCrop | None) -> Path:
    key = [SERIES_CACHE_VERSION, *video_key(video, reference_frame, crop), asdict(params),
           code_digest(sys.modules[__name__], frame_rate, frame_crop, real_trials)]  # it hashed this module alone
    text = json.dumps(key if rates is None else [*key, list(rates)])
    return cache_dir / f"{cache_stem(video)}__contact__{hashlib.sha256(text.encode()).hexdigest()[:16]}.npy"


TrialSeries = dict[VideoKey, np.ndarray]


def _cached_series(video: Path, cache_dir: str | Path | None, reference_frame: int, params: ContactMotionParams,
                   rates: Mapping[Path, tuple[float, float]], crop: FrameCrop | None) -> np.ndarray:
    """:func:`contact_series` of one video (its frames cut by ``crop`` when given, picked at ``rates[video]``
    when it is there), read from / written to the cache when there is a cache folder."""
    rate = rates.get(video)
    cached = (None if cache_dir is None
              else _series_cache_path(Path(cache_dir), video, reference_frame, params, rate, crop))
    if cached is not None and (series := read_cached(cached, np.load)) is not None:
        return series
    try:
        series = contact_series(read_frames(video, crop), params, reference_frame, rate)
    except ValueError as exc:
        raise ValueError(f"{video}: {exc}") from exc
    if cached is not None:
        write_atomically(cached, lambda tmp: np.save(tmp, series))
    return series


def trial_series(trials: Sequence[Trial], cache_dir: str | Path | None = None, reference_frame: int = 1,
                 params: ContactMotionParams = ContactMotionParams(), workers: int = 1,
                 progress: bool = True, rates: Mapping[Path, tuple[float, float]] | None = None,
                 crop: FrameCrop | None = None) -> TrialSeries:
    """:func:`contact_series` of every camera of every trial, keyed (trial name, camera), in
    ``workers`` processes with one progress bar; cached as one .npy per video under ``cache_dir``
    (None: no cache; ValueError naming a folder that cannot be written), keyed by the video, the crop,
    the parameters, the rates and this module's code. ``rates``: (video fps, model fps) of the videos whose
    frames are picked at the model's rate (the others: all frames). ``crop``: the frames' cut (raw
    recordings, see :func:`fv_algos.real_trials.read_frames`)."""
    compute = partial(_cached_series, cache_dir=cache_folder(cache_dir), reference_frame=reference_frame,
                      params=params, rates=rates or {}, crop=crop)
    return map_videos(trials, compute, workers, progress, "contact motion")
