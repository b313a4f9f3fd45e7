"""FisheyeCamera: projection against OpenCV, exact round trips, calibration files, undistortion."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.fisheye import DEFAULT_CAMERA_DISTANCE_MM, FisheyeCamera

# Off-centre principal point, non-square pixels and strong distortion: every term counts.
GENERAL = FisheyeCamera(
    K=np.array([[310.0, 0.0, 331.0], [0.0, 296.0, 228.0], [0.0, 0.0, 1.0]]),
    D=np.array([0.05, -0.02, 0.01, -0.002]),
    width=640,
    height=480,
)


def wide_points(n: int, seed: int) -> np.ndarray:
    """(n, 3) camera-frame points up to 75 deg off the optical axis, mm."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, np.deg2rad(75.0), n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    depth = rng.uniform(5.0, 40.0, n)
    return np.stack([np.tan(theta) * np.cos(phi), np.tan(theta) * np.sin(phi), np.ones(n)], axis=1) * depth[:, None]


@pytest.mark.parametrize("camera", [FisheyeCamera.default(), GENERAL])
def test_project_matches_opencv_fisheye(camera: FisheyeCamera) -> None:
    points = wide_points(500, seed=1)
    reference, _ = cv2.fisheye.projectPoints(
        points[:, None, :], np.zeros(3), np.zeros(3), camera.K, camera.D
    )
    np.testing.assert_allclose(camera.project(points), reference[:, 0], rtol=0, atol=1e-6)


def test_project_without_lens_matches_opencv_pinhole() -> None:
    points = wide_points(200, seed=2)
    reference, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), GENERAL.K, np.zeros(5))
    np.testing.assert_allclose(GENERAL.project(points, lens=False), reference[:, 0], rtol=0, atol=1e-6)


def test_optical_axis_projects_to_principal_point() -> None:
    np.testing.assert_allclose(GENERAL.project(np.array([[0.0, 0.0, 7.0]])), [[331.0, 228.0]], atol=1e-12)


@pytest.mark.parametrize("lens", [True, False])
def test_unproject_to_plane_inverts_project(lens: bool) -> None:
    rng = np.random.default_rng(3)
    distance_mm = 12.5
    xy = rng.uniform(-14.0, 14.0, (400, 2))
    points = np.column_stack([xy, np.full(len(xy), distance_mm)])
    pixels = GENERAL.project(points, lens=lens)
    np.testing.assert_allclose(GENERAL.unproject_to_plane(pixels, distance_mm, lens=lens), xy, rtol=0, atol=1e-6)


def test_pixel_rays_reproject_to_every_pixel() -> None:
    camera = FisheyeCamera.default()
    u, v = np.meshgrid(np.linspace(0, 639, 41), np.linspace(0, 479, 31))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    rays, valid = camera.pixel_rays(pixels)
    assert valid.all()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(camera.project(rays), pixels, rtol=0, atol=1e-6)


def test_pixels_beyond_the_invertible_range_are_flagged() -> None:
    # theta_d = theta (1 - 0.3 theta^2) peaks at theta = 1/sqrt(0.9): theta_d = 0.7027.
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    camera = FisheyeCamera(K=K, D=np.array([-0.3, 0, 0, 0]), width=100, height=100)
    pixels = np.array([[50.0 + 100 * 0.69, 50.0], [50.0 + 100 * 0.72, 50.0]])
    rays, valid = camera.pixel_rays(pixels)
    assert valid.tolist() == [True, False]
    np.testing.assert_array_equal(rays[1], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(camera.project(rays[:1]), pixels[:1], atol=1e-6)
    with pytest.raises(ValueError, match=r"rows \[1\]"):
        camera.unproject_to_plane(pixels, 10.0)


def test_default_camera_frames_the_skin() -> None:
    camera = FisheyeCamera.default()
    half_mm = 12.0
    corners = np.array([[x, y, DEFAULT_CAMERA_DISTANCE_MM] for x in (-half_mm, half_mm) for y in (-half_mm, half_mm)])
    edges = np.array([[0.0, -half_mm, DEFAULT_CAMERA_DISTANCE_MM], [0.0, half_mm, DEFAULT_CAMERA_DISTANCE_MM]])
    corner_px = camera.project(corners)
    assert np.all((corner_px >= 0) & (corner_px <= [camera.width - 1, camera.height - 1]))
    span = np.ptp(camera.project(edges)[:, 1]) / camera.height
    assert 0.7 < span < 1.0


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((3, 2)), r"shape \(N, 3\)"),
        (np.array([[0.0, 0.0, np.nan]]), "non-finite"),
        (np.array([[1.0, 0.0, 5.0], [1.0, 0.0, -1.0]]), r"rows \[1\]"),
    ],
)
def test_project_rejects_bad_points(points: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        GENERAL.project(points)


def test_points_past_the_fold_of_the_distortion_are_refused() -> None:
    """D = [-0.3, 0, 0, 0] folds back at 60.4 deg: a point 70 deg off the axis projected onto the pixel of
    one at 50.25 deg, and that pixel's ray was the 50.25 deg one, valid. Points within the fold still
    project; without the lens every point in front of the camera does."""
    camera = FisheyeCamera(K=GENERAL.K, D=np.array([-0.3, 0.0, 0.0, 0.0]), width=640, height=480)

    def off_axis(deg: float) -> np.ndarray:
        return np.array([[np.tan(np.radians(deg)), 0.0, 1.0]])

    with pytest.raises(ValueError, match=r"rows \[0\] lie 70.0 deg off the axis, at or past 60.4 deg"):
        camera.project(off_axis(70.0))
    rays, valid = camera.pixel_rays(camera.project(off_axis(50.25)))
    assert valid[0] and np.degrees(np.arccos(rays[0, 2])) == pytest.approx(50.25, abs=1e-6)
    assert np.all(np.isfinite(camera.project(off_axis(70.0), lens=False)))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"K": np.eye(2)}, "K"),
        ({"K": np.array([[-1.0, 0, 1], [0, 1, 1], [0, 0, 1]])}, "K"),
        ({"K": np.array([[1.0, 0.1, 1], [0, 1, 1], [0, 0, 1]])}, "skew"),
        ({"D": np.zeros(5)}, "D"),
        ({"D": np.array([np.inf, 0, 0, 0])}, "D"),
        ({"width": 0}, "width"),
        ({"rms_px": -1.0}, "rms_px"),
    ],
)
def test_constructor_names_the_bad_field(kwargs: dict, field: str) -> None:
    values = {"K": GENERAL.K, "D": GENERAL.D, "width": 640, "height": 480} | kwargs
    with pytest.raises(ValueError, match=field):
        FisheyeCamera(**values)


