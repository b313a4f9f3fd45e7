"""Fisheye calibration from chessboard views, their sources, and a synthetic view renderer.

Workflow: collect (name, image) views with `load_images` (a folder) or `load_video_frames`
(every k-th frame of a video), then `calibrate_fisheye(views, CalibrationParams(...))`,
then `result.camera.save(path)`. `ChessboardRenderer` and `random_board_poses` make
synthetic views through a known camera, for tests and demos.

Board frame: x along the rows of inner corners, y along the columns, z normal to the board,
mm; the first inner corner is the origin. Camera frame and pixels as in `fv_algos.fisheye`.
"""
from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from fv_algos.fisheye import FisheyeCamera, utc_timestamp

log = logging.getLogger(__name__)

IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")

STARTING_HALF_FOV_RAD: tuple[float, ...] = (1.0, 1.25, 1.5)
"""Ray angles (rad) at half the image's longer side that `cv2.fisheye.calibrate` is started from: focal
length max(W, H) / 2 / angle, principal point at the image centre; the fit with the lowest RMS wins.
OpenCV's own start, max(W, H) / pi (pi / 2 rad), is not among them: from it a strong fisheye (fx near
W / 3) diverged or failed on most small sets of clean views."""

OUTLIER_FACTOR = 3.0
"""A view is dropped as an outlier only when its reprojection RMS is over `CalibrationParams.max_rms_px`
and over this many times the median view's."""

MIN_TILT_DEG = 10.0  # at least one view's board this far from face-on: face-on views fit any focal length
# (8 face-on views of a 300 px lens: fx 10,772 px, RMS 0.69 px, its distortion folding back 2.8 deg off the axis)
SAME_VIEW_PX = 1.0  # a view whose corners lie within this RMS of an earlier view's is that view again
# (six copies of one image calibrated to fx 10,818 px for a 300 px lens, RMS 1.29 px)

SUBPIX_SPACING_SHARE = 1.0 / 3.0
"""The cornerSubPix half window is at most this share of the distance to the nearest neighbouring corner:
a larger one takes in the next corner's edges and pulls the refined corner off."""


@dataclass(frozen=True)
class Chessboard:
    """A printed chessboard.

    Attributes:
        inner_corners: (columns, rows) of inner corners, as OpenCV's patternSize.
        square_mm: side of one square, mm.
        margin_squares: width of the white border around the squares, in squares (used by
            the renderer; the detector needs a light border).
    """

    inner_corners: tuple[int, int] = (7, 5)
    square_mm: float = 2.5
    margin_squares: float = 1.0

    def __post_init__(self) -> None:
        cols, rows = self.inner_corners
        if cols < 2 or rows < 2:
            raise ValueError(f"inner_corners must be at least (2, 2), got {self.inner_corners}")
        if not (np.isfinite(self.square_mm) and self.square_mm > 0):
            raise ValueError(f"square_mm must be a finite number > 0, got {self.square_mm}")
        if not (np.isfinite(self.margin_squares) and self.margin_squares >= 0):
            raise ValueError(f"margin_squares must be a finite number >= 0, got {self.margin_squares}")

    def object_points_mm(self) -> np.ndarray:
        """(M, 3) float64 inner-corner positions in the board frame, mm, row by row (z = 0)."""
        cols, rows = self.inner_corners
        u, v = np.meshgrid(np.arange(cols), np.arange(rows))
        return np.stack([u.ravel(), v.ravel(), np.zeros(cols * rows)], axis=1) * np.array([self.square_mm, self.square_mm, 1.0])

    def outline_mm(self) -> np.ndarray:
        """(4, 3) float64 corners of the board including its white border, board frame, mm."""
        cols, rows = self.inner_corners
        low = -(1.0 + self.margin_squares) * self.square_mm
        high_u = (cols + self.margin_squares) * self.square_mm
        high_v = (rows + self.margin_squares) * self.square_mm
        return np.array([[low, low, 0.0], [high_u, low, 0.0], [high_u, high_v, 0.0], [low, high_v, 0.0]])

    def centre_mm(self) -> np.ndarray:
        """(3,) float64 centre of the inner-corner grid, board frame, mm."""
        cols, rows = self.inner_corners
        return np.array([(cols - 1) / 2.0, (rows - 1) / 2.0, 0.0]) * self.square_mm


