"""Render camera frames of the marker skin as seen by the fisheye camera.

A frame is: a light (or dark), slightly uneven skin background; each marker drawn as the
image of a disc of the printed diameter, anti-aliased with sub-pixel accurate centres;
then, by effect, a passing occluder, illumination change, blur and sensor noise.

Skin coordinates (as in `fv_algos.sim.skin`): x right, y down in the skin plane, origin at
the skin centre, z normal to the skin, positive toward the camera, mm. The camera looks at
the skin from below: skin point (x, y, z) is at camera point (x, y, camera_distance_mm - z).

Effects (the `effects` set of `SkinRenderer`; an effect not listed is not computed at all):
    "lens":      fisheye distortion (without it, the pinhole part K of the camera only);
    "lighting":  vignetting, an illumination gradient that turns over time, exposure drift;
    "noise":     optical blur and additive Gaussian sensor noise;
    "occlusion": now and then a dark blob passes across the image, hiding markers;
    "missing":   each marker drops out of single frames at random.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from fv_algos.fisheye import FisheyeCamera

EFFECTS: frozenset[str] = frozenset({"lens", "lighting", "noise", "occlusion", "missing"})
"""All effect names `SkinRenderer` knows."""

_JACOBIAN_STEP_MM = 1e-3
_NOISE_PAD_PX = 16
_ROWS_NAMED = 5  # rows a MarkersReachCameraError names; it counts the rest


class MarkersReachCameraError(ValueError):
    """Markers at or behind the camera, which cannot be imaged.

    Attributes:
        rows: (K,) int64 indices of those markers in the `markers_skin_mm` given to `SkinRenderer.render`.
    """

    def __init__(self, rows: np.ndarray, camera_distance_mm: float) -> None:
        self.rows = rows
        named = ", ".join(str(row) for row in rows[:_ROWS_NAMED])
        more = f", ... ({len(rows)} in all)" if len(rows) > _ROWS_NAMED else ""
        super().__init__(f"markers_skin_mm rows [{named}{more}] reach the camera (z >= {camera_distance_mm} mm)")


@dataclass(frozen=True)
class RenderParams:
    """Appearance of the rendered frames. Grey levels are 0..255.

    Attributes:
        polarity: "dark" markers on a light background, or "light" markers on a dark one.
        light_level: grey level of the light surface (background, or markers if "light").
        dark_level: grey level of the dark surface (markers, or background if "light").
        background_unevenness: standard deviation of the smooth background texture, grey levels.
        background_scale_px: correlation length of that texture, px.
        edge_margin_px: a marker counts as visible only if its disc plus this margin lies
            inside the image, px.
        blur_sigma_px: Gaussian blur sigma ("noise" effect), px.
        noise_std: additive Gaussian sensor noise ("noise" effect), grey levels.
        noise_bank_size: pre-generated noise frames that the per-frame noise is cut from.
        vignetting: relative brightness loss at the image corners ("lighting" effect).
        gradient_amplitude: relative brightness change from the image centre to the left or
            right edge, of an illumination gradient whose direction turns ("lighting").
        gradient_period_frames: frames per full turn of that gradient.
        exposure_amplitude: relative amplitude of the exposure drift ("lighting").
        exposure_period_frames: period of the exposure drift, frames.
        occlusion_probability: chance per frame that an occluder starts crossing the image
            while none is ("occlusion" effect).
        occluder_radius_px: (min, max) radius of an occluder, px.
        occluder_speed_px: (min, max) speed of an occluder, px per frame.
        occluder_level: grey level of an occluder.
        missing_probability: chance per marker and frame that it is not drawn ("missing").
    """

    polarity: Literal["dark", "light"] = "dark"
    light_level: float = 210.0
    dark_level: float = 35.0
    background_unevenness: float = 6.0
    background_scale_px: float = 80.0
    edge_margin_px: float = 1.0
    blur_sigma_px: float = 0.7
    noise_std: float = 2.0
    noise_bank_size: int = 4
    vignetting: float = 0.3
    gradient_amplitude: float = 0.15
    gradient_period_frames: float = 900.0
    exposure_amplitude: float = 0.15
    exposure_period_frames: float = 300.0
    occlusion_probability: float = 0.01
    occluder_radius_px: tuple[float, float] = (30.0, 80.0)
    occluder_speed_px: tuple[float, float] = (4.0, 12.0)
    occluder_level: float = 15.0
    missing_probability: float = 0.002

    def __post_init__(self) -> None:
        if self.polarity not in ("dark", "light"):
            raise ValueError(f"polarity must be 'dark' or 'light', got {self.polarity!r}")
        for name in ("light_level", "dark_level", "occluder_level"):
            if not 0.0 <= getattr(self, name) <= 255.0:
                raise ValueError(f"{name} must be in [0, 255], got {getattr(self, name)}")
        for name in ("background_unevenness", "edge_margin_px", "blur_sigma_px", "noise_std", "vignetting",
                     "gradient_amplitude", "exposure_amplitude"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        for name in ("background_scale_px", "gradient_period_frames", "exposure_period_frames"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value}")
        if self.noise_bank_size < 1:
            raise ValueError(f"noise_bank_size must be >= 1, got {self.noise_bank_size}")
        if self.vignetting >= 1 or self.exposure_amplitude >= 1 or self.gradient_amplitude >= 1:
            raise ValueError("vignetting, exposure_amplitude and gradient_amplitude must be < 1")
        for name in ("occlusion_probability", "missing_probability"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("occluder_radius_px", "occluder_speed_px"):
            low, high = getattr(self, name)
            if not 0 < low <= high:
                raise ValueError(f"{name} must be (min, max) with 0 < min <= max, got {(low, high)}")

    @property
    def background_level(self) -> float:
        """Grey level of the skin background."""
        return self.light_level if self.polarity == "dark" else self.dark_level

    @property
    def marker_level(self) -> float:
        """Grey level of the markers."""
        return self.dark_level if self.polarity == "dark" else self.light_level


@dataclass(eq=False)
class RenderResult:
    """One rendered frame and its ground truth.

    Attributes:
        image: (H, W) uint8 mono frame.
        markers_px: (N, 2) float64 true image centres (u, v) of the markers, px (also for
            markers that are not visible).
        visible: (N,) bool, False for a marker that is missing, occluded, or whose disc is
            not entirely inside the image.
        radius_px: (N,) float64 apparent radius of each marker (radius of the disc of the
            same area as its image), px.
    """

    image: np.ndarray
    markers_px: np.ndarray
    visible: np.ndarray
    radius_px: np.ndarray


@dataclass(frozen=True)
class _FrameDraws:
    """The random draws of one frame (None: its effect is off).

    Attributes:
        drawn: (N,) bool markers not dropped out ("missing").
        occluder: (centre (2,) px, radius px) of the occluder in the frame, or None when none is ("occlusion").
        noise_cut: (bank frame, u offset px, v offset px) of the sensor noise ("noise").
    """

    drawn: np.ndarray | None
    occluder: tuple[np.ndarray, float] | None
    noise_cut: tuple[int, int, int] | None


def ellipse_coverage(centres_px: np.ndarray, axes_px: np.ndarray, half_window: int) -> tuple[np.ndarray, np.ndarray]:
    """Anti-aliased coverage of filled ellipses on square pixel windows.

    Ellipse k is {c_k + A_k p : |p| <= 1}. Coverage is 0.5 minus the first-order signed
    distance of each pixel centre to the outline, clipped to [0, 1], which keeps the
    centroid of the coverage within a few hundredths of a pixel of c_k.

    Args:
        centres_px: (N, 2) ellipse centres (u, v), px.
        axes_px: (N, 2, 2) matrices A_k mapping the unit disc onto the ellipse, px.
        half_window: the windows are (2 half_window + 1) pixels square.
    Returns:
        coverage: (N, w, w) float64 in [0, 1], indexed [k, row, column].
        origin: (N, 2) int64 (u, v) pixel of window element [k, 0, 0].
    """
    inverse = np.linalg.inv(axes_px)
    origin = np.floor(centres_px).astype(np.int64) - half_window
    offsets = np.arange(2 * half_window + 1, dtype=np.float64)
    du = (origin[:, 0:1] - centres_px[:, 0:1] + offsets)[:, None, :]
    dv = (origin[:, 1:2] - centres_px[:, 1:2] + offsets)[:, :, None]
    m = inverse[:, :, :, None, None]
    pu = m[:, 0, 0] * du + m[:, 0, 1] * dv
    pv = m[:, 1, 0] * du + m[:, 1, 1] * dv
    norm = np.maximum(np.hypot(pu, pv), 1e-12)
    # Gradient of |A^-1 d| with respect to d is A^-T p / |p|.
    gu = (m[:, 0, 0] * pu + m[:, 1, 0] * pv) / norm
    gv = (m[:, 0, 1] * pu + m[:, 1, 1] * pv) / norm
    signed_distance = (norm - 1.0) / np.hypot(gu, gv)
    return np.clip(0.5 - signed_distance, 0.0, 1.0), origin


class SkinRenderer:
    """Renders marker frames; holds the precomputed background, noise and lighting maps.

    Each call to `render` (or `skip`) is the next frame in time (exposure drift, turning gradient,
    occluders moving); a renderer built with the same arguments and fed the same markers
    returns identical frames.

    Attributes:
        background: (H, W) float32 read-only skin background (grey levels) before markers
            and effects; the same for every effect set with the same seed.
    """

    def __init__(
        self,
        camera: FisheyeCamera,
        camera_distance_mm: float,
        marker_diameter_mm: float,
        params: RenderParams,
        effects: frozenset[str],
        seed: int,
    ) -> None:
        """
        Args:
            camera: the camera model (its image size is the frame size).
            camera_distance_mm: distance from the camera centre to the undeformed skin, mm.
            marker_diameter_mm: printed marker diameter, mm.
            params: appearance parameters.
            effects: subset of EFFECTS to simulate.
            seed: seed of all randomness (background texture, noise, occluders, dropouts).
        """
        unknown = set(effects) - EFFECTS
        if unknown:
            raise ValueError(f"unknown effects {sorted(unknown)}; known: {sorted(EFFECTS)}")
        if not (np.isfinite(camera_distance_mm) and camera_distance_mm > 0):
            raise ValueError(f"camera_distance_mm must be a finite number > 0, got {camera_distance_mm}")
        if not (np.isfinite(marker_diameter_mm) and marker_diameter_mm > 0):
            raise ValueError(f"marker_diameter_mm must be a finite number > 0, got {marker_diameter_mm}")
        self.camera = camera
        self.camera_distance_mm = float(camera_distance_mm)
        self.marker_diameter_mm = float(marker_diameter_mm)
        self.params = params
        self.effects = frozenset(effects)
        self._rng = np.random.default_rng(seed)
        self._frame_index = 0
        self._occluder: tuple[np.ndarray, np.ndarray, float] | None = None
        h, w = camera.height, camera.width
        self.background = self._make_background()
        self._frame = np.empty((h, w), dtype=np.float32)
        if "lighting" in self.effects:
            self._phases = self._rng.uniform(0.0, 2.0 * np.pi, size=2)
            self._light_maps = self._make_light_maps()
            self._light = np.empty((h, w), dtype=np.float32)
        if "noise" in self.effects:
            bank_shape = (params.noise_bank_size, h + 2 * _NOISE_PAD_PX, w + 2 * _NOISE_PAD_PX)
            self._noise_bank = self._rng.standard_normal(bank_shape, dtype=np.float32) * np.float32(params.noise_std)

    @property
    def frame_index(self) -> int:
        """Number of frames rendered so far."""
        return self._frame_index

    def _make_background(self) -> np.ndarray:
        """(H, W) float32 skin background: the base level plus a smooth random texture."""
        h, w = self.camera.height, self.camera.width
        p = self.params
        coarse_shape = (int(np.ceil(h / p.background_scale_px)) + 2, int(np.ceil(w / p.background_scale_px)) + 2)
        coarse = self._rng.standard_normal(coarse_shape).astype(np.float32)
        texture = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        texture *= np.float32(p.background_unevenness / max(float(texture.std()), 1e-6))
        background = texture + np.float32(p.background_level)
        background.setflags(write=False)
        return background

    def _make_light_maps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vignetting map V and the gradient bases V*x, V*y ((H, W) float32 each).

        x, y are pixel offsets from the image centre divided by half the image width.
        """
        h, w = self.camera.height, self.camera.width
        half_w = w / 2.0
        x = ((np.arange(w, dtype=np.float32) - (w - 1) / 2.0) / half_w)[None, :]
        y = ((np.arange(h, dtype=np.float32) - (h - 1) / 2.0) / half_w)[:, None]
        corner_sq = ((w - 1) / 2.0) ** 2 / half_w**2 + ((h - 1) / 2.0) ** 2 / half_w**2
        vignette = (1.0 - self.params.vignetting * (x * x + y * y) / corner_sq).astype(np.float32)
        return vignette, vignette * x, vignette * y

    def _project_discs(self, markers_skin_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image centres (N, 2) px and disc-to-ellipse matrices (N, 2, 2) px of the markers."""
        n = len(markers_skin_mm)
        cam = np.empty((5, n, 3))
        cam[:] = markers_skin_mm
        cam[..., 2] = self.camera_distance_mm - cam[..., 2]
        cam[1, :, 0] += _JACOBIAN_STEP_MM
        cam[2, :, 0] -= _JACOBIAN_STEP_MM
        cam[3, :, 1] += _JACOBIAN_STEP_MM
        cam[4, :, 1] -= _JACOBIAN_STEP_MM
        px = self.camera.project(cam.reshape(-1, 3), lens="lens" in self.effects).reshape(5, n, 2)
        jacobian = np.stack([px[1] - px[2], px[3] - px[4]], axis=2) / (2.0 * _JACOBIAN_STEP_MM)
        return px[0], jacobian * (self.marker_diameter_mm / 2.0)

    def _paint(self, coverage: np.ndarray, origin: np.ndarray, level: float) -> None:
        """Blend `level` into the frame with the given window coverages (see ellipse_coverage)."""
        h, w = self._frame.shape
        size = coverage.shape[1]
        cols = origin[:, 0:1] + np.arange(size)
        rows = origin[:, 1:2] + np.arange(size)
        inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
        mask = inside & (coverage > 0)
        flat = (rows[:, :, None] * w + cols[:, None, :])[mask]
        alpha = coverage[mask].astype(np.float32)
        frame = self._frame.reshape(-1)
        frame[flat] += alpha * (np.float32(level) - frame[flat])

    def _paint_disc(self, centre_px: np.ndarray, radius_px: float, level: float) -> None:
        """Blend `level` into the frame over an anti-aliased disc (the part inside the image)."""
        h, w = self._frame.shape
        u0, v0 = np.maximum(np.floor(centre_px - radius_px - 1.0).astype(int), 0)
        u1, v1 = np.minimum(np.ceil(centre_px + radius_px + 2.0).astype(int), [w, h])
        if u0 >= u1 or v0 >= v1:
            return
        du = (np.arange(u0, u1, dtype=np.float32) - np.float32(centre_px[0]))[None, :]
        dv = (np.arange(v0, v1, dtype=np.float32) - np.float32(centre_px[1]))[:, None]
        alpha = np.clip(np.float32(radius_px + 0.5) - np.sqrt(du * du + dv * dv), 0.0, 1.0)
        patch = self._frame[v0:v1, u0:u1]
        patch += alpha * (np.float32(level) - patch)

    def _step_occluder(self) -> tuple[np.ndarray, float] | None:
        """Advance (or start) the passing occluder; return its (centre px, radius px) or None."""
        p = self.params
        h, w = self._frame.shape
        if self._occluder is None:
            if self._rng.random() >= p.occlusion_probability:
                return None
            radius = self._rng.uniform(*p.occluder_radius_px)
            side_angle = self._rng.uniform(0.0, 2.0 * np.pi)
            half_diag = np.hypot(w, h) / 2.0 + radius
            centre = np.array([w / 2.0, h / 2.0]) + half_diag * np.array([np.cos(side_angle), np.sin(side_angle)])
            target = np.array([self._rng.uniform(0.25, 0.75) * w, self._rng.uniform(0.25, 0.75) * h])
            direction = (target - centre) / np.linalg.norm(target - centre)
            self._occluder = (centre, direction * self._rng.uniform(*p.occluder_speed_px), radius)
        centre, velocity, radius = self._occluder
        centre = centre + velocity
        self._occluder = (centre, velocity, radius)
        outside_u = centre[0] + radius < 0 or centre[0] - radius > w - 1
        outside_v = centre[1] + radius < 0 or centre[1] - radius > h - 1
        moving_away = np.dot(velocity, np.array([w / 2.0, h / 2.0]) - centre) < 0
        if (outside_u or outside_v) and moving_away:
            self._occluder = None
            return None
        return centre, radius

    def _apply_lighting(self) -> None:
        """Multiply the frame by this frame's illumination map."""
        p = self.params
        t = self._frame_index
        exposure = 1.0 + p.exposure_amplitude * np.sin(2.0 * np.pi * t / p.exposure_period_frames + self._phases[0])
        turn = 2.0 * np.pi * t / p.gradient_period_frames + self._phases[1]
        gu = exposure * p.gradient_amplitude * np.cos(turn)
        gv = exposure * p.gradient_amplitude * np.sin(turn)
        vignette, vignette_x, vignette_y = self._light_maps
        cv2.addWeighted(vignette_x, gu, vignette_y, gv, 0.0, dst=self._light)
        cv2.scaleAdd(vignette, exposure, self._light, dst=self._light)
        cv2.multiply(self._frame, self._light, dst=self._frame)

    def _apply_noise(self, cut: tuple[int, int, int]) -> None:
        """Blur the frame and add sensor noise cut from the noise bank: `cut` is (bank frame, u offset px,
        v offset px), drawn by `_draw`."""
        h, w = self._frame.shape
        if self.params.blur_sigma_px > 0:
            cv2.GaussianBlur(self._frame, (0, 0), self.params.blur_sigma_px, dst=self._frame)
        k, du, dv = cut
        cv2.add(self._frame, self._noise_bank[k, dv:dv + h, du:du + w], dst=self._frame)

    def _draw(self, n_markers: int) -> _FrameDraws:
        """This frame's randomness, by effect, in one fixed order: what `render` and `skip` both take, so
        that a skipped frame leaves the renderer where rendering it would."""
        drawn = self._rng.random(n_markers) >= self.params.missing_probability if "missing" in self.effects else None
        occluder = self._step_occluder() if "occlusion" in self.effects else None
        cut = None
        if "noise" in self.effects:
            k = int(self._rng.integers(len(self._noise_bank)))
            du, dv = (int(d) for d in self._rng.integers(0, 2 * _NOISE_PAD_PX + 1, size=2))
            cut = (k, du, dv)
        return _FrameDraws(drawn, occluder, cut)

    def skip(self, n_markers: int) -> None:
        """Pass over the next frame without rendering it: the renderer then renders the frame after it as
        if it had rendered this one (the same randomness drawn, occluders moved, lighting advanced).

        Args:
            n_markers: the markers the frame would have had (the per-marker dropouts draw one number each).
        """
        self._draw(n_markers)
        self._frame_index += 1

    def render(self, markers_skin_mm: np.ndarray) -> RenderResult:
        """Render the next frame.

        Args:
            markers_skin_mm: (N, 3) deformed marker positions in skin coordinates, mm, with
                z < camera_distance_mm.
        Returns:
            The frame and its ground truth (see RenderResult); the image is a new array.
        Raises:
            ValueError: wrong shape or non-finite values.
            MarkersReachCameraError: a marker at or behind the camera.
        """
        markers = np.asarray(markers_skin_mm, dtype=np.float64)
        if markers.ndim != 2 or markers.shape[1] != 3:
            raise ValueError(f"markers_skin_mm must have shape (N, 3), got {markers.shape}")
        if not np.all(np.isfinite(markers)):
            raise ValueError("markers_skin_mm contains non-finite values")
        behind = markers[:, 2] >= self.camera_distance_mm
        if np.any(behind):
            raise MarkersReachCameraError(np.flatnonzero(behind), self.camera_distance_mm)
        p = self.params
        h, w = self._frame.shape
        centres, axes = self._project_discs(markers)
        singular = np.linalg.svd(axes, compute_uv=False)
        extent = singular[:, 0] + p.edge_margin_px
        visible = (
            (centres[:, 0] - extent >= 0) & (centres[:, 0] + extent <= w - 1)
            & (centres[:, 1] - extent >= 0) & (centres[:, 1] + extent <= h - 1)
        )
        draws = self._draw(len(markers))
        drawn = np.ones(len(markers), dtype=bool) if draws.drawn is None else draws.drawn
        visible &= drawn
        np.copyto(self._frame, self.background)
        if np.any(drawn):
            half_window = int(np.ceil(singular[drawn, 0].max())) + 1
            coverage, origin = ellipse_coverage(centres[drawn], axes[drawn], half_window)
            self._paint(coverage, origin, p.marker_level)
        if draws.occluder is not None:
            centre, radius = draws.occluder
            visible &= np.hypot(*(centres - centre).T) > radius + extent
            self._paint_disc(centre, radius, p.occluder_level)
        if "lighting" in self.effects:
            self._apply_lighting()
        if draws.noise_cut is not None:
            self._apply_noise(draws.noise_cut)
        np.clip(self._frame, 0.0, 255.0, out=self._frame)
        np.rint(self._frame, out=self._frame)
        self._frame_index += 1
        return RenderResult(
            image=self._frame.astype(np.uint8),
            markers_px=centres,
            visible=visible,
            radius_px=np.sqrt(singular[:, 0] * singular[:, 1]),
        )
