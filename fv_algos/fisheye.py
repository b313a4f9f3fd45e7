"""The fisheye camera model (OpenCV `cv2.fisheye` convention) with projection, unprojection,
undistortion maps and a JSON calibration file.

Camera frame: x right, y down, z forward along the optical axis, in mm. Pixel coordinates
follow OpenCV: the centre of pixel (row i, column j) is at (u, v) = (j, i).

Model (Kannala-Brandt, as in `cv2.fisheye`): for a camera-frame point (X, Y, Z),
a = X/Z, b = Y/Z, r = sqrt(a^2 + b^2), theta = atan(r),
theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
(x', y') = (theta_d / r) (a, b), and [u, v, 1]^T = K [x', y', 1]^T.
Without the lens distortion (`lens=False`) the pinhole part alone is used:
[u, v, 1]^T = K [a, b, 1]^T.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from fv_algos.atomic_file import write_atomically
from fv_algos.frame_crop import FrameCrop

DEFAULT_CAMERA_DISTANCE_MM = 15.0
"""Distance from the camera centre to the undeformed skin plane of the default sensor, mm."""

ASPECT_TOLERANCE = 0.01
"""Relative difference of width / height taken as the same aspect ratio (`FisheyeCamera.for_size`)."""

_NEWTON_ITERATIONS = 30
_NEWTON_TOLERANCE = 1e-12


def _as_points(points: np.ndarray, n_cols: int, name: str) -> np.ndarray:
    """Validate an (N, n_cols) array of finite numbers and return it as float64."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != n_cols:
        raise ValueError(f"{name} must have shape (N, {n_cols}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def utc_timestamp() -> str:
    """The current UTC time as ISO-8601 with seconds, the `date` format of calibration files."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _json_int(value: object) -> int:
    """An integer read from JSON; refuses floats, strings, booleans and null."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"expected an integer, got {value!r}")
    return value


def _json_coefficients(value: object) -> np.ndarray:
    """(4,) float64 k1..k4 read from JSON: a list of 4 numbers, or OpenCV's 4x1 column of them."""
    D = np.array(value, dtype=np.float64)
    if D.shape not in ((4,), (4, 1)):
        raise ValueError(f"expected 4 coefficients k1..k4 as a list (or a 4x1 column), got {value!r}")
    return D.reshape(4)


def _json_optional(kind: type | tuple[type, ...], what: str, value: object) -> object:
    """`value` read from JSON when it is null or of `kind` (a bool is no number); ValueError naming
    `what` was expected otherwise."""
    if value is None or (isinstance(value, kind) and not isinstance(value, bool)):
        return value
    raise ValueError(f"expected {what} or null, got {value!r}")


@dataclass(frozen=True, eq=False)
class FisheyeCamera:
    """A calibrated fisheye camera.

    Attributes:
        K: (3, 3) float64 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in px (no
            skew: `cv2.fisheye` undistortion ignores it; calibrate with CALIB_FIX_SKEW).
        D: (4,) float64 fisheye distortion coefficients k1..k4 (dimensionless).
        width: image width, px.
        height: image height, px.
        rms_px: reprojection RMS of the calibration that produced it, px (None if unknown).
        date: ISO-8601 date of that calibration (None if unknown).
    """

    K: np.ndarray
    D: np.ndarray
    width: int
    height: int
    rms_px: float | None = None
    date: str | None = None

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        D = np.array(self.D, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
            raise ValueError(
                f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (no skew: OpenCV's fisheye "
                f"undistortion ignores it), got {K.tolist()}"
            )
        if D.shape != (4,) or not np.all(np.isfinite(D)):
            raise ValueError(f"D must hold 4 finite coefficients k1..k4, got shape {D.shape}")
        if int(self.width) != self.width or int(self.height) != self.height or self.width <= 0 or self.height <= 0:
            raise ValueError(f"width and height must be positive integers, got {self.width}x{self.height}")
        if self.rms_px is not None and not (np.isfinite(self.rms_px) and self.rms_px >= 0):
            raise ValueError(f"rms_px must be a finite number >= 0 or None, got {self.rms_px}")
        K.setflags(write=False)
        D.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.rms_px is not None:
            object.__setattr__(self, "rms_px", float(self.rms_px))

    @classmethod
    def default(cls) -> "FisheyeCamera":
        """A 640x480 FingerVision-like wide-angle camera (about 157 deg across the diagonal).

        With the skin plane at DEFAULT_CAMERA_DISTANCE_MM, a 24 mm square skin spans about
        400 px, i.e. about 83% of the image height.
        """
        K = np.array([[300.0, 0.0, 319.5], [0.0, 300.0, 239.5], [0.0, 0.0, 1.0]])
        D = np.array([-0.03, 0.01, -0.002, 0.0])
        return cls(K=K, D=D, width=640, height=480)

    @property
    def size(self) -> tuple[int, int]:
        """Image size (width, height) in px, the order OpenCV expects."""
        return (self.width, self.height)

    @cached_property
    def _theta_max(self) -> float:
        """Largest ray angle (rad, <= pi) up to which theta_d(theta) strictly increases."""
        k1, k2, k3, k4 = self.D
        # d theta_d / d theta as a polynomial in s = theta^2, highest power first.
        roots = np.roots([9 * k4, 7 * k3, 5 * k2, 3 * k1, 1.0])
        positive = [r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0]
        return float(min([np.pi] + [np.sqrt(s) for s in positive]))

    def _distort(self, theta: np.ndarray) -> np.ndarray:
        """theta_d for ray angles theta (any shape, rad)."""
        k1, k2, k3, k4 = self.D
        t2 = theta * theta
        return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _distort_derivative(self, theta: np.ndarray) -> np.ndarray:
        """d theta_d / d theta for ray angles theta (any shape, rad)."""
        k1, k2, k3, k4 = self.D
        t2 = theta * theta
        return 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))

    def project(self, points_cam_mm: np.ndarray, lens: bool = True) -> np.ndarray:
        """Project camera-frame points to pixels.

        Args:
            points_cam_mm: (N, 3) points in the camera frame, mm, with z > 0.
            lens: apply the fisheye distortion; False projects with the pinhole part K only.
        Returns:
            (N, 2) float64 pixel coordinates (u, v).
        Raises:
            ValueError: wrong shape, non-finite values, a point with z <= 0, or (with the lens) a
                point at or past the ray angle where the distortion polynomial folds back
                (`_theta_max`): its pixel would be that of a ray nearer the axis.
        """
        pts = _as_points(points_cam_mm, 3, "points_cam_mm")
        z = pts[:, 2]
        if np.any(z <= 0):
            rows = np.flatnonzero(z <= 0).tolist()
            raise ValueError(f"points_cam_mm must lie in front of the camera (z > 0); rows {rows} do not")
        ab = pts[:, :2] / z[:, None]
        if lens:
            r = np.hypot(ab[:, 0], ab[:, 1])
            theta = np.arctan(r)
            folded = theta >= self._theta_max
            if folded.any():
                rows, worst_deg = np.flatnonzero(folded)[:10].tolist(), np.degrees(theta[folded].max())
                raise ValueError(
                    f"points_cam_mm rows {rows} lie {worst_deg:.1f} deg off the axis, at or past "
                    f"{np.degrees(self._theta_max):.1f} deg where this camera's distortion D {self.D.tolist()} "
                    "folds back (their pixels would be those of rays nearer the axis)")
            scale = np.ones_like(r)
            nonzero = r > 0
            scale[nonzero] = self._distort(theta[nonzero]) / r[nonzero]
            ab = ab * scale[:, None]
        K = self.K
        u = K[0, 0] * ab[:, 0] + K[0, 2]
        v = K[1, 1] * ab[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)

    def pixel_rays(self, points_px: np.ndarray, lens: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Unit viewing rays through pixels (the inverse of `project` up to scale).

        Args:
            points_px: (N, 2) pixel coordinates (u, v).
            lens: invert the fisheye distortion; False inverts the pinhole part K only.
        Returns:
            rays: (N, 3) float64 unit vectors in the camera frame; (0, 0, 1) where invalid.
            valid: (N,) bool, False where the pixel lies beyond the range in which the
                distortion polynomial is invertible (no ray maps to it).
        """
        pts = _as_points(points_px, 2, "points_px")
        K = self.K
        yd = (pts[:, 1] - K[1, 2]) / K[1, 1]
        xd = (pts[:, 0] - K[0, 2]) / K[0, 0]
        if not lens:
            rays = np.stack([xd, yd, np.ones_like(xd)], axis=1)
            return rays / np.linalg.norm(rays, axis=1, keepdims=True), np.ones(len(pts), dtype=bool)
        theta_d = np.hypot(xd, yd)
        theta_max = self._theta_max
        theta = np.minimum(theta_d, theta_max)
        for _ in range(_NEWTON_ITERATIONS):
            step = (self._distort(theta) - theta_d) / np.maximum(self._distort_derivative(theta), 1e-12)
            theta = np.clip(theta - step, 0.0, theta_max)
            if np.all(np.abs(step) < _NEWTON_TOLERANCE):
                break
        valid = (np.abs(self._distort(theta) - theta_d) < 1e-9) & (theta < theta_max)
        scale = np.ones_like(theta_d)
        nonzero = theta_d > 0
        scale[nonzero] = np.sin(theta[nonzero]) / theta_d[nonzero]
        rays = np.stack([xd * scale, yd * scale, np.cos(theta)], axis=1)
        rays[~valid] = (0.0, 0.0, 1.0)
        return rays, valid

    def unproject_to_plane(self, points_px: np.ndarray, distance_mm: float, lens: bool = True) -> np.ndarray:
        """Intersect pixel rays with the plane z_cam = distance_mm.

        Args:
            points_px: (N, 2) pixel coordinates (u, v).
            distance_mm: plane distance in front of the camera, mm (> 0).
            lens: invert the fisheye distortion; False inverts the pinhole part K only.
        Returns:
            (N, 2) float64 (x, y) of the intersections in the camera frame, mm.
        Raises:
            ValueError: distance_mm <= 0, or a pixel whose ray does not meet the plane.
        """
        if not (np.isfinite(distance_mm) and distance_mm > 0):
            raise ValueError(f"distance_mm must be a finite number > 0, got {distance_mm}")
        rays, valid = self.pixel_rays(points_px, lens=lens)
        hits = valid & (rays[:, 2] > 1e-9)
        if not np.all(hits):
            rows = np.flatnonzero(~hits).tolist()
            raise ValueError(f"points_px rows {rows} have rays that never meet the plane z = {distance_mm} mm")
        return rays[:, :2] * (distance_mm / rays[:, 2:3])

    def undistorted_camera_matrix(self, balance: float = 0.0) -> np.ndarray:
        """(3, 3) float64 pinhole camera matrix of the undistorted image made by `undistort_maps`.

        Args:
            balance: 0 keeps only valid pixels (crops), 1 keeps the whole field of view.
        """
        if not 0.0 <= balance <= 1.0:
            raise ValueError(f"balance must be in [0, 1], got {balance}")
        return cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            self.K, self.D, self.size, np.eye(3), balance=balance
        )

    def for_size(self, width: int, height: int) -> FisheyeCamera:
        """This camera (calibrated on its own width x height frames) for frames of width x height px:
        itself when the sizes match, else its matrix and RMS scaled to the new resolution (the
        distortion acts on normalised coordinates and stays).

        Raises:
            ValueError: a size below 1 px, or the aspect ratios differ (another camera, or a cropped mode);
                both sizes named.
        """
        if self.size == (width, height):
            return self
        if min(width, height) < 1:
            raise ValueError(f"frames of {width}x{height} px: both sides must be >= 1 px")
        if abs(width * self.height / (height * self.width) - 1.0) > ASPECT_TOLERANCE:
            raise ValueError(
                f"calibration for {self.width}x{self.height} frames does not fit the source's {width}x{height} "
                "frames (another aspect ratio: another camera or a cropped mode); calibrate at this size"
            )
        K, _, _ = FrameCrop(size=(width, height)).camera_matrix(self.K, self.width, self.height)
        rms_px = None if self.rms_px is None else self.rms_px * width / self.width
        return replace(self, K=K, width=width, height=height, rms_px=rms_px)

    def undistort_maps(self, balance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Maps for `cv2.remap(image, map1, map2, cv2.INTER_LINEAR)` that undistort a frame.

        Args:
            balance: 0 keeps only valid pixels (crops), 1 keeps the whole field of view.
        Returns:
            map1: (H, W, 2) int16 fixed-point pixel coordinates; map2: (H, W) uint16
            interpolation table indices (OpenCV CV_16SC2 format). The undistorted image
            has the camera matrix `undistorted_camera_matrix(balance)`.
        """
        new_K = self.undistorted_camera_matrix(balance)
        return cv2.fisheye.initUndistortRectifyMap(self.K, self.D, np.eye(3), new_K, self.size, cv2.CV_16SC2)

    def save(self, path: str | Path) -> None:
        """Write the calibration as JSON: K, D, width, height, rms_px, date.

        `date` is the stored one, or the current UTC time when none is stored. Missing folders
        are created; the file is written beside its place and renamed into it, so that a reader
        (or a failed write) never leaves half a file.
        """
        record = {
            "K": self.K.tolist(),
            "D": self.D.tolist(),
            "width": self.width,
            "height": self.height,
            "rms_px": self.rms_px,
            "date": self.date if self.date is not None else utc_timestamp(),
        }
        text = json.dumps(record, indent=2) + "\n"
        write_atomically(Path(path), lambda tmp: tmp.write_text(text))

    @classmethod
    def load(cls, path: str | Path) -> "FisheyeCamera":
        """Read a calibration written by `save`.

        Raises:
            ValueError: the file is not JSON, or a field is missing or malformed (named).
        """
        path = Path(path)
        try:
            record = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"calibration file {path} is not valid JSON: {exc}") from exc
        if not isinstance(record, dict):
            raise ValueError(f"calibration file {path} must hold a JSON object")
        for field in ("K", "D", "width", "height"):
            if field not in record:
                raise ValueError(f"calibration file {path} lacks the field '{field}'")
        fields = {
            "K": lambda v: np.array(v, dtype=np.float64),
            "D": _json_coefficients,
            "width": _json_int,
            "height": _json_int,
            "rms_px": lambda v: _json_optional((int, float), "a number", v),
            "date": lambda v: _json_optional(str, "a string", v),
        }
        values = {}
        for field, convert in fields.items():
            try:
                values[field] = convert(record.get(field))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"calibration file {path}: field '{field}' is malformed: {exc}") from exc
        try:
            return cls(**values)
        except ValueError as exc:
            raise ValueError(f"calibration file {path}: {exc}") from exc