@dataclass(frozen=True)
class CalibrationParams:
    """Parameters of `calibrate_fisheye`.

    Attributes:
        board: the chessboard in the views.
        min_views: fewest views with a found board that a calibration accepts.
        subpix_half_window_px: largest half side of the cornerSubPix search window, px (smaller
            where the corners lie closer: see `find_chessboard_corners`).
        max_iterations: iteration limit of cv2.fisheye.calibrate.
        epsilon: convergence threshold of cv2.fisheye.calibrate.
        max_rms_px: largest reprojection RMS accepted, px: a view above it (and OUTLIER_FACTOR
            times the median view) is dropped, worst first, and the rest calibrated again; a
            calibration still above it is refused.
    """

    board: Chessboard = field(default_factory=Chessboard)
    min_views: int = 5
    subpix_half_window_px: int = 5
    max_iterations: int = 100
    epsilon: float = 1e-9
    max_rms_px: float = 2.0

    def __post_init__(self) -> None:
        if self.min_views < 3:
            raise ValueError(f"min_views must be >= 3, got {self.min_views}")
        if self.subpix_half_window_px < 2:
            raise ValueError(f"subpix_half_window_px must be >= 2, got {self.subpix_half_window_px}")
        if self.max_iterations < 1 or not self.epsilon > 0:
            raise ValueError(f"max_iterations must be >= 1 and epsilon > 0, got {self.max_iterations}, {self.epsilon}")
        if not (np.isfinite(self.max_rms_px) and self.max_rms_px > 0):
            raise ValueError(f"max_rms_px must be a finite number > 0, got {self.max_rms_px}")


@dataclass(eq=False)
class CalibrationResult:
    """Outcome of `calibrate_fisheye`.

    Attributes:
        camera: the calibrated camera (rms_px and date filled in).
        rms_px: overall reprojection RMS, px.
        used: names of the views that took part.
        rejected: name -> reason, for the views that did not.
        per_view_rms_px: (len(used),) float64 reprojection RMS of each used view, px.
    """

    camera: FisheyeCamera
    rms_px: float
    used: list[str]
    rejected: dict[str, str]
    per_view_rms_px: np.ndarray


def _to_gray(image: np.ndarray, name: str) -> np.ndarray:
    """(H, W) uint8 view of a mono or BGR uint8 image."""
    if image.dtype != np.uint8:
        raise ValueError(f"image {name!r} must be uint8, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    raise ValueError(f"image {name!r} must be (H, W) or (H, W, 3), got shape {image.shape}")


def _subpix_half_windows(corners: np.ndarray, board: Chessboard, max_half_window_px: int) -> np.ndarray:
    """(M,) int cornerSubPix half windows, px: SUBPIX_SPACING_SHARE of each corner's distance to its
    nearest row or column neighbour, from 1 to max_half_window_px.

    Args:
        corners: (M, 2) corner pixels in the detector's grid order (rows of `board.inner_corners[0]`).
    """
    cols, rows = board.inner_corners
    grid = corners.reshape(rows, cols, 2)
    across = np.linalg.norm(np.diff(grid, axis=1), axis=2)  # (rows, cols - 1)
    down = np.linalg.norm(np.diff(grid, axis=0), axis=2)  # (rows - 1, cols)
    spacing = np.full((rows, cols), np.inf)
    spacing[:, :-1] = across
    spacing[:, 1:] = np.minimum(spacing[:, 1:], across)
    spacing[:-1] = np.minimum(spacing[:-1], down)
    spacing[1:] = np.minimum(spacing[1:], down)
    return np.clip(np.floor(spacing * SUBPIX_SPACING_SHARE), 1, max_half_window_px).astype(int).ravel()


def find_chessboard_corners(image: np.ndarray, board: Chessboard, subpix_half_window_px: int = 5) -> np.ndarray | None:
    """Inner corners of the chessboard in an image, refined to sub-pixel.

    Each corner is refined in a window of at most a third of the distance to its nearest
    neighbouring corner (`SUBPIX_SPACING_SHARE`), so that small or steeply tilted squares are
    refined on their own edges only.

    Args:
        image: (H, W) or (H, W, 3) BGR uint8 image.
        board: the chessboard looked for.
        subpix_half_window_px: largest half side of the cornerSubPix search window, px.
    Returns:
        (M, 2) float64 corner pixels (u, v) row by row as `board.object_points_mm()`
        (possibly starting from the opposite corner), or None if the board is not found.
    """
    gray = _to_gray(image, "image")
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, board.inner_corners, flags=flags)
    if not found:
        return None
    corners = corners.reshape(-1, 2).astype(np.float32)
    half_windows = _subpix_half_windows(corners, board, subpix_half_window_px)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-3)
    for half in np.unique(half_windows):
        chosen = half_windows == half
        window = (int(half), int(half))
        refined = cv2.cornerSubPix(gray, corners[chosen].reshape(-1, 1, 2), window, (-1, -1), criteria)
        corners[chosen] = refined.reshape(-1, 2)
    return corners.astype(np.float64)


