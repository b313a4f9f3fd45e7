"""Marker detection against synthetic frames with exact ground truth, and the real light-marker frame.

`render_markers` and `grid_centres` are imported by the other perception test modules.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.detection import (
    Detections,
    MarkerParams,
    detect_blobs,
    detect_fast,
    drop_crowded_markers,
    estimate_marker_params,
    refine_centres,
    to_gray,
)
from fv_algos.perception import Perception


def grid_centres(rows: int = 16, cols: int = 16, pitch_px: float = 25.0, origin_px: tuple[float, float] = (132.3, 52.7)) -> np.ndarray:
    """(rows*cols, 2) float64 (x, y) px centres of a square marker grid, row-major."""
    ys, xs = np.mgrid[0:rows, 0:cols].astype(np.float64)
    return np.column_stack([origin_px[0] + pitch_px * xs.ravel(), origin_px[1] + pitch_px * ys.ravel()])


def render_markers(
    centres_px: np.ndarray,
    diameter_px: float = 9.0,
    shape: tuple[int, int] = (480, 640),
    background: float = 190.0,
    marker: float = 60.0,
    noise_sigma: float = 0.0,
    supersample: int = 8,
    seed: int = 0,
) -> np.ndarray:
    """(H, W) uint8 frame of discs at exact sub-pixel centres (pixel centres at integers).

    Each pixel is the area-weighted mix of `background` and `marker` grey levels, the disc
    coverage being measured on a supersample x supersample grid of points inside the pixel.
    """
    h, w = shape
    coverage = np.zeros(shape, dtype=np.float32)
    centres = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
    centres = centres[np.all(np.isfinite(centres), axis=1)]
    radius = diameter_px / 2.0
    half = int(np.ceil(radius)) + 1
    offs = np.arange(-half, half + 1)
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    for cx, cy in centres:
        ix, iy = int(round(cx)), int(round(cy))
        px = ix + offs[None, :, None, None] + sub[None, None, None, :] - cx
        py = iy + offs[:, None, None, None] + sub[None, None, :, None] - cy
        cov = ((px * px + py * py) <= radius * radius).mean(axis=(2, 3)).astype(np.float32)
        x0, y0 = ix - half, iy - half
        xa, ya = max(x0, 0), max(y0, 0)
        xb, yb = min(x0 + cov.shape[1], w), min(y0 + cov.shape[0], h)
        if xa >= xb or ya >= yb:
            continue
        patch = cov[ya - y0 : yb - y0, xa - x0 : xb - x0]
        np.maximum(coverage[ya:yb, xa:xb], patch, out=coverage[ya:yb, xa:xb])
    image = background + (marker - background) * coverage
    if noise_sigma > 0.0:
        image = image + np.random.default_rng(seed).normal(0.0, noise_sigma, shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


SIM_MARKER = MarkerParams(diameter_px=9.0, pitch_px=25.0, polarity="dark", contrast=130.0)


def _match_error(found: Detections, truth: np.ndarray) -> tuple[np.ndarray, int]:
    """Distance of each truth centre to its nearest detection (px) and the number of detections."""
    d = np.linalg.norm(found.centres_px[None, :, :] - truth[:, None, :], axis=2)
    return d.min(axis=1), len(found)


def test_fast_detector_is_subpixel_exact_on_clean_frame() -> None:
    truth = grid_centres() + np.random.default_rng(1).uniform(-0.5, 0.5, (256, 2))
    found = detect_fast(render_markers(truth), SIM_MARKER)
    error, count = _match_error(found, truth)
    assert count == 256
    assert np.sqrt(np.mean(error**2)) < 0.03
    assert error.max() < 0.08


def test_fast_detector_with_noise_and_shading() -> None:
    truth = grid_centres() + np.random.default_rng(2).uniform(-0.5, 0.5, (256, 2))
    image = render_markers(truth, noise_sigma=3.0).astype(np.float64)
    ramp = np.linspace(-50.0, 50.0, image.shape[1])[None, :]
    shaded = np.clip(image + ramp, 0, 255).astype(np.uint8)
    found = detect_fast(shaded, SIM_MARKER)
    error, count = _match_error(found, truth)
    assert count == 256
    assert np.sqrt(np.mean(error**2)) < 0.1


def test_blob_detector_finds_every_marker() -> None:
    truth = grid_centres()
    found = detect_blobs(render_markers(truth), SIM_MARKER)
    error, count = _match_error(found, truth)
    assert count == 256
    assert error.max() < 0.5


def test_light_markers_and_bgr_input() -> None:
    truth = grid_centres(8, 8, 40.0, (100.0, 80.0)) + 0.3
    mono = render_markers(truth, diameter_px=12.0, background=70.0, marker=200.0)
    bgr = cv2.merge([mono, mono, mono])
    light = MarkerParams(diameter_px=12.0, pitch_px=40.0, polarity="light", contrast=130.0)
    for image in (mono, bgr):
        error, count = _match_error(detect_fast(image, light), truth)
        assert count == 64
        assert error.max() < 0.08


def test_bgr_becomes_luma_and_a_red_overlay_line_is_no_marker() -> None:
    truth = grid_centres(4, 4, 30.0, (40.0, 40.0))
    mono = render_markers(truth, diameter_px=10.0, shape=(160, 160))
    bgr = cv2.merge([mono, mono, mono])
    np.testing.assert_array_equal(to_gray(bgr), mono)
    cv2.line(bgr, (0, 150), (159, 150), (0, 0, 255), 3)
    found = detect_fast(bgr, MarkerParams(diameter_px=10.0, pitch_px=30.0, contrast=130.0))
    error, count = _match_error(found, truth)
    assert len(found) == count == 16
    assert error.max() < 0.05


def test_red_overlay_inside_markers_of_a_chroma_subsampled_frame_keeps_centres() -> None:
    """Red '+' marks drawn 1 px off every marker centre (as a tracker's overlay), then the
    4:2:0 chroma subsampling of video codecs: the centres stay within 0.02 px."""
    truth = grid_centres(8, 8, 30.0, (60.0, 50.0)) + 0.3
    mono = render_markers(truth, diameter_px=12.0, background=190.0, marker=30.0)
    bgr = cv2.merge([mono, mono, mono])
    for x, y in np.rint(truth).astype(int) + 1:
        cv2.line(bgr, (x - 1, y), (x + 1, y), (0, 0, 255), 1)
        cv2.line(bgr, (x, y - 1), (x, y + 1), (0, 0, 255), 1)
    ycc = cv2.cvtColor(bgr, cv2.COLOR_BGR2YCrCb)
    h, w = mono.shape
    for c in (1, 2):
        half = cv2.resize(ycc[:, :, c], (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        ycc[:, :, c] = cv2.resize(half, (w, h), interpolation=cv2.INTER_LINEAR)
    marker = MarkerParams(diameter_px=12.0, pitch_px=30.0, contrast=160.0)
    found = detect_fast(cv2.cvtColor(ycc, cv2.COLOR_YCrCb2BGR), marker)
    error, count = _match_error(found, truth)
    assert count == 64
    assert error.max() < 0.02


def test_refine_centres_with_a_given_background_matches_the_rim_median() -> None:
    truth = grid_centres(4, 4, 25.0, (40.0, 40.0)) + np.array([0.37, -0.21])
    image = render_markers(truth, shape=(160, 160))
    start = np.rint(truth)
    rim = refine_centres(image, start, SIM_MARKER)
    given = refine_centres(image, start, SIM_MARKER, background=np.full(len(truth), 190.0))
    assert np.abs(rim - truth).max() < 0.03
    assert np.abs(given - rim).max() < 1e-6


def test_estimate_marker_params_recovers_size_pitch_polarity() -> None:
    dark = render_markers(grid_centres(), diameter_px=9.0)
    est = estimate_marker_params(dark)
    assert est.polarity == "dark"
    assert est.diameter_px == pytest.approx(9.0, rel=0.1)
    assert est.pitch_px == pytest.approx(25.0, rel=0.02)
    assert est.contrast == pytest.approx(130.0, abs=15.0)
    light = render_markers(grid_centres(8, 8, 40.0, (100.0, 80.0)), diameter_px=12.0, background=70.0, marker=200.0)
    est = estimate_marker_params(light)
    assert est.polarity == "light"
    assert est.diameter_px == pytest.approx(12.0, rel=0.1)
    assert est.pitch_px == pytest.approx(40.0, rel=0.02)


def test_a_sharp_two_level_pattern_is_estimated() -> None:
    """A drawn dot grid, no blur, no noise: Otsu's threshold on its two levels came out 0, taken as no
    contrast, and no marker was found (blurred or noisy, the same grid worked)."""
    sharp = np.full((240, 320), 200, np.uint8)
    for y in range(15, 240, 30):
        for x in range(15, 320, 30):
            cv2.circle(sharp, (x, y), 4, 30, -1)
    est = estimate_marker_params(sharp)
    assert est.polarity == "dark" and est.pitch_px == pytest.approx(30.0, rel=0.02)
    assert len(Perception().reset(sharp).reference_px) == 80


def test_crowded_blobs_keep_the_one_on_the_lattice() -> None:
    """Clutter blobs 0.39 and 0.3 pitch beside two markers, larger than a marker (so size cannot
    tell them apart): the markers are kept, whose neighbours come in opposite pairs. A lattice with
    no blobs closer than half a pitch comes back whole."""
    grid = grid_centres(16, 16, 25.0)
    clutter = np.array([grid[100] + [9.75 * 0.6, 9.75 * 0.8], grid[150] + [-7.5, 0.0]])
    points = np.vstack([grid[:120], clutter, grid[120:]])
    areas = np.full(len(points), 64.0)
    areas[120:122] = 120.0
    kept = drop_crowded_markers(Detections(points, areas), 0.5 * 25.0)
    assert np.array_equal(kept.centres_px, grid)
    assert np.array_equal(kept.areas_px2, np.full(len(grid), 64.0))
    whole = drop_crowded_markers(Detections(grid, np.full(len(grid), 64.0)), 0.5 * 25.0)
    assert np.array_equal(whole.centres_px, grid)


def test_clutter_beside_a_marker_in_the_reference_does_not_take_its_dot() -> None:
    """Transparent skin: the reference frame shows a clutter blob 0.39 pitch beside marker 16 (as
    on FingerVision video, where one took a marker's identity). The clutter then goes and the skin
    moves every marker 0.39 pitch, marker 16 onto the clutter's spot: left in the reference, the
    clutter took marker 16's dot and both were lost. Left out of it, every marker is tracked."""
    pitch = 40.0
    grid = grid_centres(6, 7, pitch, (40.3, 40.7))
    step = 0.39 * pitch * np.array([0.6, 0.8])
    perception = Perception()
    reference = perception.reset(render_markers(np.vstack([grid, grid[16] + step]), shape=(300, 320)))
    assert len(reference.valid) == len(grid)
    assert np.abs(np.sort(reference.reference_px, axis=0) - np.sort(grid, axis=0)).max() < 0.05
    state, _ = perception.step(render_markers(grid + step, shape=(300, 320)))
    assert state.valid.all()
    assert np.abs(state.displacement_px - step).max() < 0.05


@pytest.mark.parametrize("value", [0, 255])
def test_flat_frames_give_no_detections(value: int) -> None:
    flat = np.full((480, 640), value, dtype=np.uint8)
    assert len(detect_fast(flat, SIM_MARKER)) == 0
    assert len(detect_blobs(flat, SIM_MARKER)) == 0
    with pytest.raises(ValueError, match="consistent marker blobs"):
        estimate_marker_params(flat)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((480, 640), dtype=np.float32), np.zeros((480, 640, 4), dtype=np.uint8), np.zeros((4, 4), dtype=np.uint8)],
)
def test_bad_images_raise(bad: np.ndarray) -> None:
    with pytest.raises(ValueError, match="image"):
        detect_fast(bad, SIM_MARKER)


def test_bad_marker_params_raise() -> None:
    with pytest.raises(ValueError, match="pitch_px"):
        MarkerParams(diameter_px=9.0, pitch_px=5.0)
    with pytest.raises(ValueError, match="polarity"):
        MarkerParams(polarity="grey")  # type: ignore[arg-type]


def test_real_light_markers_all_found(real_data: Path) -> None:
    image = cv2.imread(str(real_data / "gelsight_light_markers_1280x720.png"))
    marker = estimate_marker_params(image)
    assert marker.polarity == "light"
    for detector in (detect_fast, detect_blobs):
        found = detector(image, marker)
        assert len(found) == 64
        xs = np.sort(found.centres_px[:, 0])
        columns = np.diff(xs) > 0.5 * marker.pitch_px
        assert columns.sum() == 7


def test_a_marker_count_below_one_is_refused() -> None:
    """min_markers 0 said "shows 0 consistent marker blobs, need >= 0" of a blank frame."""
    with pytest.raises(ValueError, match="min_markers 0 must be >= 1"):
        estimate_marker_params(np.zeros((60, 80), np.uint8), min_markers=0)
