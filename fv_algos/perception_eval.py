"""Scoring perception output against ground truth (plain arrays, no images, no timing).

Tracked markers are identified with true markers once, by reference position
(`match_reference`); each frame then gives a `PerceptionScore` (`score_frame`) and scores
add up over frames and scenes (`+`). Coordinates are image (x, y) px throughout.

Per frame, with `match` from `match_reference`:
- tracking error: current minus true position of every valid, matched marker;
- tracked: valid, matched markers whose true marker is visible, out of all visible true markers
  (true markers the tracker never had count as not tracked);
- identity swap: a valid, matched marker lying nearer to another marker's true position than
  to its own;
- inconsistent: a valid marker flagged by `fv_algos.tracking.neighbour_consistency` (the
  truth-free swap test the tracker itself can apply);
- field error: the dense field minus the true field at the same grid points.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from fv_algos.tracking import neighbour_consistency


def _points(array: np.ndarray, name: str, rows: int | None = None) -> np.ndarray:
    """(N, 2) float64 view of `array`; ValueError naming `name` on a wrong shape or NaN/inf."""
    out = np.asarray(array, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 2 or (rows is not None and out.shape[0] != rows):
        want = f"({rows}, 2)" if rows is not None else "(N, 2)"
        raise ValueError(f"{name} must have shape {want}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} holds non-finite coordinates")
    return out


def _mask(array: np.ndarray, name: str, rows: int) -> np.ndarray:
    """(rows,) bool copy of `array`; ValueError naming `name` on a wrong shape."""
    out = np.asarray(array)
    if out.shape != (rows,):
        raise ValueError(f"{name} must have shape ({rows},), got {out.shape}")
    return out.astype(bool)


def marker_pitch_px(points_px: np.ndarray, statistic: Literal["median", "min"] = "median") -> float:
    """Median (or smallest) distance, px, from each of the points (N >= 2, 2) to its nearest other point."""
    pts = _points(points_px, "points_px")
    if pts.shape[0] < 2:
        raise ValueError(f"need >= 2 points for a pitch, got {pts.shape[0]}")
    if statistic not in ("median", "min"):
        raise ValueError(f"statistic must be 'median' or 'min', got {statistic!r}")
    distances, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(distances[:, 1]) if statistic == "median" else distances[:, 1].min())


def match_reference(reference_px: np.ndarray, truth_reference_px: np.ndarray, max_distance_px: float) -> np.ndarray:
    """Identify tracked markers with true markers by their reference (rest) positions.

    reference_px: (N, 2) tracked markers' reference positions, px. truth_reference_px: (M, 2)
    true rest positions, px. A pair is made when the two are each other's nearest neighbour
    and lie less than `max_distance_px` apart (one-to-one by construction).
    Returns (N,) int64: index into the truth rows, -1 where a tracked marker has no partner.
    """
    ref = _points(reference_px, "reference_px")
    truth = _points(truth_reference_px, "truth_reference_px")
    if not (np.isfinite(max_distance_px) and max_distance_px > 0.0):
        raise ValueError(f"max_distance_px must be finite and > 0, got {max_distance_px}")
    match = np.full(ref.shape[0], -1, dtype=np.int64)
    if ref.shape[0] == 0 or truth.shape[0] == 0:
        return match
    _, to_truth = cKDTree(truth).query(ref, k=1, distance_upper_bound=max_distance_px)
    _, to_ref = cKDTree(ref).query(truth, k=1, distance_upper_bound=max_distance_px)
    rows = np.flatnonzero(to_truth < truth.shape[0])
    mutual = rows[to_ref[to_truth[rows]] == rows]
    match[mutual] = to_truth[mutual]
    return match


def identity_swaps(current_px: np.ndarray, valid: np.ndarray, match: np.ndarray, truth_px: np.ndarray) -> np.ndarray:
    """(N,) bool: valid, matched markers nearer to another true marker than to their own.

    current_px: (N, 2) tracked positions, px. valid: (N,) bool. match: (N,) int64 from
    `match_reference`. truth_px: (M, 2) true positions of all markers this frame, px.
    """
    cur = _points(current_px, "current_px")
    n = cur.shape[0]
    truth = _points(truth_px, "truth_px")
    index = _match(match, n, truth.shape[0])
    ok = _mask(valid, "valid", n) & (index >= 0)
    swapped = np.zeros(n, dtype=bool)
    if not ok.any():
        return swapped
    rows = np.flatnonzero(ok)
    own = np.linalg.norm(cur[rows] - truth[index[rows]], axis=1)
    nearest_distance, nearest = cKDTree(truth).query(cur[rows], k=1)
    swapped[rows] = (nearest != index[rows]) & (nearest_distance < own)
    return swapped


def _match(match: np.ndarray, rows: int, truth_rows: int) -> np.ndarray:
    """(rows,) int64 `match`; ValueError on a wrong shape or an index outside [-1, truth_rows)."""
    out = np.asarray(match)
    if out.shape != (rows,) or not np.issubdtype(out.dtype, np.integer):
        raise ValueError(f"match must be an integer array of shape ({rows},), got {out.dtype} {out.shape}")
    if out.size and (out.min() < -1 or out.max() >= truth_rows):
        raise ValueError(f"match indices must lie in [-1, {truth_rows}), got [{out.min()}, {out.max()}]")
    return out.astype(np.int64)


@dataclass(frozen=True)
class PerceptionScore:
    """Error totals over one or more frames; add scores with `+`, read the rates as properties.

    squared_error_px2: sum of squared tracking errors, px^2. compared: markers in that sum.
    tracked: valid, matched markers whose true marker is visible. visible: visible true
    markers. swaps: identity swaps. inconsistent: neighbour-consistency flags.
    field_squared_error_px2: sum of squared field errors over grid points, px^2.
    field_points: grid points in that sum. frames: frames scored.
    """

    squared_error_px2: float = 0.0
    compared: int = 0
    tracked: int = 0
    visible: int = 0
    swaps: int = 0
    inconsistent: int = 0
    field_squared_error_px2: float = 0.0
    field_points: int = 0
    frames: int = 0

    def __add__(self, other: "PerceptionScore") -> "PerceptionScore":
        if not isinstance(other, PerceptionScore):
            return NotImplemented
        return PerceptionScore(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    @property
    def tracking_rms_px(self) -> float:
        """Root mean square tracking error, px (nan when nothing was compared)."""
        return float(np.sqrt(self.squared_error_px2 / self.compared)) if self.compared else float("nan")

    @property
    def tracked_share(self) -> float:
        """Share of visible true markers that were tracked (nan when none was visible)."""
        return self.tracked / self.visible if self.visible else float("nan")

    @property
    def field_rmse_px(self) -> float:
        """Root mean square field error over grid points and frames, px (nan when none)."""
        return float(np.sqrt(self.field_squared_error_px2 / self.field_points)) if self.field_points else float("nan")


def score_frame(
    reference_px: np.ndarray,
    current_px: np.ndarray,
    valid: np.ndarray,
    match: np.ndarray,
    truth_px: np.ndarray,
    truth_visible: np.ndarray,
    field_px: np.ndarray,
    true_field_px: np.ndarray,
) -> PerceptionScore:
    """Score one frame.

    reference_px, current_px: (N, 2) tracked markers' reference and current positions, px
    (current_px finite). valid: (N,) bool. match: (N,) int64 from `match_reference`.
    truth_px: (M, 2) true positions, px. truth_visible: (M,) bool. field_px: (G, 2)
    estimated displacement (dx, dy) at G grid points, px; true_field_px: (G, 2) the true
    displacement at the same points, px.
    """
    cur = _points(current_px, "current_px")
    n = cur.shape[0]
    ref = _points(reference_px, "reference_px", n)
    ok = _mask(valid, "valid", n)
    truth = _points(truth_px, "truth_px")
    seen = _mask(truth_visible, "truth_visible", truth.shape[0])
    index = _match(match, n, truth.shape[0])
    estimate = _points(field_px, "field_px")
    exact = _points(true_field_px, "true_field_px", estimate.shape[0])
    compared = ok & (index >= 0)
    error = cur[compared] - truth[index[compared]]
    tracked = compared.copy()
    tracked[compared] = seen[index[compared]]
    return PerceptionScore(
        squared_error_px2=float(np.sum(error * error)),
        compared=int(compared.sum()),
        tracked=int(tracked.sum()),
        visible=int(seen.sum()),
        swaps=int(identity_swaps(cur, ok, index, truth).sum()),
        inconsistent=int(neighbour_consistency(ref, cur, ok).sum()),
        field_squared_error_px2=float(np.sum((estimate - exact) ** 2)),
        field_points=int(estimate.shape[0]),
        frames=1,
    )


def grid_points_px(x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    """(H * W, 2) float64 grid points (x, y) px, row-major (the order of a field's (H, W) cells)."""
    x = np.asarray(x_px, dtype=np.float64)
    y = np.asarray(y_px, dtype=np.float64)
    if x.ndim != 1 or y.ndim != 1 or x.size == 0 or y.size == 0:
        raise ValueError(f"x_px and y_px must be non-empty 1-D axes, got {x.shape}, {y.shape}")
    gx, gy = np.meshgrid(x, y)
    return np.column_stack([gx.ravel(), gy.ravel()])


def timing_summary_ms(samples_ms: np.ndarray) -> dict[str, float]:
    """{'median', 'p99'} of per-frame times (K,) ms (K >= 1)."""
    samples = np.asarray(samples_ms, dtype=np.float64).ravel()
    if samples.size == 0 or not np.all(np.isfinite(samples)):
        raise ValueError(f"need >= 1 finite time sample, got {samples.size} samples")
    return {"median": float(np.median(samples)), "p99": float(np.percentile(samples, 99))}
