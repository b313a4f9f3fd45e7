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

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.interpolate import RBFInterpolator, griddata

from fv_algos.reference_markers import checked_reference

Kernel = Literal["thin_plate_spline", "multiquadric", "inverse_multiquadric", "gaussian", "linear", "cubic"]

# Every kernel gets a linear polynomial term (1, x, y), as scipy.interpolate.RBFInterpolator
# does by default: it is the most any of these kernels needs, and it reproduces uniform
# translation and linear strain exactly.
MAX_MARKERS = 400  # the most markers a pipeline takes by default: the RBF solve grows as N^3 (3000 took 19 s)
MAX_SMOOTHING = 1e12  # past it the balanced RBF system overflows (1e300); from about 1e6 the field is a plane fit
_KERNELS = ("thin_plate_spline", "multiquadric", "inverse_multiquadric", "gaussian", "linear", "cubic")
_SCALED = ("multiquadric", "inverse_multiquadric", "gaussian")
_POLY_TERMS = 3
# Valid reference points whose thinner principal spread (smaller singular value of the centred
# points) is below this share of the larger one are collinear: the linear term is undetermined
# across the line (a uniform translation comes out wrong by up to its own size from a share of
# ~1e-7 down, by < 1e-3 of it from 1e-5 up).
_COLLINEAR_RTOL = 1e-5


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
    min_markers: fewer valid markers than this (or than the polynomial needs) gives an
        all-zero field flagged invalid.
    min_valid_share: a smaller share of the reference markers valid gives an all-zero field
        flagged invalid (0 disables). A corrupt frame (pure noise) gets chance matches, ~10 %
        of the markers (24 of 256 in a simulated skin), whose field is large and wrong (read as
        slip); real recordings stay above 0.25 in every frame: GelSight Mini trials >= 0.79, the
        FingerVision video fingervision_cam1_0002.m4v >= 0.29 (9 of its 31 markers, over its
        2931 frames from frame 1, the reference, on). 0.25 catches the first and none of these.
    """

    method: Literal["rbf_operator", "rbf_refit", "griddata"] = "rbf_operator"
    grid_shape: tuple[int, int] = (30, 30)
    kernel: Kernel = "thin_plate_spline"
    width_px: float | None = None
    smoothing: float = 0.0
    rcond: float = 1e-10
    min_markers: int = 3
    min_valid_share: float = 0.25

    def __post_init__(self) -> None:
        if self.method not in ("rbf_operator", "rbf_refit", "griddata"):
            raise ValueError(f"FieldParams.method must be rbf_operator, rbf_refit or griddata, got {self.method!r}")
        if self.kernel not in _KERNELS:
            raise ValueError(f"FieldParams.kernel must be one of {_KERNELS}, got {self.kernel!r}")
        if (len(self.grid_shape) != 2 or not all(isinstance(n, (int, np.integer)) for n in self.grid_shape)
                or min(self.grid_shape) < 2):  # (2.5, 3) passed, then failed in numpy as "'float' object ..."
            raise ValueError(f"FieldParams.grid_shape must be (H, W), whole numbers both >= 2, got {self.grid_shape}")
        if self.width_px is not None and not (np.isfinite(self.width_px) and self.width_px > 0.0):
            raise ValueError(f"FieldParams.width_px must be None or finite > 0, got {self.width_px}")
        if not 0.0 <= self.smoothing <= MAX_SMOOTHING:
            raise ValueError(f"FieldParams.smoothing must be in [0, {MAX_SMOOTHING:g}] (from about 1e6 on the field is "
                             f"the markers' least-squares plane), got {self.smoothing}")
        if not 0.0 < self.rcond < 1.0:
            raise ValueError(f"FieldParams.rcond must be in (0, 1), got {self.rcond}")
        if self.min_markers < 1:
            raise ValueError(f"min_markers must be >= 1, got {self.min_markers}")
        if not 0.0 <= self.min_valid_share <= 1.0:
            raise ValueError(f"FieldParams.min_valid_share must be in [0, 1], got {self.min_valid_share}")


@dataclass(frozen=True)
class DisplacementField:
    """One frame's dense field.

    field: (H, W, 3) float32, channels dx_px, dy_px, magnitude_px; all finite (zeros when
    invalid). x_px: (W,) float64 and y_px: (H,) float64 grid coordinates in the reference
    frame. valid: False when too few markers (or too small a share of them) were valid, their
    reference points were collinear, or the field is not finite in float32. markers_used:
    markers that fed it.
    filled_cells: grid cells filled from the nearest marker (griddata outside the hull).
    """

    field: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    valid: bool
    markers_used: int
    filled_cells: int = 0


def _spans_plane(points_px: np.ndarray) -> bool:
    """Whether points (n >= 2, 2) px are not (numerically) collinear: the smaller singular value
    of the centred points exceeds `_COLLINEAR_RTOL` x the larger (coincident points: False)."""
    spread = np.linalg.svd(points_px - points_px.mean(axis=0), compute_uv=False)
    return bool(spread[1] > _COLLINEAR_RTOL * spread[0])


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


def rbf_system(
    markers_px: np.ndarray,
    grid_points_px: np.ndarray,
    kernel: str = "thin_plate_spline",
    width_px: float = 25.0,
    smoothing: float = 0.0,
    rcond: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The RBF interpolation system of N markers and its evaluation at G grid points.

    markers_px: (N, 2) float64 finite reference positions. grid_points_px: (G, 2) float64.
    Kernel phi(r / width_px) for multiquadric / inverse_multiquadric / gaussian, phi(r / extent)
    for the scale-free kernels (extent = the markers' largest bounding-box side; the
    interpolant does not depend on it), plus a linear polynomial. The symmetric system
    A = [[K + smoothing I, P], [P^T, 0]] is inverted by an eigen pseudo-inverse (eigenvalues
    below rcond x the largest magnitude dropped) so collinear or coincident markers stay
    finite. Returns (inverse (N+3, N+3), evaluation (G, N+3) float64, condition number of A as balanced):
    grid values = evaluation @ inverse[:, :N] @ marker values.
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
    # Balanced: the polynomial rows and columns scaled by 1 + smoothing (the kernel block's entries are about 1
    # plus the smoothing), and the inverse scaled back. Unbalanced, a large smoothing put the polynomial block's
    # eigenvalues (about |P|^2 / smoothing) below rcond x the largest: they were dropped and the field came out
    # zero, flagged valid (smoothing 1e8). Balanced, theirs are about |P|^2 (1 + smoothing). No smoothing: a
    # scale of 1, the same system as before.
    scale = np.ones(n + _POLY_TERMS)
    scale[n:] = 1.0 + smoothing
    system *= scale[:, None] * scale[None, :]
    eigenvalues, vectors = np.linalg.eigh(system)
    magnitude = np.abs(eigenvalues)
    largest = magnitude.max()
    keep = magnitude > rcond * largest if largest > 0.0 else np.zeros_like(magnitude, dtype=bool)
    inverse = scale[:, None] * ((vectors[:, keep] / eigenvalues[keep]) @ vectors[:, keep].T) * scale[None, :]
    evaluation = np.hstack(
        [
            _kernel(_distances(grid_points_px, markers_px), kernel, width),
            _linear_basis(grid_points_px, centre, extent),
        ]
    )
    smallest = magnitude.min()
    condition = float(largest / smallest) if smallest > 0.0 else float("inf")
    return inverse, evaluation, condition


def rbf_operator(
    markers_px: np.ndarray,
    grid_points_px: np.ndarray,
    kernel: str = "thin_plate_spline",
    width_px: float = 25.0,
    smoothing: float = 0.0,
    rcond: float = 1e-10,
) -> tuple[np.ndarray, float]:
    """(operator (G, N) float64, condition number): grid values = operator @ marker values
    (N, C) for the RBF interpolant of `rbf_system`."""
    inverse, evaluation, condition = rbf_system(markers_px, grid_points_px, kernel, width_px, smoothing, rcond)
    return evaluation @ inverse[:, : markers_px.shape[0]], condition


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
        ref = checked_reference(reference_px, "reference_px")
        self.params = params
        self.reference_px = ref
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
        self._system: tuple[np.ndarray, np.ndarray] | None = None
        self.condition = float("nan")

    def system(self) -> tuple[np.ndarray, np.ndarray]:
        """(inverse (N+3, N+3), evaluation (G, N+3)) of all reference markers, solved once."""
        if self._system is None:
            inverse, evaluation, self.condition = rbf_system(
                self.reference_px, self._grid_points, self.params.kernel, self.width_px,
                self.params.smoothing, self.params.rcond)
            self._system = inverse, evaluation
        return self._system

    def interpolate(self, current_px: np.ndarray, valid: np.ndarray) -> DisplacementField:
        """Field from current marker positions (N, 2) px and validity (N,) bool.

        Markers with non-finite positions count as not valid. Returns a `DisplacementField`,
        flagged invalid and all-zero when the valid markers cannot carry a field (`_carries_field`)
        or the field does not fit float32.
        """
        cur = np.asarray(current_px, dtype=np.float64)
        mask = np.asarray(valid, dtype=bool)
        n = self.reference_px.shape[0]
        if cur.shape != (n, 2) or mask.shape != (n,):
            raise ValueError(f"current_px must be ({n}, 2) and valid ({n},), got {cur.shape}, {mask.shape}")
        mask = mask & np.all(np.isfinite(cur), axis=1)
        used = int(mask.sum())
        h, w = self.params.grid_shape
        if not self._carries_field(mask):
            return DisplacementField(np.zeros((h, w, 3), np.float32), self.x_px, self.y_px, False, used)
        disp = cur[mask] - self.reference_px[mask]
        filled = 0
        method = self.params.method
        if method == "rbf_operator":
            grid = self._apply_operator(mask, disp)
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
        out = np.empty((h * w, 3), dtype=np.float32)
        with np.errstate(over="ignore"):  # beyond float32: inf, refused below
            out[:, :2] = grid
            out[:, 2] = np.hypot(grid[:, 0], grid[:, 1])
        if not np.all(np.isfinite(out)):
            return DisplacementField(np.zeros((h, w, 3), np.float32), self.x_px, self.y_px, False, used)
        return DisplacementField(out.reshape(h, w, 3), self.x_px, self.y_px, True, used, filled)

    def _carries_field(self, mask: np.ndarray) -> bool:
        """Whether the valid markers `mask` (N,) bool can carry a field: at least `min_markers` (and
        the polynomial's 3), at least `min_valid_share` of the reference markers, and reference
        points spanning the plane (`_spans_plane`: the linear term needs 2-D)."""
        used = int(mask.sum())
        if used < max(self.params.min_markers, _POLY_TERMS):
            return False
        if used < self.params.min_valid_share * mask.size:
            return False
        return _spans_plane(self.reference_px[mask])

    def _apply_operator(self, mask: np.ndarray, disp: np.ndarray) -> np.ndarray:
        """(G, 2) grid displacements from the valid markers' (n_valid, 2) displacements.

        Exact RBF interpolation of the valid markers alone, without solving their system:
        with B the inverse of the all-markers system and S the k missing markers, the
        inverse of the reduced system is B_RR - B_RS B_SS^-1 B_SR (block inverse), so a
        frame costs two (N+3) x N products and one k x k solve.
        """
        inverse, evaluation = self.system()
        n = self.reference_px.shape[0]
        values = np.zeros((n, 2))
        values[mask] = disp
        coeffs = inverse[:, :n] @ values
        missing = np.flatnonzero(~mask)
        if missing.size:
            block = inverse[np.ix_(missing, missing)]
            try:
                correction = np.linalg.solve(block, coeffs[missing])
            except np.linalg.LinAlgError:
                correction = np.linalg.lstsq(block, coeffs[missing], rcond=None)[0]
            coeffs -= inverse[:, missing] @ correction
            coeffs[missing] = 0.0
        return evaluation @ coeffs

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
