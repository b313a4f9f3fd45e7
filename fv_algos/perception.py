"""The perception core as one object: detect -> track -> field per frame, with stage timings.

`PerceptionParams.preset(name)` gives the three named configurations:
- 'paper': cv2.SimpleBlobDetector, nearest-neighbour tracking (several markers may take one
  detection), scipy RBFInterpolator refitted every frame;
- 'default': fast thresholded-component detector with sub-pixel centroids, one-to-one
  neighbour-predicted tracking, precomputed RBF operator;
- 'fastest': as 'default' with no centroid refinement and a single propagation round.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from fv_algos.detection import (
    DetectorParams,
    Detections,
    MarkerParams,
    detect_blobs,
    detect_fast,
    drop_border_markers,
    drop_crowded_markers,
    estimate_marker_params,
)
from fv_algos.field import MAX_MARKERS, DisplacementField, FieldInterpolator, FieldParams
from fv_algos.reference_markers import checked_reference, point_rows
from fv_algos.tracking import Tracker, TrackerParams, TrackState

PresetName = Literal["paper", "default", "fastest"]


@dataclass(frozen=True)
class PerceptionParams:
    """Everything the perception core needs; defaults are the 'default' preset.

    detector: 'blob' (the paper) or 'fast'. marker: marker appearance, None = estimated
    from the reference frame by `estimate_marker_params`. interpolation: the field settings.
    max_markers: a reference frame showing more is refused (`reset`): no marker grid but noise (a
    camera's garbage frame gave 3,494 "markers", a reference that cost 1.5 s to build and 0.2 s a frame
    to track, and whose markers no interpolator takes). The interpolator node's `max_markers` default.
    """

    detector: Literal["blob", "fast"] = "fast"
    marker: MarkerParams | None = None
    detection: DetectorParams = field(default_factory=DetectorParams)
    tracking: TrackerParams = field(default_factory=TrackerParams)
    interpolation: FieldParams = field(default_factory=FieldParams)
    max_markers: int = MAX_MARKERS

    def __post_init__(self) -> None:
        if self.detector not in ("blob", "fast"):
            raise ValueError(f"PerceptionParams.detector must be 'blob' or 'fast', got {self.detector!r}")
        if self.max_markers < 3:
            raise ValueError(f"PerceptionParams.max_markers {self.max_markers} must be >= 3")

    @staticmethod
    def preset(name: PresetName) -> "PerceptionParams":
        """One of the named configurations 'paper', 'default', 'fastest'."""
        if name == "default":
            return PerceptionParams()
        if name == "paper":
            return PerceptionParams(
                detector="blob",
                tracking=TrackerParams(method="nearest"),
                interpolation=FieldParams(method="rbf_refit"),
            )
        if name == "fastest":
            return PerceptionParams(
                detection=DetectorParams(refine_iterations=0),
                tracking=TrackerParams(rounds=1),
            )
        raise ValueError(f"unknown preset {name!r}; use 'paper', 'default' or 'fastest'")


def resumable_reference(reference_px: np.ndarray) -> np.ndarray:
    """(N, 2) float64 copy of reference marker positions `reference_px` (px) that `Perception.resume` can
    track against: ValueError naming what is wrong for fewer than 3 markers (no field) and for what
    `fv_algos.reference_markers.checked_reference` refuses (another shape, non-finite coordinates, a
    marker listed twice)."""
    ref = point_rows(reference_px, "reference_px")
    if ref.shape[0] < 3:
        raise ValueError(f"reference_px holds {ref.shape[0]} markers, need >= 3")
    return checked_reference(ref, "reference_px")


class Perception:
    """detect -> track -> field on camera frames ((H, W) uint8 or (H, W, 3) uint8 BGR).

    The first frame given to `reset` (or to `step` when none was) is the reference: the
    skin at rest. `timings_ms` holds the last frame's 'detect', 'track', 'field' times in ms.
    """

    def __init__(self, params: PerceptionParams = PerceptionParams()) -> None:
        self.params = params
        self.marker: MarkerParams | None = params.marker
        self.tracker: Tracker | None = None
        self.interpolator: FieldInterpolator | None = None
        self.frame_shape: tuple[int, int] | None = None  # (H, W) px of the reference frame
        self.timings_ms: dict[str, float] = {}

    def detect(self, image: np.ndarray) -> Detections:
        """Detections of one frame with the configured detector (needs `self.marker`); ValueError naming
        both sizes for a frame of another size than the reference's (its markers would be matched to
        positions of another image: a wrong field, taken as valid)."""
        if self.marker is None:
            raise ValueError("marker parameters unknown: call reset() with a reference frame first")
        if self.frame_shape is not None and image.shape[:2] != self.frame_shape:
            (h, w), (h0, w0) = image.shape[:2], self.frame_shape
            raise ValueError(f"a {w}x{h} frame, but the reference is {w0}x{h0}: take a new reference")
        return self._detect_any(image)

    def _detect_any(self, image: np.ndarray) -> Detections:
        """:meth:`detect` of a frame of any size (a new reference's)."""
        assert self.marker is not None
        if self.params.detector == "blob":
            return detect_blobs(image, self.marker, self.params.detection)
        return detect_fast(image, self.marker, self.params.detection)

    def reset(self, reference_image: np.ndarray) -> TrackState:
        """Start over with `reference_image` as the undeformed skin (estimates markers if unset).

        Markers cut by the frame edge are left out of the reference, and of blobs less than half a
        pitch apart all but the one that fits the marker lattice best (`drop_crowded_markers`). ValueError
        for a frame of fewer than 3 markers, or more than `max_markers`.
        """
        if self.params.marker is None:
            self.marker = estimate_marker_params(reference_image)
        assert self.marker is not None
        detected = drop_border_markers(
            self._detect_any(reference_image), reference_image.shape, 0.5 * self.marker.diameter_px + 1.0
        )
        if len(detected) > self.params.max_markers:  # before the costlier crowding and the field's solve
            raise ValueError(f"reference frame shows {len(detected)} markers, more than max_markers "
                             f"{self.params.max_markers}: noise, not a marker grid")
        reference = drop_crowded_markers(detected, 0.5 * self.marker.pitch_px)
        if len(reference) < 3:
            raise ValueError(f"reference frame shows {len(reference)} markers, need >= 3")
        self.tracker = Tracker(reference, self.params.tracking, cluttered=len(reference) < len(detected))
        self.interpolator = FieldInterpolator(reference.centres_px, self.params.interpolation)
        self.frame_shape = reference_image.shape[:2]
        return self.tracker.state

    def resume(self, image: np.ndarray, reference_px: np.ndarray) -> TrackState:
        """Go on tracking against markers taken as the reference earlier (e.g. by a tracker
        process that has since restarted), with `image` possibly showing the skin deformed.

        reference_px: (N, 2) undeformed marker positions in px that `resumable_reference` takes
        (ValueError naming what it refuses, and when the markers' look is unknown and `image` shows
        none to estimate it from: `estimate_marker_params`). The markers of
        `image` are matched to them as one tracking step (motions up to the tracker's
        one-frame limit, about 1.5 marker pitches, are followed); the markers are then taken as still
        (`Tracker.hold_still`): that step's motion is the deformation since the reference, not a frame's, and
        as the next step's prediction it put markers of a skin sheared by most of a pitch on a neighbour's
        dot. The markers' reference area (the
        tracker's area check) is the median detection's, or the marker disc's
        (`MarkerParams.area_px2`) when `image` shows none (e.g. the camera still dark): what the
        detector measures of an undeformed marker, so the markers are picked up once they show.
        The reference is taken as cluttered (`Tracker`'s `cluttered`, which `reset` sets when it left
        blobs out) when `image` holds blobs less than half a pitch apart: the earlier process's
        reference no longer shows what it left out, but clutter behind a transparent skin shows on later
        frames too. FingerVision video resumed at frame 300, 900, 1500 or 2100 from frame 1's reference:
        valid markers on another marker's dot up to its end 138, 347, 73 and 1,703 marker-frames with
        the rule, 487, 303, 159 and 2,141 without (116 tracked from frame 1 without a break). GelSight
        Mini trials: 3 of 10,076 frames so crowded (every 10th frame of the 300 videos).
        """
        ref = resumable_reference(reference_px)
        if self.params.marker is None:
            self.marker = estimate_marker_params(image)
        assert self.marker is not None
        detections = self._detect_any(image)
        area = float(np.median(detections.areas_px2)) if len(detections) else self.marker.area_px2
        cluttered = len(drop_crowded_markers(detections, 0.5 * self.marker.pitch_px)) < len(detections)
        self.tracker = Tracker(Detections(ref, np.full(ref.shape[0], area)), self.params.tracking, cluttered=cluttered)
        self.interpolator = FieldInterpolator(ref, self.params.interpolation)
        self.frame_shape = image.shape[:2]  # the caller's reference was taken on frames of this size
        state = self.tracker.step(detections)
        self.tracker.hold_still()  # this step's motion is the whole deformation, not a frame's
        return state

    def step(self, image: np.ndarray) -> tuple[TrackState, DisplacementField]:
        """Track one frame; returns the `TrackState` and the `DisplacementField`."""
        if self.tracker is None or self.interpolator is None:
            self.reset(image)
            return self.step(image)
        t0 = time.perf_counter()
        detections = self.detect(image)
        t1 = time.perf_counter()
        state = self.tracker.step(detections)
        t2 = time.perf_counter()
        dense = self.interpolator.interpolate(state.current_px, state.valid)
        t3 = time.perf_counter()
        self.timings_ms = {"detect": 1e3 * (t1 - t0), "track": 1e3 * (t2 - t1), "field": 1e3 * (t3 - t2)}
        return state, dense

