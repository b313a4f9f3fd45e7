"""Marker detection: the paper's blob detector and a fast thresholded-component detector.

Both detectors take a camera frame, (H, W) uint8 mono or (H, W, 3) uint8 BGR, and return
`Detections`: marker centres in px (x right, y down, pixel centres at integer coordinates)
and marker areas in px^2. `estimate_marker_params` derives the marker diameter, pitch,
polarity and contrast from one reference frame so that nobody has to tune by hand.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Literal

import cv2
import numpy as np
from scipy.spatial import cKDTree

Polarity = Literal["dark", "light"]


@dataclass(frozen=True)
class MarkerParams:
    """What the markers look like in the image; defaults fit the simulated sensor.

    diameter_px: marker diameter in px. pitch_px: typical centre-to-centre spacing in px.
    polarity: 'dark' markers on a lighter skin or 'light' markers on a darker one.
    contrast: grey levels (0-255) between a marker's core and the local background.
    """

    diameter_px: float = 9.0
    pitch_px: float = 25.0
    polarity: Polarity = "dark"
    contrast: float = 80.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.diameter_px) and self.diameter_px >= 2.0):
            raise ValueError(f"MarkerParams.diameter_px must be finite and >= 2, got {self.diameter_px}")
        if not (np.isfinite(self.pitch_px) and self.pitch_px > self.diameter_px):
            raise ValueError(
                f"MarkerParams.pitch_px must be finite and > diameter_px ({self.diameter_px}), got {self.pitch_px}"
            )
        if self.polarity not in ("dark", "light"):
            raise ValueError(f"MarkerParams.polarity must be 'dark' or 'light', got {self.polarity!r}")
        if not (np.isfinite(self.contrast) and 4.0 <= self.contrast <= 255.0):
            raise ValueError(f"MarkerParams.contrast must be in [4, 255] grey levels, got {self.contrast}")

    @property
    def area_px2(self) -> float:
        """Area of one marker disc in px^2."""
        return float(np.pi * self.diameter_px**2 / 4.0)


@dataclass(frozen=True)
class DetectorParams:
    """Tuning of both detectors, relative to `MarkerParams` so that one set fits all sensors.

    threshold_fraction: a pixel belongs to a marker when it differs from the local mean by
        more than this fraction of `MarkerParams.contrast`.
    background_pitches: side of the box filter giving the local mean, in marker pitches.
    min_area_ratio, max_area_ratio: accepted component area relative to one marker disc.
    max_aspect: largest accepted bounding-box aspect ratio of a component.
    refine_iterations: passes of intensity-weighted centroid refinement (0: binary centroid).
    min_downsampled_px: segment on a 2x downsampled frame when markers stay at least this
        wide (px) there.
    """

    threshold_fraction: float = 0.4
    background_pitches: float = 1.0
    min_area_ratio: float = 0.2
    max_area_ratio: float = 3.5
    max_aspect: float = 3.5
    refine_iterations: int = 1
    min_downsampled_px: float = 3.5

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold_fraction < 1.0:
            raise ValueError(f"threshold_fraction must be in (0, 1), got {self.threshold_fraction}")
        if not self.background_pitches > 0.0:
            raise ValueError(f"background_pitches must be > 0, got {self.background_pitches}")
        if not 0.0 < self.min_area_ratio < self.max_area_ratio:
            raise ValueError(
                f"need 0 < min_area_ratio < max_area_ratio, got {self.min_area_ratio}, {self.max_area_ratio}"
            )
        if not self.max_aspect >= 1.0:
            raise ValueError(f"max_aspect must be >= 1, got {self.max_aspect}")
        if not self.min_downsampled_px >= 2.0:
            raise ValueError(f"min_downsampled_px must be >= 2, got {self.min_downsampled_px}")
        if self.refine_iterations < 0:
            raise ValueError(f"refine_iterations must be >= 0, got {self.refine_iterations}")


@dataclass(frozen=True)
class Detections:
    """Detected markers of one frame.

    centres_px: (N, 2) float64, (x, y) in px. areas_px2: (N,) float64, marker area in px^2.
    """

    centres_px: np.ndarray
    areas_px2: np.ndarray

    def __len__(self) -> int:
        return int(self.centres_px.shape[0])


def to_gray(image: np.ndarray) -> np.ndarray:
    """Grey image of a frame, (H, W) uint8: BT.601 luma for BGR, mono input as is.

    Luma, not a single channel or the channel maximum: colour video is stored as full
    resolution luma plus half resolution chroma, so any channel mix other than luma blurs
    marker edges with chroma from the surroundings (a coloured overlay drawn over the frame,
    coloured shading).
    Raises ValueError for any other shape or dtype.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"image must be a uint8 numpy array, got {getattr(image, 'dtype', type(image))}")
    if image.ndim == 2:
        if min(image.shape) < 8:
            raise ValueError(f"image is too small: {image.shape}")
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        if min(image.shape[:2]) < 8:
            raise ValueError(f"image is too small: {image.shape}")
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    raise ValueError(f"image must be (H, W) mono or (H, W, 3) BGR, got shape {image.shape}")


