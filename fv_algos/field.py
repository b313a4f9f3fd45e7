"""Dense displacement field: marker displacements interpolated onto a fixed grid.

The grid lives in reference (undeformed) marker coordinates: GRID_W x GRID_H points spaced
evenly from the smallest to the largest reference marker x (and y), corners included. The
field holds, at each grid point, the displacement (dx, dy) of the skin that started there
and its magnitude, all in px.

Because the reference markers never move, RBF interpolation from the markers to the grid
is one fixed linear operator (G x N). `FieldInterpolator` precomputes it once per pattern
of valid markers (LRU cache) so that a frame costs one matrix product. The paper-faithful
reference (scipy RBFInterpolator refit every frame) and cubic griddata are the alternatives.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.interpolate import RBFInterpolator, griddata
from scipy.spatial import cKDTree

Kernel = Literal["thin_plate_spline", "multiquadric", "inverse_multiquadric", "gaussian", "linear", "cubic"]

# Every kernel gets a linear polynomial term (1, x, y), as scipy.interpolate.RBFInterpolator
# does by default: it is the most any of these kernels needs, and it reproduces uniform
# translation and linear strain exactly.
_KERNELS = ("thin_plate_spline", "multiquadric", "inverse_multiquadric", "gaussian", "linear", "cubic")
_SCALED = ("multiquadric", "inverse_multiquadric", "gaussian")
_POLY_TERMS = 3


@dataclass(frozen=True)
class FieldParams:
    """How the displacement field is made.

    method: 'rbf_operator' (precomputed linear operator), 'rbf_refit' (scipy RBFInterpolator
        fitted every frame: the paper-faithful reference) or 'griddata' (scipy cubic
        griddata; cells outside the valid markers' hull take the nearest marker's value).
    grid_shape: (rows H, columns W) of the grid.
    kernel: radial basis function (scipy RBFInterpolator names).
    width_px: shape width of multiquadric / inverse_multiquadric / gaussian kernels,
        phi(r / width_px); None = median nearest-neighbour spacing of the reference markers.
    smoothing: added to the kernel matrix diagonal (0 = exact interpolation).
    rcond: singular values below rcond x the largest are dropped when solving (keeps
        ill-conditioned systems finite).
    cache_size: operators kept, one per validity pattern.
    rebuild_after_frames: 'rbf_operator' solves an exact operator for a new validity
        pattern only once the pattern has held this many frames in a row; until then the
        missing markers' displacements are estimated from their valid reference
        neighbours (inverse-distance weighted) and the all-markers operator is applied, so
        flickering markers never cost a solve in the frame loop.
    fill_neighbours: reference neighbours used for that estimate.
    min_markers: fewer valid markers than this (or than the polynomial needs) gives an
        all-zero field flagged invalid.
    """

    method: Literal["rbf_operator", "rbf_refit", "griddata"] = "rbf_operator"
    grid_shape: tuple[int, int] = (30, 30)
    kernel: Kernel = "thin_plate_spline"
    width_px: float | None = None
    smoothing: float = 0.0
    rcond: float = 1e-10
    cache_size: int = 64
    min_markers: int = 3
    rebuild_after_frames: int = 5
    fill_neighbours: int = 6

    def __post_init__(self) -> None:
        if self.method not in ("rbf_operator", "rbf_refit", "griddata"):
            raise ValueError(f"FieldParams.method must be rbf_operator, rbf_refit or griddata, got {self.method!r}")
        if self.kernel not in _KERNELS:
            raise ValueError(f"FieldParams.kernel must be one of {_KERNELS}, got {self.kernel!r}")
        if len(self.grid_shape) != 2 or min(self.grid_shape) < 2:
            raise ValueError(f"FieldParams.grid_shape must be (H, W) with both >= 2, got {self.grid_shape}")
        if self.width_px is not None and not (np.isfinite(self.width_px) and self.width_px > 0.0):
            raise ValueError(f"FieldParams.width_px must be None or finite > 0, got {self.width_px}")
        if not (np.isfinite(self.smoothing) and self.smoothing >= 0.0):
            raise ValueError(f"FieldParams.smoothing must be finite >= 0, got {self.smoothing}")
        if not 0.0 < self.rcond < 1.0:
            raise ValueError(f"FieldParams.rcond must be in (0, 1), got {self.rcond}")
        if self.cache_size < 1 or self.min_markers < 1:
            raise ValueError(f"cache_size and min_markers must be >= 1, got {self.cache_size}, {self.min_markers}")
        if self.rebuild_after_frames < 1 or self.fill_neighbours < 1:
            raise ValueError(f"rebuild_after_frames and fill_neighbours must be >= 1, got "
                             f"{self.rebuild_after_frames}, {self.fill_neighbours}")


@dataclass(frozen=True)
class DisplacementField:
    """One frame's dense field.

    field: (H, W, 3) float32, channels dx_px, dy_px, magnitude_px; all finite (zeros when
    invalid). x_px: (W,) float64 and y_px: (H,) float64 grid coordinates in the reference
    frame. valid: False when too few markers were valid. markers_used: markers that fed it.
    filled_cells: grid cells filled from the nearest marker (griddata outside the hull).
    estimated_markers: missing markers whose displacement was estimated from their
    neighbours ('rbf_operator' while a new validity pattern is not yet solved).
    """

    field: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    valid: bool
    markers_used: int
    filled_cells: int = 0
    estimated_markers: int = 0


def _kernel(r: np.ndarray, kernel: str, width: float) -> np.ndarray:
    """phi(r / width) for distances r (any shape, same unit as width), float64."""
    s = r / width
    if kernel == "thin_plate_spline":
        return s * s * np.log(np.where(s > 0.0, s, 1.0))
    if kernel == "linear":
        return -s
    if kernel == "cubic":
        return s**3
    if kernel == "multiquadric":
        return -np.sqrt(1.0 + s * s)
    if kernel == "inverse_multiquadric":
        return 1.0 / np.sqrt(1.0 + s * s)
    return np.exp(-s * s)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) float64 Euclidean distances between point sets (n, 2) and (m, 2)."""
    dx = a[:, None, 0] - b[None, :, 0]
    dy = a[:, None, 1] - b[None, :, 1]
    return np.sqrt(dx * dx + dy * dy)