def _common_size(grays: Sequence[tuple[str, np.ndarray]]) -> tuple[tuple[int, int], dict[str, str]]:
    """The most common (width, height) of the views (the first seen on a tie), and name -> reason
    for the views of another size."""
    sizes = [(gray.shape[1], gray.shape[0]) for _, gray in grays]
    counts = Counter(sizes)
    size, count = counts.most_common(1)[0]
    odd = {
        name: f"image size {w}x{h} differs from the most common {size[0]}x{size[1]} ({count} of {len(grays)} views)"
        for (name, _), (w, h) in zip(grays, sizes) if (w, h) != size
    }
    return size, odd


def _not_found_error(n_found: int, n_views: int, rejected: dict[str, str], params: CalibrationParams) -> ValueError:
    """A short error for too few boards found: the count of each reason, with a few view names."""
    by_reason: dict[str, list[str]] = {}
    for name, why in rejected.items():
        by_reason.setdefault(why, []).append(name)
    parts = [f"{len(names)} x {why} ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''})"
             for why, names in by_reason.items()]
    cols, rows = params.board.inner_corners
    hint = (f". The board size counts INNER corners: {cols}x{rows} is a board of {cols + 1}x{rows + 1} squares"
            if _not_found(params.board) in by_reason else "")  # (said of duplicate views too, found in every one)
    return ValueError(f"chessboard usable in {n_found} of {n_views} views, need at least {params.min_views}"
                      f"{'; rejected: ' + '; '.join(parts) if parts else ''}{hint}")


def _not_found(board: Chessboard) -> str:
    """Why a view is rejected when `board` is not found in it."""
    return f"chessboard with {board.inner_corners[0]}x{board.inner_corners[1]} inner corners not found"


@dataclass(frozen=True)
class _Fit:
    """One cv2.fisheye.calibrate solution: the camera (without rms_px and date), (V,) float64
    per-view reprojection RMS, px (inf for a view whose board it puts partly behind the camera), and
    (V,) float64 tilt of each view's board, deg (0: face-on to the camera)."""

    camera: FisheyeCamera
    per_view_rms_px: np.ndarray
    tilt_deg: np.ndarray

    @property
    def rms_px(self) -> float:
        """Overall reprojection RMS, px (every view has the same corners); inf if a view's is."""
        return float(np.sqrt(np.mean(self.per_view_rms_px**2)))


def _per_view_rms(camera: FisheyeCamera, object_points: np.ndarray, image_points: Sequence[np.ndarray],
                  rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray]) -> np.ndarray:
    """(V,) float64 reprojection RMS of each view, px; inf where a board point falls behind the camera."""
    rms = np.full(len(image_points), np.inf)
    for i, (rvec, tvec, observed) in enumerate(zip(rvecs, tvecs, image_points)):
        R, _ = cv2.Rodrigues(rvec)
        points_cam = object_points @ R.T + tvec.reshape(1, 3)
        if np.all(points_cam[:, 2] > 0):
            rms[i] = np.sqrt(np.mean(np.sum((camera.project(points_cam) - observed) ** 2, axis=1)))
    return rms


