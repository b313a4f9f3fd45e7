"""SkinRenderer: sub-pixel marker centres, apparent size, visibility, effects and determinism."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from fv_algos.fisheye import DEFAULT_CAMERA_DISTANCE_MM, FisheyeCamera
from fv_algos.sim.render import EFFECTS, MarkersReachCameraError, RenderParams, SkinRenderer, ellipse_coverage

CAMERA = FisheyeCamera.default()
DISTANCE_MM = DEFAULT_CAMERA_DISTANCE_MM
DIAMETER_MM = 0.5
FLAT = RenderParams(background_unevenness=0.0)


def marker_grid() -> np.ndarray:
    """(256, 3) the default 16 x 16 markers at 1.5 mm pitch, undeformed, skin frame, mm."""
    g = (np.arange(16) - 7.5) * 1.5
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def pressed_grid() -> np.ndarray:
    """The grid under a smooth 2.5 mm press with some shear and jitter, mm."""
    grid = marker_grid()
    r2 = (grid[:, 0] - 1.0) ** 2 + (grid[:, 1] + 2.0) ** 2
    bump = np.exp(-r2 / 40.0)
    jitter = np.random.default_rng(7).normal(0.0, 0.1, (len(grid), 2))
    return grid + np.column_stack([0.4 * bump + jitter[:, 0], -0.3 * bump + jitter[:, 1], 2.5 * bump])


def blob_centroids(image: np.ndarray, level: float, polarity: str) -> np.ndarray:
    """(B, 2) intensity-weighted centroids (u, v) of the connected blobs that differ from `level`."""
    contrast = level - image.astype(np.float64) if polarity == "dark" else image.astype(np.float64) - level
    weight = np.clip(contrast, 0.0, None)
    n, labels = cv2.connectedComponents((weight > 0).astype(np.uint8), connectivity=8)
    v, u = np.mgrid[: image.shape[0], : image.shape[1]]
    total = np.bincount(labels.ravel(), weight.ravel(), n)[1:]
    cu = np.bincount(labels.ravel(), (weight * u).ravel(), n)[1:] / total
    cv = np.bincount(labels.ravel(), (weight * v).ravel(), n)[1:] / total
    return np.column_stack([cu, cv])


def match_errors(truth_px: np.ndarray, found_px: np.ndarray) -> np.ndarray:
    """Distance from each true centre to the nearest found centre, px; requires one-to-one counts."""
    assert len(truth_px) == len(found_px)
    return np.linalg.norm(truth_px[:, None] - found_px[None], axis=2).min(axis=1)


@pytest.mark.parametrize("effects", [frozenset({"lens"}), frozenset()])
@pytest.mark.parametrize("polarity", ["dark", "light"])
def test_true_centres_match_blob_centroids(effects: frozenset[str], polarity: str) -> None:
    params = RenderParams(polarity=polarity, background_unevenness=0.0)
    result = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, effects, seed=0).render(pressed_grid())
    visible = result.markers_px[result.visible]
    assert result.visible.sum() >= 200
    found = blob_centroids(result.image, params.background_level, polarity)
    assert match_errors(visible, found).max() < 0.1


def test_centroids_stay_accurate_on_an_uneven_background() -> None:
    renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, RenderParams(), frozenset({"lens"}), seed=3)
    result = renderer.render(pressed_grid())
    contrast = renderer.background.astype(np.float64) - result.image
    # Rounding to uint8 against a non-integer background leaves +-0.5 everywhere; keep the markers.
    found = blob_centroids(np.where(contrast > 1.0, 255.0 - contrast, 255.0), 255.0, "dark")
    assert match_errors(result.markers_px[result.visible], found).max() < 0.1


def test_pinhole_size_and_position_follow_the_closed_form() -> None:
    # Without the lens: u = cx + f x / (d - z), radius = f (D / 2) / (d - z).
    markers = np.array([[0.0, 0.0, 0.0], [3.0, -1.5, 0.0], [-3.0, -1.5, 2.0], [-4.5, 6.0, 4.0]])
    result = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, FLAT, frozenset(), seed=0).render(markers)
    depth = DISTANCE_MM - markers[:, 2]
    f, cx, cy = CAMERA.K[0, 0], CAMERA.K[0, 2], CAMERA.K[1, 2]
    expected_px = np.column_stack([cx + f * markers[:, 0] / depth, cy + f * markers[:, 1] / depth])
    np.testing.assert_allclose(result.markers_px, expected_px, atol=1e-9)
    np.testing.assert_allclose(result.radius_px, f * DIAMETER_MM / 2 / depth, rtol=1e-6)
    coverage = (FLAT.light_level - result.image.astype(np.float64)) / (FLAT.light_level - FLAT.dark_level)
    n, labels = cv2.connectedComponents((coverage > 0).astype(np.uint8))
    areas = np.bincount(labels.ravel(), coverage.ravel(), n)[1:]
    np.testing.assert_allclose(np.sort(areas), np.sort(np.pi * result.radius_px**2), rtol=0.02)


def test_pressing_makes_markers_bigger_and_moves_them_outward_through_the_lens() -> None:
    markers = np.array([[4.5, 3.0, 0.0], [4.5, 3.0, 2.0]])
    result = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, FLAT, frozenset({"lens"}), seed=0).render(markers)
    centre = CAMERA.K[:2, 2]
    assert result.radius_px[1] > result.radius_px[0] * 1.05
    assert np.linalg.norm(result.markers_px[1] - centre) > np.linalg.norm(result.markers_px[0] - centre) + 5.0
    in_camera_mm = np.column_stack([markers[:, :2], DISTANCE_MM - markers[:, 2]])
    np.testing.assert_allclose(result.markers_px, CAMERA.project(in_camera_mm), atol=1e-12)


def test_markers_outside_the_image_are_not_visible() -> None:
    markers = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 11.8, 0.0]])
    # Pinhole: v = 239.5 + 300 * 11.8 / 15 = 475.5, within a radius (5 px) of the bottom edge.
    result = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, FLAT, frozenset(), seed=0).render(markers)
    assert result.visible.tolist() == [True, False, False]
    assert np.all(np.isfinite(result.markers_px))


def test_missing_markers_are_absent_from_the_image() -> None:
    params = RenderParams(background_unevenness=0.0, missing_probability=0.3)
    renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset({"lens", "missing"}), seed=5)
    result = renderer.render(marker_grid())
    missing = ~result.visible
    assert 40 < missing.sum() < 120
    found = blob_centroids(result.image, params.light_level, "dark")
    assert match_errors(result.markers_px[result.visible], found).max() < 0.1
    u, v = np.rint(result.markers_px[missing]).astype(int).T
    assert np.all(result.image[v, u] == params.light_level)


def test_occluder_hides_markers_and_spares_the_visible_ones() -> None:
    params = RenderParams(
        background_unevenness=0.0, occlusion_probability=1.0, occluder_radius_px=(60.0, 60.0), occluder_speed_px=(25.0, 25.0)
    )
    markers = marker_grid()
    clean = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset({"lens"}), seed=2).render(markers).image
    n, labels = cv2.connectedComponents((clean < params.light_level).astype(np.uint8), connectivity=8)
    renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset({"lens", "occlusion"}), seed=2)
    hidden_counts = []
    for _ in range(40):
        result = renderer.render(markers)
        hidden = ~result.visible
        hidden_counts.append(int(hidden.sum()))
        u, v = np.rint(result.markers_px).astype(int).T
        # Every pixel of a visible marker's blob is untouched by the occluder.
        untouched = np.isin(labels, labels[v[result.visible], u[result.visible]])
        np.testing.assert_array_equal(result.image[untouched], clean[untouched])
        # A hidden marker has the occluder within a few pixels of its blob.
        occluder = (result.image == params.occluder_level).astype(np.uint8)
        near_occluder = cv2.dilate(occluder, np.ones((5, 5), np.uint8)) > 0
        for k in np.flatnonzero(hidden):
            assert np.any(near_occluder[labels == labels[v[k], u[k]]])
    assert max(hidden_counts) > 5


def test_same_seed_gives_identical_frames_and_another_seed_does_not() -> None:
    params = RenderParams(occlusion_probability=0.2, missing_probability=0.05)
    markers = pressed_grid()

    def frames(seed: int) -> list[np.ndarray]:
        renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, EFFECTS, seed=seed)
        return [renderer.render(markers) for _ in range(6)]

    first, again, other = frames(11), frames(11), frames(12)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.visible, b.visible)
    assert not np.array_equal(first[0].image, other[0].image)


def test_noise_has_the_requested_std() -> None:
    params = RenderParams(blur_sigma_px=0.0, noise_std=3.0)
    markers = marker_grid()
    clean = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset({"lens"}), seed=4).render(markers)
    noisy_renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset({"lens", "noise"}), seed=4)
    first = noisy_renderer.render(markers).image.astype(np.float64)
    second = noisy_renderer.render(markers).image.astype(np.float64)
    residual = first - clean.image
    # Rounding a noisy value adds variance 1/12 on top of the clean frame's own rounding.
    assert abs(residual.std() - np.sqrt(9.0 + 1.0 / 6.0)) < 0.15
    assert abs(residual.mean()) < 0.05
    assert not np.array_equal(first, second)


def test_lighting_changes_brightness_over_time_and_darkens_the_corners() -> None:
    params = RenderParams(background_unevenness=0.0, exposure_amplitude=0.2, exposure_period_frames=40.0, vignetting=0.3)
    renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset({"lighting"}), seed=1)
    means = [renderer.render(np.empty((0, 3))).image.mean() for _ in range(40)]
    # A full exposure period: the mean swings by about +-20% around its average.
    assert np.ptp(means) > 0.3 * np.mean(means)
    frame = renderer.render(np.empty((0, 3))).image.astype(np.float64)
    assert frame[:20, :20].mean() < 0.85 * frame[230:250, 310:330].mean()
    unlit = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, params, frozenset(), seed=1)
    assert np.all(unlit.render(np.empty((0, 3))).image == params.light_level)


def test_ellipse_coverage_integrates_to_the_ellipse_area() -> None:
    axes = np.array([[[6.0, 1.0], [0.5, 3.0]]])
    coverage, origin = ellipse_coverage(np.array([[20.3, 17.8]]), axes, 9)
    assert coverage.shape == (1, 19, 19)
    np.testing.assert_array_equal(origin, [[11, 8]])
    assert coverage.sum() == pytest.approx(np.pi * abs(np.linalg.det(axes[0])), rel=0.01)


@pytest.mark.parametrize(
    ("markers", "message"),
    [
        (np.zeros((4, 2)), r"shape \(N, 3\)"),
        (np.array([[0.0, np.nan, 0.0]]), "non-finite"),
        (np.array([[0.0, 0.0, 0.0], [0.0, 0.0, DISTANCE_MM]]), r"rows \[1\]"),
    ],
)
def test_render_rejects_bad_markers(markers: np.ndarray, message: str) -> None:
    renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, FLAT, frozenset(), seed=0)
    with pytest.raises(ValueError, match=message):
        renderer.render(markers)


def test_markers_at_the_camera_are_counted_not_all_listed() -> None:
    """A heavy press listed all 256 row indices in its message."""
    renderer = SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, FLAT, frozenset(), seed=0)
    markers = marker_grid()
    markers[10:, 2] = DISTANCE_MM + 1.0
    with pytest.raises(MarkersReachCameraError, match=r"^markers_skin_mm rows \[10, 11, 12, 13, 14, \.\.\. \(246 in all\)\] "
                                                      r"reach the camera \(z >= 15.0 mm\)$") as caught:
        renderer.render(markers)
    np.testing.assert_array_equal(caught.value.rows, np.arange(10, 256))


def test_bad_configuration_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown effects"):
        SkinRenderer(CAMERA, DISTANCE_MM, DIAMETER_MM, FLAT, frozenset({"lens", "rain"}), seed=0)
    with pytest.raises(ValueError, match="camera_distance_mm"):
        SkinRenderer(CAMERA, -1.0, DIAMETER_MM, FLAT, frozenset(), seed=0)
    with pytest.raises(ValueError, match="polarity"):
        RenderParams(polarity="grey")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="occluder_radius_px"):
        RenderParams(occluder_radius_px=(5.0, 1.0))