def _linear_basis(points: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    """(n, 3) polynomial basis 1, x, y in coordinates centred on `centre` and divided by `scale`."""
    normalised = (points - centre) / scale
    return np.column_stack([np.ones(points.shape[0]), normalised])


def rbf_operator(
    markers_px: np.ndarray,
    grid_points_px: np.ndarray,
    kernel: str = "thin_plate_spline",
    width_px: float = 25.0,
    smoothing: float = 0.0,
    rcond: float = 1e-10,
) -> tuple[np.ndarray, float]:
    """Linear operator mapping marker values to grid values by RBF interpolation.

    markers_px: (N, 2) float64 finite reference positions. grid_points_px: (G, 2) float64.
    Kernel phi(r / width_px) for multiquadric / inverse_multiquadric / gaussian, phi(r / extent)
    for the scale-free kernels (extent = the markers' largest bounding-box side; the
    interpolant does not depend on it), plus a linear polynomial. Solves the symmetric system
    [[K + smoothing I, P], [P^T, 0]] by an eigen pseudo-inverse (eigenvalues below
    rcond x the largest magnitude dropped) so collinear or coincident markers stay finite.
    Returns (operator (G, N) float64, condition number of the system); values_grid =
    operator @ values_markers for any (N, C) values.
    """
    n = markers_px.shape[0]
    centre = markers_px.mean(axis=0)
    extent = float(max(np.ptp(markers_px, axis=0).max(), 1e-9))
    width = width_px if kernel in _SCALED else extent
    system = np.zeros((n + _POLY_TERMS, n + _POLY_TERMS))
    system[:n, :n] = _kernel(_distances(markers_px, markers_px), kernel, width) + smoothing * np.eye(n)
    basis = _linear_basis(markers_px, centre, extent)
    system[:n, n:] = basis
    system[n:, :n] = basis.T
    eigenvalues, vectors = np.linalg.eigh(system)
    magnitude = np.abs(eigenvalues)
    largest = magnitude.max()
    keep = magnitude > rcond * largest if largest > 0.0 else np.zeros_like(magnitude, dtype=bool)
    inverse_cols = (vectors[:, keep] / eigenvalues[keep]) @ vectors[:n, keep].T
    evaluation = np.hstack(
        [
            _kernel(_distances(grid_points_px, markers_px), kernel, width),
            _linear_basis(grid_points_px, centre, extent),
        ]
    )
    smallest = magnitude.min()
    condition = float(largest / smallest) if smallest > 0.0 else float("inf")
    return evaluation @ inverse_cols, condition


def grid_axes(reference_px: np.ndarray, grid_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Grid coordinates x (W,) and y (H,) float64 px spanning the reference markers' bounding box.

    A degenerate extent (all markers on one line or point) is widened to +/- 1 px.
    """
    lo = reference_px.min(axis=0)
    hi = reference_px.max(axis=0)
    hi = np.where(hi - lo < 2.0, lo + 1.0, hi)
    lo = np.where(hi - lo < 2.0, lo - 1.0, lo)
    h, w = grid_shape
    return np.linspace(lo[0], hi[0], w), np.linspace(lo[1], hi[1], h)


class FieldInterpolator:
    """Interpolates tracked marker displacements onto the fixed grid.

    Build once from the reference markers (N, 2) px; `interpolate(current_px, valid)` per frame.
    """

    def __init__(self, reference_px: np.ndarray, params: FieldParams = FieldParams()) -> None:
        ref = np.asarray(reference_px, dtype=np.float64)
        if ref.ndim != 2 or ref.shape[1] != 2 or ref.shape[0] == 0:
            raise ValueError(f"reference_px must have shape (N >= 1, 2), got {ref.shape}")
        if not np.all(np.isfinite(ref)):
            raise ValueError("reference_px holds non-finite coordinates")
        self.params = params
        self.reference_px = ref.copy()
        self.x_px, self.y_px = grid_axes(ref, params.grid_shape)
        gx, gy = np.meshgrid(self.x_px, self.y_px)
        self._grid_points = np.column_stack([gx.ravel(), gy.ravel()])
        if params.width_px is not None:
            self.width_px = float(params.width_px)
        elif ref.shape[0] > 1:
            d = _distances(ref, ref) + np.diag(np.full(ref.shape[0], np.inf))
            self.width_px = float(max(np.median(d.min(axis=1)), 1e-6))
        else:
            self.width_px = 1.0
        self._cache: OrderedDict[bytes, tuple[np.ndarray, float]] = OrderedDict()
        self.last_condition = float("nan")
        k = min(params.fill_neighbours, ref.shape[0] - 1)
        if k >= 1:
            dist, idx = cKDTree(ref).query(ref, k=k + 1)
            self._fill_idx, self._fill_w = idx[:, 1:], 1.0 / np.maximum(dist[:, 1:], 1e-9)
        else:
            self._fill_idx, self._fill_w = np.zeros((ref.shape[0], 0), int), np.zeros((ref.shape[0], 0))
        self._pattern = b""
        self._streak = 0

    def operator(self, valid: np.ndarray) -> np.ndarray:
        """(G, n_valid) float64 operator for the markers where `valid` (N,) bool is True (cached)."""
        key = np.packbits(valid).tobytes()
        hit = self._cache.get(key)
        if hit is None:
            hit = rbf_operator(
                self.reference_px[valid],
                self._grid_points,
                self.params.kernel,
                self.width_px,
                self.params.smoothing,
                self.params.rcond,
            )
            self._cache[key] = hit
            if len(self._cache) > self.params.cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        self.last_condition = hit[1]
        return hit[0]

    def interpolate(self, current_px: np.ndarray, valid: np.ndarray) -> DisplacementField:
        """Field from current marker positions (N, 2) px and validity (N,) bool.

        Markers with non-finite positions count as not valid. Returns a `DisplacementField`
        (flagged invalid and all-zero when fewer than `min_markers` are usable).
        """
        cur = np.asarray(current_px, dtype=np.float64)
        mask = np.asarray(valid, dtype=bool)
        n = self.reference_px.shape[0]
        if cur.shape != (n, 2) or mask.shape != (n,):
            raise ValueError(f"current_px must be ({n}, 2) and valid ({n},), got {cur.shape}, {mask.shape}")
        mask = mask & np.all(np.isfinite(cur), axis=1)
        used = int(mask.sum())
        h, w = self.params.grid_shape
        needed = max(self.params.min_markers, _POLY_TERMS)
        if used < needed:
            return DisplacementField(np.zeros((h, w, 3), np.float32), self.x_px, self.y_px, False, used)
        disp = cur[mask] - self.reference_px[mask]
        filled = 0
        method = self.params.method
        estimated = 0
        if method == "rbf_operator":
            grid, estimated = self._apply_operator(cur, mask, disp)
        elif method == "rbf_refit":
            epsilon = 1.0 / self.width_px if self.params.kernel in _SCALED else 1.0
            try:
                grid = RBFInterpolator(
                    self.reference_px[mask],
                    disp,
                    kernel=self.params.kernel,
                    epsilon=epsilon,
                    smoothing=self.params.smoothing,
                    degree=1,
                )(self._grid_points)
            except (np.linalg.LinAlgError, ValueError):
                grid = np.full((self._grid_points.shape[0], 2), np.nan)
        else:
            grid, filled = self._griddata(self.reference_px[mask], disp)
        if not np.all(np.isfinite(grid)):
            return DisplacementField(np.zeros((h, w, 3), np.float32), self.x_px, self.y_px, False, used)
        out = np.empty((h * w, 3), dtype=np.float32)
        out[:, :2] = grid
        out[:, 2] = np.hypot(grid[:, 0], grid[:, 1])
        return DisplacementField(out.reshape(h, w, 3), self.x_px, self.y_px, True, used, filled, estimated)

    def _apply_operator(self, cur: np.ndarray, mask: np.ndarray, disp: np.ndarray) -> tuple[np.ndarray, int]:
        """(G, 2) grid displacements and the number of estimated markers (see
        FieldParams.rebuild_after_frames)."""
        key = np.packbits(mask).tobytes()
        self._streak = self._streak + 1 if key == self._pattern else 1
        self._pattern = key
        if mask.all() or key in self._cache or self._streak >= self.params.rebuild_after_frames:
            return self.operator(mask) @ disp, 0
        full = np.zeros_like(cur)
        full[mask] = disp
        missing = np.flatnonzero(~mask)
        full[missing] = self._estimate_missing(full, mask, missing, disp)
        return self.operator(np.ones_like(mask)) @ full, int(missing.size)

    def _estimate_missing(self, full: np.ndarray, mask: np.ndarray, missing: np.ndarray,
                          disp: np.ndarray) -> np.ndarray:
        """(M, 2) displacement estimates of the `missing` markers: an inverse-distance
        weighted affine fit over their valid reference neighbours (exact for affine
        motion); weighted mean where the fit is degenerate; the median valid displacement
        where no neighbour is valid."""
        nbr = self._fill_idx[missing]
        w = self._fill_w[missing] * mask[nbr]
        offsets = self.reference_px[nbr] - self.reference_px[missing][:, None, :]
        basis = np.concatenate([np.ones(offsets.shape[:2] + (1,)), offsets], axis=2)  # (M, k, 3)
        normal = np.einsum("mk,mki,mkj->mij", w, basis, basis)
        rhs = np.einsum("mk,mki,mkc->mic", w, basis, full[nbr])
        total = w.sum(axis=1)
        estimate = np.einsum("mk,mkc->mc", w, full[nbr]) / np.maximum(total, 1e-300)[:, None]
        fit = (mask[nbr].sum(axis=1) >= 3) & (np.abs(np.linalg.det(normal)) > 1e-12 * np.maximum(total, 1e-300) ** 3)
        if fit.any():
            estimate[fit] = np.linalg.solve(normal[fit], rhs[fit])[:, 0, :]
        isolated = total <= 0
        if isolated.any():
            estimate[isolated] = np.median(disp, axis=0)
        return estimate

    def _griddata(self, points: np.ndarray, disp: np.ndarray) -> tuple[np.ndarray, int]:
        """Cubic griddata (G, 2); cells outside the hull (or degenerate input) take the nearest marker."""
        try:
            grid = griddata(points, disp, self._grid_points, method="cubic")
        except (ValueError, RuntimeError):
            grid = np.full((self._grid_points.shape[0], 2), np.nan)
        outside = ~np.all(np.isfinite(grid), axis=1)
        if outside.any():
            grid[outside] = griddata(points, disp, self._grid_points[outside], method="nearest")
        return grid, int(outside.sum())