def _fit_from(start_K: np.ndarray, object_points: np.ndarray, image_points: Sequence[np.ndarray],
              size: tuple[int, int], params: CalibrationParams) -> _Fit:
    """cv2.fisheye.calibrate started from the (3, 3) matrix start_K and no distortion.

    Raises:
        cv2.error: OpenCV failed.
        ValueError: it returned no valid camera (a focal length <= 0).
    """
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.max_iterations, params.epsilon)
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS
    # cv2.fisheye.calibrate accepts the points as (1, M, 3) / (1, M, 2) float64 arrays.
    _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
        [object_points[None]] * len(image_points), [p[None] for p in image_points],
        size, start_K.copy(), np.zeros(4), flags=flags, criteria=criteria,
    )
    camera = FisheyeCamera(K=K, D=D.ravel(), width=size[0], height=size[1])
    tilt_deg = np.array([np.degrees(np.arccos(min(1.0, abs(cv2.Rodrigues(rvec)[0][2, 2])))) for rvec in rvecs])
    return _Fit(camera, _per_view_rms(camera, object_points, image_points, rvecs, tvecs), tilt_deg)


def _best_fit(object_points: np.ndarray, image_points: Sequence[np.ndarray], size: tuple[int, int],
              params: CalibrationParams, names: Sequence[str]) -> _Fit:
    """The fit with the lowest RMS among the starts of STARTING_HALF_FOV_RAD.

    Raises:
        ValueError: OpenCV failed, or gave no valid camera, from every start (the views named).
    """
    fits: list[_Fit] = []
    errors: list[str] = []
    for half_fov in STARTING_HALF_FOV_RAD:
        focal = max(size) / 2.0 / half_fov
        start_K = np.array([[focal, 0.0, (size[0] - 1) / 2.0], [0.0, focal, (size[1] - 1) / 2.0], [0.0, 0.0, 1.0]])
        try:
            fits.append(_fit_from(start_K, object_points, image_points, size, params))
        except (cv2.error, ValueError) as exc:
            errors.append(f"from fx {focal:.0f} px: {str(exc).strip().splitlines()[-1]}")
    if not fits:
        raise ValueError(f"cv2.fisheye.calibrate failed on views {list(names)}: {'; '.join(errors)}")
    return min(fits, key=lambda fit: fit.rms_px)


def _outlier(per_view_rms_px: np.ndarray, max_rms_px: float) -> tuple[int, str] | None:
    """(index, reason) of the worst view when it is an outlier (over max_rms_px and OUTLIER_FACTOR times the
    median view), else None."""
    worst = int(np.argmax(per_view_rms_px))
    value, median = per_view_rms_px[worst], np.median(per_view_rms_px)
    if not (value > max_rms_px and value > OUTLIER_FACTOR * median):
        return None
    if not np.isfinite(value):
        return worst, "the calibration puts its board behind the camera: dropped as an outlier"
    return worst, (f"reprojection RMS {value:.2f} px, over {max_rms_px:g} px and {OUTLIER_FACTOR:g}x the "
                   f"median view's {median:.2f} px: dropped as an outlier")


def _rms_error(fit: _Fit, names: Sequence[str], max_rms_px: float) -> ValueError:
    """The refusal of a calibration over max_rms_px, naming its RMS and its worst views."""
    order = np.argsort(-fit.per_view_rms_px)[:3]
    worst = ", ".join(f"{names[i]} {fit.per_view_rms_px[i]:.2f} px" for i in order)
    return ValueError(
        f"calibration RMS {fit.rms_px:.2f} px is over the limit of {max_rms_px:g} px (worst views: {worst}); "
        "check the board size and square, and remove blurred or partly hidden views"
    )