def _odd(value: float) -> int:
    """Nearest odd integer >= 3."""
    return max(3, int(round(value)) | 1)


@lru_cache(maxsize=16)
def _disc_window(radius: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of a disc of `radius` px in an image `width` px wide.

    Returns flat index offsets (K,) intp, (x, y) offsets (K, 2) intp, the moment matrix
    (K, 3) float32 with columns dx, dy, 1, and the (K,) bool mask of the disc's rim.
    """
    dy, dx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    r2 = dx * dx + dy * dy
    inside = r2 <= radius * radius
    dx, dy = dx[inside].astype(np.intp), dy[inside].astype(np.intp)
    window = (
        dy * width + dx,
        np.column_stack([dx, dy]),
        np.column_stack([dx, dy, np.ones_like(dx)]).astype(np.float32),
        r2[inside] > (radius - 1.5) ** 2,
    )
    for array in window:
        array.flags.writeable = False  # shared by every call through the cache
    return window


def _rim_median(values: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """(N, 1) float32 median over the rim pixels (mask (K,) bool) of window values (N, K)."""
    rim_values = values[:, rim]
    lo, hi = (rim_values.shape[1] - 1) // 2, rim_values.shape[1] // 2
    ordered = np.partition(rim_values, (lo, hi), axis=1)
    return 0.5 * (ordered[:, lo : lo + 1].astype(np.float32) + ordered[:, hi : hi + 1])


def refine_centres(
    gray: np.ndarray,
    centres_px: np.ndarray,
    marker: MarkerParams,
    iterations: int = 1,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """Sub-pixel intensity-weighted centroids around approximate marker centres.

    gray: (H, W) uint8 from `to_gray`. centres_px: (N, 2) float64 approximate (x, y) px,
    within ~1.5 px of the truth. background: (N,) grey levels of the skin around each
    marker (e.g. a local mean); None = the median of a rim around each marker. Each marker
    is weighted by its contrast to its background, less a margin of 0.2 x contrast, inside
    a disc window of radius diameter/2 + 2 px (capped so that no neighbour enters); the
    result is exact for a symmetric marker fully inside the window.
    Returns (N, 2) float64 px; a marker whose window holds no contrast keeps its input.
    """
    centres = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
    if centres.shape[0] == 0 or iterations == 0:
        return centres.copy()
    h, w = gray.shape
    limit = int(np.floor(marker.pitch_px - 0.5 * marker.diameter_px - 1.0))
    radius = max(2, min(int(np.ceil(0.5 * marker.diameter_px + 2.0)), limit))
    offsets, offsets_xy, moments, rim = _disc_window(radius, w)
    margin = np.float32(0.5 * max(2.0, 0.4 * marker.contrast))
    flat = np.ascontiguousarray(gray).ravel()
    given = None if background is None else np.asarray(background, dtype=np.float32).reshape(-1, 1)
    if given is not None and given.shape[0] != centres.shape[0]:
        raise ValueError(f"background has {given.shape[0]} levels for {centres.shape[0]} centres")
    out = centres.copy()
    for _ in range(iterations):
        pixel = np.rint(out).astype(np.intp)
        np.clip(pixel[:, 0], 0, w - 1, out=pixel[:, 0])
        np.clip(pixel[:, 1], 0, h - 1, out=pixel[:, 1])
        interior = bool(np.all((pixel >= radius) & (pixel < np.array([w - radius, h - radius]))))
        if interior:
            values = flat[(pixel[:, 1] * w + pixel[:, 0])[:, None] + offsets[None, :]]
            inside = None
        else:
            xs = pixel[:, 0, None] + offsets_xy[None, :, 0]
            ys = pixel[:, 1, None] + offsets_xy[None, :, 1]
            inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
            values = gray[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
        level = _rim_median(values, rim) if given is None else given
        if marker.polarity == "dark":
            weights = (level - margin) - values
        else:
            weights = values - (level + margin)
        np.maximum(weights, np.float32(0.0), out=weights)
        if inside is not None:
            weights *= inside
        sums = weights @ moments
        ok = sums[:, 2] > 0.0
        out[ok] = pixel[ok] + sums[ok, :2] / sums[ok, 2:3]
    return out


def _segment(
    gray: np.ndarray, marker: MarkerParams, params: DetectorParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker components of `gray` (H, W) uint8, in `gray`'s own pixels.

    A pixel belongs to a marker when it differs from the box-filter mean by more than the
    threshold margin. Returns component centroids (N, 2) float64 px, areas (N,) float64 px^2
    and the skin grey level around each (N,) float32: the box mean at the centroid less the
    marker's own share of it.
    """
    box = _odd(params.background_pitches * marker.pitch_px)
    mean = cv2.boxFilter(gray, -1, (box, box), borderType=cv2.BORDER_REPLICATE)
    margin = float(max(2.0, round(params.threshold_fraction * marker.contrast)))
    if marker.polarity == "dark":
        mask = cv2.compare(gray, cv2.subtract(mean, margin), cv2.CMP_LT)
    else:
        mask = cv2.compare(gray, cv2.add(mean, margin), cv2.CMP_GT)
    h, w = gray.shape
    # 16-bit labels are much faster and cannot overflow when every 8-connected component
    # (at most one per 2 x 2 block) gets its own label.
    ltype = cv2.CV_16U if ((h + 1) // 2) * ((w + 1) // 2) < 65535 else cv2.CV_32S
    _, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=ltype)
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    bw = stats[1:, cv2.CC_STAT_WIDTH]
    bh = stats[1:, cv2.CC_STAT_HEIGHT]
    expected = marker.area_px2
    keep = (
        (area >= max(2.0, params.min_area_ratio * expected))
        & (area <= params.max_area_ratio * expected)
        & (np.maximum(bw, bh) <= params.max_aspect * np.minimum(bw, bh))
    )
    centres = centroids[1:][keep]
    pixel = np.rint(centres).astype(np.intp)
    # The box mean over a marker holds the marker too: remove its share of the contrast.
    marker_share = marker.area_px2 / float(box * box)
    skin_offset = marker_share * (marker.contrast if marker.polarity == "dark" else -marker.contrast)
    skin = mean[pixel[:, 1], pixel[:, 0]].astype(np.float32) + np.float32(skin_offset)
    return centres, area[keep], skin


def detect_fast(
    image: np.ndarray, marker: MarkerParams, params: DetectorParams = DetectorParams()
) -> Detections:
    """Fast detector: box-filter background normalisation, threshold, connected components.

    image: (H, W) uint8 or (H, W, 3) uint8 BGR. Markers of >= 2 * `min_downsampled_px`
    diameter are segmented on a 2x area-downsampled frame (4x fewer pixels). Components are
    kept when their area lies in [min_area_ratio, max_area_ratio] x the marker disc area and
    their bounding box is not too elongated; centres are then refined to sub-pixel on the
    full-resolution frame by `refine_centres`, against the skin level from the box filter.
    Returns `Detections` (centres (N, 2) float64 px, areas (N,) float64 px^2).
    """
    gray = to_gray(image)
    if marker.diameter_px >= 2.0 * params.min_downsampled_px:
        small = cv2.resize(gray, (gray.shape[1] // 2, gray.shape[0] // 2), interpolation=cv2.INTER_AREA)
        half = replace(marker, diameter_px=marker.diameter_px / 2.0, pitch_px=marker.pitch_px / 2.0)
        coarse, area, background = _segment(small, half, params)
        coarse, area = 2.0 * coarse + 0.5, 4.0 * area
    else:
        coarse, area, background = _segment(gray, marker, params)
    centres = refine_centres(gray, coarse, marker, params.refine_iterations, background)
    return Detections(centres_px=centres, areas_px2=area)


def detect_blobs(
    image: np.ndarray, marker: MarkerParams, params: DetectorParams = DetectorParams()
) -> Detections:
    """The paper's detector: cv2.SimpleBlobDetector with parameters derived from the markers.

    image: (H, W) uint8 or (H, W, 3) uint8 BGR. Area limits follow `params`, the minimum
    distance between blobs is half a pitch, circularity >= 0.5. Centres are the detector's
    own (no refinement), areas are pi/4 * size^2 from the key-point diameters.
    Returns `Detections` (centres (N, 2) float64 px, areas (N,) float64 px^2).
    """
    gray = to_gray(image)
    blob = cv2.SimpleBlobDetector_Params()
    blob.filterByColor = True
    blob.blobColor = 0 if marker.polarity == "dark" else 255
    blob.minThreshold = 10.0
    blob.maxThreshold = 245.0
    blob.thresholdStep = 10.0
    blob.minRepeatability = 2
    blob.filterByArea = True
    blob.minArea = float(max(2.0, params.min_area_ratio * marker.area_px2))
    blob.maxArea = float(params.max_area_ratio * marker.area_px2)
    blob.filterByCircularity = True
    blob.minCircularity = 0.5
    blob.filterByConvexity = False
    blob.filterByInertia = True
    blob.minInertiaRatio = 1.0 / params.max_aspect**2
    blob.minDistBetweenBlobs = float(0.5 * marker.pitch_px)
    keypoints = cv2.SimpleBlobDetector_create(blob).detect(gray)
    centres = np.array([kp.pt for kp in keypoints], dtype=np.float64).reshape(-1, 2)
    sizes = np.array([kp.size for kp in keypoints], dtype=np.float64)
    return Detections(centres_px=centres, areas_px2=np.pi / 4.0 * sizes**2)


MIN_BLOB_CONTRAST = 4  # grey levels a blob must stand out from its surroundings by (an image of noise alone: none)


def _candidate_blobs(gray: np.ndarray, polarity: Polarity) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compact blobs of one polarity found with no prior: centres (N, 2), areas (N,), contrasts (N,)."""
    h, w = gray.shape
    background = cv2.medianBlur(gray, min(_odd(min(h, w) / 8.0), 255))
    diff = cv2.subtract(background, gray) if polarity == "dark" else cv2.subtract(gray, background)
    level, mask = cv2.threshold(diff, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    if level < MIN_BLOB_CONTRAST:  # Otsu gives 0 for two levels (a sharp, noise-free pattern): at least this
        level, mask = cv2.threshold(diff, MIN_BLOB_CONTRAST - 1, 255, cv2.THRESH_BINARY)
    if not mask.any():
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    bw = stats[1:, cv2.CC_STAT_WIDTH].astype(np.float64)
    bh = stats[1:, cv2.CC_STAT_HEIGHT].astype(np.float64)
    x0 = stats[1:, cv2.CC_STAT_LEFT]
    y0 = stats[1:, cv2.CC_STAT_TOP]
    interior = (x0 > 0) & (y0 > 0) & (x0 + bw < w) & (y0 + bh < h)
    compact = (area >= 6) & (area >= 0.5 * bw * bh) & (np.maximum(bw, bh) <= 2.0 * np.minimum(bw, bh))
    keep = interior & compact
    peak = np.zeros(n, dtype=np.float64)
    np.maximum.at(peak, labels.ravel(), diff.ravel().astype(np.float64))
    return centroids[1:][keep], area[keep], peak[1:][keep]


def estimate_marker_params(image: np.ndarray, min_markers: int = 4) -> MarkerParams:
    """Estimate marker diameter, pitch, polarity and contrast from one reference frame.

    image: (H, W) uint8 or (H, W, 3) uint8 BGR with the skin at rest. Both polarities are
    tried; the one whose blobs of a consistent size (area within a factor 2 of the median)
    have the larger count x median contrast wins. Diameter from the median blob area, pitch from the median distance to
    the nearest blob, contrast from the median blob peak contrast to a median-filtered
    background. Raises ValueError when fewer than `min_markers` consistent blobs exist.
    """
    if min_markers < 1:  # ("shows 0 consistent marker blobs, need >= 0" before)
        raise ValueError(f"min_markers {min_markers} must be >= 1")
    best: tuple[float, int, Polarity, np.ndarray, np.ndarray, np.ndarray] | None = None
    gray = to_gray(image)
    for polarity in ("dark", "light"):
        centres, area, peak = _candidate_blobs(gray, polarity)
        if area.size == 0:
            continue
        median_area = np.median(area)
        consistent = (area > 0.5 * median_area) & (area < 2.0 * median_area)
        count = int(consistent.sum())
        score = count * float(np.median(peak[consistent]))
        if best is None or score > best[0]:
            best = (score, count, polarity, centres[consistent], area[consistent], peak[consistent])
    if best is None or best[1] < min_markers:
        found = 0 if best is None else best[1]
        raise ValueError(f"reference frame shows {found} consistent marker blobs, need >= {min_markers}")
    _, _, polarity, centres, area, peak = best
    diameter = float(2.0 * np.sqrt(np.median(area) / np.pi))
    distances, _ = cKDTree(centres).query(centres, k=2)
    pitch = float(max(np.median(distances[:, 1]), 1.5 * diameter))
    contrast = float(np.clip(np.median(peak), 4.0, 255.0))
    return MarkerParams(diameter_px=diameter, pitch_px=pitch, polarity=polarity, contrast=contrast)


def drop_border_markers(detections: Detections, shape: tuple[int, ...], margin_px: float) -> Detections:
    """Detections whose centre lies at least `margin_px` from every image edge.

    shape: the frame's shape, (H, W) or (H, W, 3). Markers cut by the frame edge have
    biased centroids and vanish under small motions, so they make poor references.
    """
    h, w = shape[0], shape[1]
    c = detections.centres_px
    keep = (
        (c[:, 0] >= margin_px) & (c[:, 0] <= w - 1 - margin_px) & (c[:, 1] >= margin_px) & (c[:, 1] <= h - 1 - margin_px)
    )
    return Detections(centres_px=c[keep], areas_px2=detections.areas_px2[keep])


def _lattice_support(centres_px: np.ndarray, neighbours: int = 8, tolerance: float = 0.2) -> np.ndarray:
    """(N,) int64: for each of the centres (N, 2) px, how many of its `neighbours` nearest other
    centres have a centre within `tolerance` x their distance of their point reflection through it.

    A lattice marker's neighbours come in opposite pairs, also under a smooth distortion such as
    a fisheye's; a clutter blob beside a marker has next to none.
    """
    n = centres_px.shape[0]
    k = min(neighbours, n - 1)
    if k < 1:
        return np.zeros(n, dtype=np.int64)
    tree = cKDTree(centres_px)
    distance, index = tree.query(centres_px, k=k + 1)
    mirrored = 2.0 * centres_px[:, None, :] - centres_px[index[:, 1:]]
    gap, _ = tree.query(mirrored.reshape(-1, 2))
    return np.count_nonzero(gap.reshape(n, k) <= tolerance * distance[:, 1:], axis=1)


def drop_crowded_markers(detections: Detections, radius_px: float) -> Detections:
    """Detections with no two centres closer than `radius_px`: of blobs closer than that, the one
    that fits the marker lattice best (`_lattice_support`; on a tie the larger) is kept.

    Lattice markers lie a pitch apart, so of two blobs less than half a pitch apart at most one
    is a marker. Behind a transparent skin (FingerVision) the reference frame shows background
    clutter too, and a clutter blob taken as a reference marker next to a real one can take that
    marker's dot (it lies inside the tracker's gate) once the clutter is gone.
    """
    centres = detections.centres_px
    pairs = cKDTree(centres).query_pairs(radius_px, output_type="ndarray")
    if pairs.size == 0:
        return detections
    rank = np.empty(len(detections), dtype=np.int64)
    rank[np.lexsort((-detections.areas_px2, -_lattice_support(centres)))] = np.arange(len(detections))
    keep = np.ones(len(detections), dtype=bool)
    crowded = np.unique(pairs)
    for blob in crowded[np.argsort(rank[crowded])]:
        if keep[blob]:
            partners = pairs[(pairs == blob).any(axis=1)].ravel()
            keep[partners[rank[partners] > rank[blob]]] = False
    return Detections(centres_px=centres[keep], areas_px2=detections.areas_px2[keep])
