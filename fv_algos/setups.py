"""Which set-up (camera, lens and skin) filmed each trial, so that training can draw every set-up's grasps of
each label alike (:class:`fv_algos.trial_net.TrialNetConfig` ``balance``): where one set-up holds mostly slips
and another mostly held grasps, a network can learn the set-up for the label.

A trial's set-up is the ``setup`` column of its table (``labels.csv``) where every trial has one; else the
markers' pitch in its first camera's reference frame, grouped: trials filmed through other optics or skins
see their markers at other pitches (the 150 GelSight Mini grasps: 30 to 32 px in 94 trials, 43 to 44 px in
56, none between). The pitch tells only magnifications apart: set-ups that film their markers at one pitch
are one set-up to it."""
from __future__ import annotations

from collections.abc import Sequence
from itertools import islice
from pathlib import Path

import numpy as np

from fv_algos.detection import estimate_marker_params
from fv_algos.frame_crop import FrameCrop
from fv_algos.real_trials import Trial, read_frames

SETUP_COLUMN = "setup"  # labels.csv column naming each trial's set-up
PITCH_STEP = 1.2  # a pitch more than this factor above the next smaller one starts another set-up


def marker_pitch(video: str | Path, frame: int, crop: FrameCrop | None = None) -> float:
    """The markers' pitch (px, centre to centre) in frame ``frame`` of ``video`` (its last when shorter), cut by
    ``crop``; ValueError naming the video when it has no frame or no markers are found."""
    image = None
    for image in islice(read_frames(video, crop), frame + 1):
        pass
    if image is None:
        raise ValueError(f"video {video}: no frame to measure the marker pitch in")
    try:
        return float(estimate_marker_params(image).pitch_px)
    except ValueError as error:
        raise ValueError(f"video {video}, frame {frame}: {error}") from None


def pitch_setups(pitches: Sequence[float], step: float = PITCH_STEP) -> list[str]:
    """A set-up name per pitch (px): sorted, the pitches split wherever one is more than ``step`` times the one
    before; each group named by its range ("pitch 29-32 px"), the names in the order of the pitches."""
    pitches = np.asarray(pitches, np.float64)
    if pitches.size == 0:
        return []
    if not np.all(np.isfinite(pitches) & (pitches > 0)):
        raise ValueError(f"marker pitches must be finite and > 0, got {pitches[~(np.isfinite(pitches) & (pitches > 0))]}")
    order = np.argsort(pitches, kind="stable")
    sorted_pitches = pitches[order]
    group = np.concatenate([[0], np.cumsum(sorted_pitches[1:] > step * sorted_pitches[:-1])])
    names = {g: f"pitch {sorted_pitches[group == g].min():.0f}-{sorted_pitches[group == g].max():.0f} px"
             for g in np.unique(group)}
    out = np.empty(pitches.size, object)
    out[order] = [names[g] for g in group]
    return out.tolist()


def trial_setups(trials: Sequence[Trial], reference_frame: int = 1, crop: FrameCrop | None = None) -> list[str]:
    """Each trial's set-up: its ``setup`` column where the table has one, else :func:`pitch_setups` of the
    marker pitch in frame ``reference_frame`` of its first camera. ValueError naming the trials (and their
    table lines) whose cell is empty when others are filled."""
    column = [t.extra.get(SETUP_COLUMN, "").strip() for t in trials]
    if any(column):
        empty = [f"{t.name} ({t.row})" if t.row else t.name for t, name in zip(trials, column) if not name]
        if empty:
            raise ValueError(f"the {SETUP_COLUMN} column names the set-up of {len(trials) - len(empty)} trials but not "
                             f"of {len(empty)}: {', '.join(empty[:5])}{' ...' if len(empty) > 5 else ''}")
        return column
    return pitch_setups([marker_pitch(t.videos[min(t.videos)], reference_frame, crop) for t in trials])


def setup_counts(setups: Sequence[str], labels: np.ndarray) -> dict[str, dict[str, int]]:
    """Trials per set-up and label: {set-up: {"slip": n, "no_slip": n}}, set-ups sorted."""
    labels = np.asarray(labels)
    names = np.asarray(setups)
    return {name: {"slip": int(np.sum((names == name) & (labels == 1))),
                   "no_slip": int(np.sum((names == name) & (labels == 0)))} for name in sorted(set(setups))}