def calibrate_fisheye(views: Sequence[tuple[str, np.ndarray]], params: CalibrationParams) -> CalibrationResult:
    """Calibrate a fisheye camera from chessboard views with `cv2.fisheye.calibrate`.

    The solver is started from several focal lengths (STARTING_HALF_FOV_RAD) and the best fit
    kept; a view that fails (reprojection RMS over params.max_rms_px and OUTLIER_FACTOR times the
    median view, or its board put behind the camera) is dropped and the rest calibrated again.

    Args:
        views: (name, image) pairs; images (H, W) or (H, W, 3) uint8.
        params: board and solver parameters.
    Returns:
        The calibration at the most common image size; views of another size, whose board was
        not found, or dropped as outliers are listed in `rejected` with the reason.
    Raises:
        ValueError: no views, malformed images, fewer than params.min_views boards found
            (counted by reason, a few views named), the solver failed, the RMS is over
            params.max_rms_px (its worst views named), or every view shows the board within
            MIN_TILT_DEG of face-on.
    """
    if len(views) == 0:
        raise ValueError("views is empty: calibration needs chessboard images")
    board = params.board
    grays = [(name, _to_gray(image, name)) for name, image in views]
    size, rejected = _common_size(grays)
    used: list[str] = []
    image_points: list[np.ndarray] = []
    for name, gray in grays:
        if name in rejected:
            continue
        corners = find_chessboard_corners(gray, board, params.subpix_half_window_px)
        if corners is None:
            rejected[name] = _not_found(board)
            continue
        same = [other for other, seen in zip(used, image_points)
                if np.sqrt(np.mean(np.sum((corners - seen) ** 2, axis=1))) < SAME_VIEW_PX]
        if same:  # frames of a board held still: one view counted several times pins nothing down
            rejected[name] = f"the board where {same[0]} shows it (corners within {SAME_VIEW_PX:g} px): adds nothing"
            continue
        used.append(name)
        image_points.append(corners)
    if len(used) < params.min_views:
        raise _not_found_error(len(used), len(views), rejected, params)
    object_points = board.object_points_mm()
    fit = _best_fit(object_points, image_points, size, params, used)
    while len(used) > params.min_views and (outlier := _outlier(fit.per_view_rms_px, params.max_rms_px)):
        worst, rejected[used[worst]] = outlier
        del used[worst], image_points[worst]
        fit = _best_fit(object_points, image_points, size, params, used)
    if not fit.rms_px <= params.max_rms_px:
        raise _rms_error(fit, used, params.max_rms_px)
    if fit.tilt_deg.max() < MIN_TILT_DEG:
        raise ValueError(
            f"every view shows the board nearly face-on (the most tilted {fit.tilt_deg.max():.1f} deg; fit: RMS "
            f"{fit.rms_px:.2f} px, fx {fit.camera.K[0, 0]:.0f} px): such views fit any focal length, so the lens is "
            f"not known. Tilt the board {MIN_TILT_DEG:g} to 45 deg in several views, near the image's corners too")
    camera = replace(fit.camera, rms_px=fit.rms_px, date=utc_timestamp())
    return CalibrationResult(camera=camera, rms_px=fit.rms_px, used=used, rejected=rejected,
                             per_view_rms_px=fit.per_view_rms_px)


