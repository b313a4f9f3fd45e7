"""FrameCrop: the part of a frame kept, the resize, the camera matrix that follows them, and
the params it is built from."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.frame_crop import FrameCrop


def test_a_seventh_off_each_border_of_a_448x336_frame_keeps_its_central_320x240() -> None:
    crop = FrameCrop.from_lists([0.142857], [320, 240])
    assert crop.window(448, 336) == (64, 48, 384, 288)
    image = np.random.default_rng(0).integers(0, 255, (336, 448, 3), np.uint8)
    np.testing.assert_array_equal(crop.apply(image), image[48:288, 64:384])


def test_resized_frames_have_the_size_asked_for_in_mono_and_colour() -> None:
    crop = FrameCrop((0.1, 0.2, 0.05, 0.15), (160, 90))
    assert crop.apply(np.zeros((480, 640), np.uint8)).shape == (90, 160)
    assert crop.apply(np.zeros((100, 200, 3), np.uint8)).shape == (90, 160, 3)  # grown, not shrunk


@pytest.mark.parametrize("size", [(300, 200), (900, 700)])
def test_the_camera_matrix_follows_a_point_through_the_crop_and_resize(size: tuple[int, int]) -> None:
    """A blob at (u, v) in the captured frame lies where the new matrix puts the same ray."""
    width, height, (u, v) = 800, 600, (431.3, 287.6)
    K = np.array([[500.0, 0.0, 399.5], [0.0, 510.0, 299.5], [0.0, 0.0, 1.0]])
    yy, xx = np.mgrid[0:height, 0:width]
    image = (255 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 6.0 ** 2))).astype(np.uint8)
    crop = FrameCrop((0.1, 0.05, 0.2, 0.1), size)
    out = crop.apply(image).astype(np.float64)
    oy, ox = np.mgrid[0:out.shape[0], 0:out.shape[1]]
    found = np.array([(ox * out).sum(), (oy * out).sum()]) / out.sum()
    K2, w2, h2 = crop.camera_matrix(K, width, height)
    ray = np.linalg.solve(K, [u, v, 1.0])
    predicted = (K2 @ ray)[:2]
    assert (w2, h2) == size
    np.testing.assert_allclose(found, predicted, atol=0.1)


def test_params_give_no_crop_one_share_for_all_borders_or_four() -> None:
    assert FrameCrop.from_lists([], []) is None
    assert FrameCrop.from_lists([0.25], []) == FrameCrop((0.25,) * 4, None)
    assert FrameCrop.from_lists([], [64, 48]) == FrameCrop((0.0,) * 4, (64, 48))
    assert FrameCrop.from_lists([0.1, 0.2, 0.3, 0.4], []).borders == (0.1, 0.2, 0.3, 0.4)


@pytest.mark.parametrize("crop, size, message", [
    ([0.5], [], "every share must be in"),
    ([-0.1], [], "every share must be in"),
    ([], [320], "must be \\[width, height\\]"),
    ([], [0, 240], "both >= 1"),
    ([], [100000, 100000], "<= 8192"),  # taken: every frame resized to 30 GB
])
def test_bad_params_are_refused_by_name(crop: list, size: list, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FrameCrop.from_lists(crop, size)


def test_a_crop_that_leaves_nothing_of_a_small_frame_is_refused() -> None:
    with pytest.raises(ValueError, match="leaves nothing of a 2x2 frame"):
        FrameCrop((0.49, 0.49, 0.0, 0.0)).window(2, 2)
