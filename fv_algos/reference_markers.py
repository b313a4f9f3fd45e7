"""The reference markers' positions as the interpolator and the tracker take them: checked once, here."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# Reference markers closer than this are one marker listed twice (no detector resolves 1e-3 px):
# the RBF system turns their differences into huge coefficients, the tracker's pitch into ~0.
_COINCIDENT_PX = 1e-3
# Reference coordinates beyond this are no camera's (frames are < 1e4 px wide): squared
# distances of such points overflow or swamp the kernel.
_MAX_COORD_PX = 1e6


def point_rows(points_px: np.ndarray, name: str) -> np.ndarray:
    """(N, 2) float64 view or copy of marker positions `points_px` (px); an empty array of any shape is (0, 2).
    ValueError naming `name` for another shape: read as (-1, 2), a (4, 3) array became 6 markers of
    garbage, tracked without a word."""
    points = np.asarray(points_px, dtype=np.float64)
    if points.size == 0:
        return points.reshape(0, 2)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {points.shape}")
    return points


def checked_reference(points_px: np.ndarray, name: str) -> np.ndarray:
    """(N, 2) float64 copy of reference marker positions `points_px` (px), N >= 1.

    The check shared by `fv_algos.field.FieldInterpolator` and `fv_algos.tracking.Tracker`: ValueError
    naming `name` for another shape, no markers, non-finite coordinates, coordinates beyond +/- 1e6 px,
    or markers that coincide (closer than 1e-3 px; the message names the first pairs).
    """
    ref = np.array(points_px, dtype=np.float64)
    if ref.ndim != 2 or ref.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {ref.shape}")
    if ref.shape[0] == 0:
        raise ValueError(f"{name} holds no markers")
    if not np.all(np.isfinite(ref)):
        raise ValueError(f"{name} holds non-finite coordinates")
    largest = float(np.abs(ref).max())
    if largest > _MAX_COORD_PX:
        raise ValueError(f"{name} holds coordinates beyond +/- {_MAX_COORD_PX:g} px (up to {largest:g} px)")
    pairs = cKDTree(ref).query_pairs(_COINCIDENT_PX, output_type="ndarray")
    if pairs.size:
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
        listed = ", ".join(f"{i} and {j} (at {ref[i, 0]:g}, {ref[i, 1]:g} px)" for i, j in pairs[:5])
        more = f" and {len(pairs) - 5} more pairs" if len(pairs) > 5 else ""
        raise ValueError(f"{name}: markers {listed}{more} coincide (closer than {_COINCIDENT_PX:g} px): "
                         "list each marker once")
    return ref