def image_files(folder: str | Path, suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> list[Path]:
    """The image files of a folder (not recursive), sorted by name.

    Raises:
        ValueError: the folder does not exist or holds no file ending in `suffixes`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"image folder {folder} {'is a file, not a folder' if folder.exists() else 'does not exist'}")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in suffixes and p.is_file())
    if not paths:
        raise ValueError(f"image folder {folder} holds no file ending in {', '.join(suffixes)}")
    return paths


def load_images(folder: str | Path, suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> list[tuple[str, np.ndarray]]:
    """Read every image in a folder (not recursive) as mono uint8, sorted by file name. A file that
    cannot be decoded (a macOS `._name.png`, a half-copied image) is skipped with a warning naming it:
    one such file stopped the whole calibration.

    Returns:
        (file name, (H, W) uint8 image) pairs.
    Raises:
        ValueError: the folder does not exist, holds no image, or no image can be decoded.
    """
    views, undecoded = [], []
    for path in image_files(folder, suffixes):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            undecoded.append(path.name)
            log.warning("image %s cannot be decoded: skipped", path)
            continue
        views.append((path.name, image))
    if not views:
        raise ValueError(f"no image of {folder} can be decoded ({', '.join(undecoded[:3])}"
                         f"{', ...' if len(undecoded) > 3 else ''})")
    return views


def load_video_frames(path: str | Path, every_k: int) -> list[tuple[str, np.ndarray]]:
    """Read every k-th frame of a video file as mono uint8.

    Returns:
        ("frame_NNNNNN" with the 0-based frame index, (H, W) uint8 image) pairs.
    Raises:
        ValueError: every_k < 1, or the file cannot be opened or holds no frame.
    """
    if every_k < 1:
        raise ValueError(f"every_k must be >= 1, got {every_k}")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ValueError(f"video {path} cannot be opened")
    views = []
    index = 0
    try:
        while True:
            ok = capture.grab()
            if not ok:
                break
            if index % every_k == 0:
                ok, frame = capture.retrieve()
                if not ok:
                    break
                views.append((f"frame_{index:06d}", _to_gray(frame, f"frame_{index:06d}")))
            index += 1
    finally:
        capture.release()
    if not views:
        raise ValueError(f"video {path} holds no readable frame")
    return views


@dataclass(frozen=True)
class ChessboardRenderParams:
    """Appearance of synthetic chessboard views.

    Attributes:
        supersample: sub-pixel samples per pixel side (anti-aliasing by box filtering).
        dark_level: grey level of the dark squares.
        light_level: grey level of the light squares and the border.
        background_level: grey level where no board is seen.
    """

    supersample: int = 3
    dark_level: float = 30.0
    light_level: float = 220.0
    background_level: float = 90.0

    def __post_init__(self) -> None:
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        for name in ("dark_level", "light_level", "background_level"):
            if not 0.0 <= getattr(self, name) <= 255.0:
                raise ValueError(f"{name} must be in [0, 255], got {getattr(self, name)}")


class ChessboardRenderer:
    """Renders a chessboard seen through a known fisheye camera.

    Each output pixel is the mean of supersample^2 sub-pixel samples; each sample's ray
    (the exact inverse of the camera model) is intersected with the board plane and the
    board pattern looked up there. The rays are computed once, at construction.
    """

    def __init__(self, camera: FisheyeCamera, board: Chessboard, params: ChessboardRenderParams) -> None:
        self.camera = camera
        self.board = board
        self.params = params
        s = params.supersample
        sub = (np.arange(s) + 0.5) / s - 0.5
        # Samples ordered (row, sub-row, column, sub-column) so that pixels are block means.
        u = np.arange(camera.width)[None, None, :, None] + sub[None, None, None, :]
        v = np.arange(camera.height)[:, None, None, None] + sub[None, :, None, None]
        u, v = np.broadcast_arrays(u, v)
        rays, valid = camera.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1))
        rays[~valid] = 0.0
        # One contiguous float32 array per component: the per-view work is elementwise.
        self._rays = [np.ascontiguousarray(rays[:, k], dtype=np.float32) for k in range(3)]

    def render(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """Render one view.

        Args:
            rvec: (3,) Rodrigues rotation of the board frame into the camera frame.
            tvec: (3,) position of the board origin in the camera frame, mm.
        Returns:
            (H, W) uint8 image.
        """
        R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
        t_board = R.T @ np.asarray(tvec, dtype=np.float64).reshape(3)
        rx, ry, rz = self._rays
        # Ray directions in the board frame (R^T d); a sample hits the board plane at
        # board point (t_z / q_z) q - R^T t when t_z / q_z > 0. Invalid rays are 0 and miss.
        q = [np.float32(R[0, k]) * rx + np.float32(R[1, k]) * ry + np.float32(R[2, k]) * rz for k in range(3)]
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.float32(t_board[2]) / q[2]
        hit = scale > 0
        square = self.board.square_mm
        board_u = (q[0] * scale - np.float32(t_board[0])) / np.float32(square)
        board_v = (q[1] * scale - np.float32(t_board[1])) / np.float32(square)
        cols, rows = self.board.inner_corners
        margin = self.board.margin_squares
        on_board = (
            hit & (board_u >= -1 - margin) & (board_u <= cols + margin) & (board_v >= -1 - margin) & (board_v <= rows + margin)
        )
        in_squares = (board_u >= -1) & (board_u < cols) & (board_v >= -1) & (board_v < rows)
        for coordinate in (board_u, board_v):
            np.copyto(coordinate, np.float32(0.0), where=~on_board)
            np.floor(coordinate, out=coordinate)
        parity = (board_u.astype(np.int32) + board_v.astype(np.int32)) & 1
        dark = in_squares & (parity == 0)
        p = self.params
        samples = np.full(len(rx), p.background_level, dtype=np.float32)
        samples[on_board] = p.light_level
        samples[dark & on_board] = p.dark_level
        s = p.supersample
        h, w = self.camera.height, self.camera.width
        image = samples.reshape(h, s, w, s).mean(axis=(1, 3))
        return np.rint(image).astype(np.uint8)


def random_board_poses(
    camera: FisheyeCamera,
    board: Chessboard,
    n_views: int,
    distance_range_mm: tuple[float, float],
    max_tilt_deg: float,
    seed: int,
    edge_margin_px: float = 10.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses spread over the image with the whole board (border included) in view.

    Args:
        camera: the camera.
        board: the chessboard.
        n_views: number of poses.
        distance_range_mm: (min, max) distance of the board centre from the camera, mm.
        max_tilt_deg: largest tilt of the board normal from the optical axis, degrees.
        seed: random seed.
        edge_margin_px: least distance of the board outline from the image border, px.
    Returns:
        n_views (rvec (3,), tvec (3,)) float64 pairs, as `ChessboardRenderer.render` takes.
    Raises:
        ValueError: bad ranges, or no such pose is found (board too large for the view).
    """
    low, high = distance_range_mm
    if not 0 < low <= high or not 0 <= max_tilt_deg < 90 or n_views < 1:
        raise ValueError(
            "need n_views >= 1, 0 < min <= max distance and tilt in [0, 90); "
            f"got {n_views}, {distance_range_mm}, {max_tilt_deg}"
        )
    rng = np.random.default_rng(seed)
    corners = board.outline_mm()
    steps = np.linspace(0.0, 1.0, 16, endpoint=False)[:, None]
    # Points along the four edges: straight edges bow in a fisheye image.
    outline = np.concatenate([corners[i] + steps * (corners[(i + 1) % 4] - corners[i]) for i in range(4)])
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    attempts = 0
    while len(poses) < n_views:
        attempts += 1
        if attempts > 1000 * n_views:
            raise ValueError(f"found only {len(poses)} of {n_views} board poses that keep the board in view")
        target_px = rng.uniform([0.2 * camera.width, 0.2 * camera.height], [0.8 * camera.width, 0.8 * camera.height])
        rays, valid = camera.pixel_rays(target_px[None])
        if not valid[0]:
            continue
        tilt_axis = rng.uniform(0.0, 2.0 * np.pi)
        tilt = np.deg2rad(rng.uniform(0.0, max_tilt_deg))
        tilt_vec = tilt * np.array([np.cos(tilt_axis), np.sin(tilt_axis), 0.0])
        spin_vec = np.array([0.0, 0.0, rng.uniform(-np.pi / 6, np.pi / 6)])
        R = cv2.Rodrigues(tilt_vec)[0] @ cv2.Rodrigues(spin_vec)[0]
        tvec = rays[0] * rng.uniform(low, high) - R @ board.centre_mm()
        outline_cam = outline @ R.T + tvec
        if np.any(outline_cam[:, 2] <= 0):
            continue
        outline_px = camera.project(outline_cam)
        upper = [camera.width - 1 - edge_margin_px, camera.height - 1 - edge_margin_px]
        if np.all(outline_px >= edge_margin_px) and np.all(outline_px <= upper):
            poses.append((cv2.Rodrigues(R)[0].ravel(), tvec))
    return poses
