"""Fisheye chessboard calibration: synthetic views through a known camera are calibrated back."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.calibration import (
    CalibrationParams,
    Chessboard,
    ChessboardRenderer,
    ChessboardRenderParams,
    calibrate_fisheye,
    find_chessboard_corners,
    load_images,
    load_video_frames,
    random_board_poses,
)
from fv_algos.fisheye import FisheyeCamera

# The true camera: off-centre principal point, non-square pixels, fisheye distortion.
TRUE_CAMERA = FisheyeCamera(
    K=np.array([[305.0, 0.0, 326.0], [0.0, 298.0, 235.0], [0.0, 0.0, 1.0]]),
    D=np.array([-0.03, 0.01, -0.002, 0.0]),
    width=640,
    height=480,
)
BOARD = Chessboard()
N_VIEWS = 12


@pytest.fixture(scope="module")
def poses() -> list[tuple[np.ndarray, np.ndarray]]:
    return random_board_poses(TRUE_CAMERA, BOARD, N_VIEWS, distance_range_mm=(18.0, 30.0), max_tilt_deg=40.0, seed=0)


@pytest.fixture(scope="module")
def views(poses: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[str, np.ndarray]]:
    renderer = ChessboardRenderer(TRUE_CAMERA, BOARD, ChessboardRenderParams())
    return [(f"view{i:02d}", renderer.render(rvec, tvec)) for i, (rvec, tvec) in enumerate(poses)]


def true_corners_px(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(M, 2) exact projections of the board's inner corners, px."""
    R, _ = cv2.Rodrigues(rvec)
    return TRUE_CAMERA.project(BOARD.object_points_mm() @ R.T + tvec)


def test_poses_keep_the_board_in_view(poses: list[tuple[np.ndarray, np.ndarray]]) -> None:
    assert len(poses) == N_VIEWS
    for rvec, tvec in poses:
        R, _ = cv2.Rodrigues(rvec)
        outline_px = TRUE_CAMERA.project(BOARD.outline_mm() @ R.T + tvec)
        assert np.all((outline_px >= 10) & (outline_px <= [629, 469]))
        assert np.degrees(np.arccos(abs(R[2, 2]))) <= 40.0 + 1e-9


def test_rendered_corners_are_found_where_they_project(views, poses) -> None:
    for (name, image), (rvec, tvec) in zip(views[:4], poses[:4]):
        found = find_chessboard_corners(image, BOARD)
        assert found is not None, name
        truth = true_corners_px(rvec, tvec)
        # The detector may start from the opposite corner of the board.
        error = min(np.linalg.norm(found - truth, axis=1), np.linalg.norm(found[::-1] - truth, axis=1), key=np.max)
        assert np.sqrt(np.mean(error**2)) < 0.15 and error.max() < 0.3, name


def test_calibration_recovers_the_true_camera(views) -> None:
    result = calibrate_fisheye(views, CalibrationParams(board=BOARD))
    assert result.used == [name for name, _ in views] and result.rejected == {}
    K, K_true = result.camera.K, TRUE_CAMERA.K
    for index in [(0, 0), (1, 1), (0, 2), (1, 2)]:
        assert K[index] == pytest.approx(K_true[index], rel=0.01), index
    assert result.rms_px < 0.3
    assert result.camera.rms_px == result.rms_px and result.camera.date is not None
    assert result.per_view_rms_px.shape == (N_VIEWS,)
    assert np.all(result.per_view_rms_px < 0.3)
    # The per-view errors and the overall RMS describe the same residuals.
    assert np.sqrt(np.mean(result.per_view_rms_px**2)) == pytest.approx(result.rms_px, rel=0.05)


def test_unusable_views_are_rejected_by_name(views) -> None:
    blank = np.full((480, 640), 128, np.uint8)
    small = views[0][1][:240, :320].copy()
    mixed = [("blank.png", blank)] + views[:6] + [("small.png", small)]
    result = calibrate_fisheye(mixed, CalibrationParams(board=BOARD))
    assert result.used == [name for name, _ in views[:6]]
    assert set(result.rejected) == {"blank.png", "small.png"}
    assert "not found" in result.rejected["blank.png"]
    assert "320x240" in result.rejected["small.png"]


def test_too_few_boards_is_a_clear_error(views) -> None:
    blank = np.full((480, 640), 128, np.uint8)
    few = views[:2] + [(f"blank{i}", blank) for i in range(3)]
    with pytest.raises(ValueError, match=r"found in 2 of 5 views, need at least 5.*blank0"):
        calibrate_fisheye(few, CalibrationParams(board=BOARD))
    with pytest.raises(ValueError, match="empty"):
        calibrate_fisheye([], CalibrationParams(board=BOARD))


def test_bad_images_are_refused() -> None:
    with pytest.raises(ValueError, match="uint8"):
        calibrate_fisheye([("a", np.zeros((48, 64), np.float32))], CalibrationParams())
    with pytest.raises(ValueError, match="shape"):
        calibrate_fisheye([("a", np.zeros((48, 64, 4), np.uint8))], CalibrationParams())


def test_load_images_reads_a_folder_sorted_and_mono(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "b.png"), np.full((8, 10, 3), 200, np.uint8))
    cv2.imwrite(str(tmp_path / "a.jpg"), np.full((8, 10), 50, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    loaded = load_images(tmp_path)
    assert [name for name, _ in loaded] == ["a.jpg", "b.png"]
    assert all(image.shape == (8, 10) and image.dtype == np.uint8 for _, image in loaded)
    assert loaded[1][1].mean() == pytest.approx(200, abs=1)


def test_load_images_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        load_images(tmp_path / "missing")
    with pytest.raises(ValueError, match="holds no file"):
        load_images(tmp_path)
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="cannot be decoded"):
        load_images(tmp_path)


def test_load_video_frames_takes_every_kth_frame(tmp_path: Path) -> None:
    path = tmp_path / "board.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48), False)
    for i in range(10):
        writer.write(np.full((48, 64), 20 * i + 10, np.uint8))
    writer.release()
    frames = load_video_frames(path, every_k=3)
    assert [name for name, _ in frames] == ["frame_000000", "frame_000003", "frame_000006", "frame_000009"]
    for (name, image), level in zip(frames, [10, 70, 130, 190]):
        assert image.shape == (48, 64) and abs(image.mean() - level) < 3, name
    with pytest.raises(ValueError, match="every_k"):
        load_video_frames(path, every_k=0)
    with pytest.raises(ValueError, match="cannot be opened"):
        load_video_frames(tmp_path / "missing.avi", every_k=1)


def test_load_video_frames_reads_the_real_fingervision_video(real_data: Path) -> None:
    frames = load_video_frames(real_data / "fingervision_cam1_0002.m4v", every_k=1000)
    assert [name for name, _ in frames] == ["frame_000000", "frame_001000", "frame_002000"]
    assert all(image.shape == (240, 320) for _, image in frames)