def test_save_load_round_trip(tmp_path: Path) -> None:
    camera = FisheyeCamera(K=GENERAL.K, D=GENERAL.D, width=640, height=480, rms_px=0.12)
    path = tmp_path / "camera.json"
    camera.save(path)
    loaded = FisheyeCamera.load(path)
    np.testing.assert_array_equal(loaded.K, camera.K)
    np.testing.assert_array_equal(loaded.D, camera.D)
    assert (loaded.width, loaded.height, loaded.rms_px) == (640, 480, 0.12)
    assert loaded.date is not None and loaded.date == json.loads(path.read_text())["date"]


def test_save_creates_missing_folders(tmp_path: Path) -> None:
    path = tmp_path / "new" / "deeper" / "camera.json"
    GENERAL.save(path)
    np.testing.assert_array_equal(FisheyeCamera.load(path).K, GENERAL.K)


def test_a_failed_save_leaves_the_old_file_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "camera.json"
    FisheyeCamera.default().save(path)
    before = path.read_text()
    real_write_text = Path.write_text

    def write_half_then_fail(self: Path, text: str) -> int:
        real_write_text(self, text[: len(text) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", write_half_then_fail)
    with pytest.raises(OSError, match="No space"):
        GENERAL.save(path)
    monkeypatch.undo()
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["camera.json"]  # no temporary file left


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda r: r.pop("K"), "'K'"),
        (lambda r: r.update(D=[0.1, 0.2]), "D"),
        (lambda r: r.update(width="640"), "'width'"),
        (lambda r: r.update(height=None), "'height'"),
        (lambda r: r.update(K=[[1, 2], "x"]), "'K'"),
        (lambda r: r.update(rms_px="bad"), "'rms_px'"),
        (lambda r: r.update(D=[[0, 0], [0, 0]]), "'D'"),  # 4 numbers, not k1..k4: taken flattened
        (lambda r: r.update(rms_px=True), "'rms_px'"),  # taken as 1.0
        (lambda r: r.update(rms_px="0.5"), "'rms_px'"),  # a string was converted
        (lambda r: r.update(date=20261127), "'date'"),  # taken as the string '20261127'
    ],
)
def test_load_names_the_bad_field(tmp_path: Path, change, field: str) -> None:
    path = tmp_path / "camera.json"
    GENERAL.save(path)
    record = json.loads(path.read_text())
    change(record)
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match=field):
        FisheyeCamera.load(path)


def test_load_rejects_non_json(tmp_path: Path) -> None:
    path = tmp_path / "camera.json"
    path.write_text("K = 1")
    with pytest.raises(ValueError, match="not valid JSON"):
        FisheyeCamera.load(path)


@pytest.mark.parametrize("balance", [0.0, 1.0])
def test_undistort_maps_send_pinhole_pixels_to_their_fisheye_pixels(balance: float) -> None:
    map1, map2 = GENERAL.undistort_maps(balance)
    assert map1.shape == (480, 640, 2) and map2.shape == (480, 640)
    map_u, map_v = cv2.convertMaps(map1, map2, cv2.CV_32FC1)
    new_K = GENERAL.undistorted_camera_matrix(balance)
    rows, cols = np.mgrid[40:440:37, 40:600:53]
    pinhole = np.column_stack([cols.ravel(), rows.ravel(), np.ones(cols.size)]) @ np.linalg.inv(new_K).T
    expected = GENERAL.project(pinhole)
    inside = np.all((expected >= 0) & (expected <= [639, 479]), axis=1)
    got = np.column_stack([map_u[rows, cols].ravel(), map_v[rows, cols].ravel()])
    # CV_16SC2 maps hold 1/32 px fixed point.
    np.testing.assert_allclose(got[inside], expected[inside], atol=1.0 / 32)


def test_undistort_maps_reject_bad_balance() -> None:
    with pytest.raises(ValueError, match="balance"):
        GENERAL.undistort_maps(1.5)


def test_for_size_refuses_an_empty_frame() -> None:
    """for_size(0, 0) raised a bare ZeroDivisionError."""
    with pytest.raises(ValueError, match="0x0 px: both sides must be >= 1 px"):
        FisheyeCamera.default().for_size(0, 0)
