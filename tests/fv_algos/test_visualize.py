"""Pictures of the pipeline: sizes, arrows where the displacement is, colour scale, the
slip chart and its history, and no crash on NaN, inf or empty inputs."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos import visualize as viz


def _grid_markers(n: int = 6, step_px: float = 20.0, origin_px: float = 20.0) -> np.ndarray:
    xs, ys = np.meshgrid(origin_px + step_px * np.arange(n), origin_px + step_px * np.arange(n))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def _arrow_mask(img: np.ndarray) -> np.ndarray:
    """Pixels drawn in the marker-arrow colour."""
    return np.all(np.abs(img.astype(int) - np.array(viz.ARROW)) < 40, axis=2)


def test_as_bgr_converts_grey_and_rgb() -> None:
    grey = np.full((4, 5), 7, np.uint8)
    assert viz.as_bgr(grey).shape == (4, 5, 3) and (viz.as_bgr(grey) == 7).all()
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB
    assert (viz.as_bgr(rgb, "rgb8")[..., 2] == 200).all() and (viz.as_bgr(rgb)[..., 0] == 200).all()
    with pytest.raises(ValueError, match="uint8"):
        viz.as_bgr(np.zeros((2, 2), np.float32))


def test_marker_arrow_is_drawn_where_the_marker_moved() -> None:
    image = np.full((160, 160), 128, np.uint8)
    ref = _grid_markers()
    cur = ref.copy()
    cur[14] += (4.0, 0.0)  # marker at (60, 60) moves 4 px right: a 20 px arrow at scale 5
    out = viz.draw_markers(image, ref, cur, arrow_scale=5.0, legend=False)
    assert out.shape == (160, 160, 3) and out.dtype == np.uint8
    mask = _arrow_mask(out)
    ys, xs = np.nonzero(mask)
    assert mask.sum() > 10
    assert xs.min() >= 58 and xs.max() <= 82 and ys.min() >= 54 and ys.max() <= 66
    assert mask[:, 68:76].sum() > 0  # along the arrow, not just at its ends
    assert image.max() == image.min() == 128  # the input is left alone


def test_markers_zoom_lost_markers_and_legend() -> None:
    image = np.full((50, 80, 3), 90, np.uint8)
    ref = _grid_markers(2)
    valid = np.array([True, False, True, True])
    out = viz.draw_markers(image, ref, ref + 1.0, valid, zoom=2.0)
    assert out.shape == (100, 160, 3)
    lost = np.all(np.abs(out.astype(int) - np.array(viz.LOST)) < 40, axis=2)
    assert lost[36:46, 76:86].any()  # the lost marker at (41, 21) px, zoomed x2
    assert (out[-20:].mean() < out[:20].mean())  # the legend band darkens the bottom edge


def test_draw_markers_survives_bad_input() -> None:
    image = np.zeros((40, 40), np.uint8)
    ref = np.array([[10, 10], [np.nan, 5], [20, 20], [1e30, -1e30]])
    cur = np.array([[np.inf, 10], [12, 5], [21, np.nan], [3, 3]])
    out = viz.draw_markers(image, ref, cur)
    assert out.shape == (40, 40, 3)
    assert viz.draw_markers(image, np.zeros((0, 2)), np.zeros((0, 2))).shape == (40, 40, 3)
    assert viz.draw_markers(np.zeros((0, 0), np.uint8), ref, cur).shape == (240, 320, 3)
    with pytest.raises(ValueError, match="markers"):
        viz.draw_markers(image, ref, cur[:2])


def _bump_field(n: int = 30, peak_px: float = 3.0) -> np.ndarray:
    """A Gaussian displacement bump pointing +x, centred in the right half of the grid."""
    yy, xx = np.mgrid[0:n, 0:n]
    mag = peak_px * np.exp(-((xx - 0.75 * n) ** 2 + (yy - n / 2) ** 2) / (2 * (n / 10) ** 2))
    return np.stack([mag, np.zeros_like(mag), mag], axis=-1).astype(np.float32)


def test_field_colour_map_is_bright_where_the_displacement_is() -> None:
    field = _bump_field()
    out = viz.render_field(field, np.linspace(0, 290, 30), np.linspace(0, 290, 30), height_px=316)
    assert out.dtype == np.uint8 and out.shape[0] == 316
    map_px = 300  # the square map inside the 8 px padding
    brightness = out[8:8 + map_px, 8:8 + map_px].astype(float).sum(axis=2)
    centre_row = brightness[map_px // 2]
    assert centre_row[int(0.75 * map_px) + 5] > centre_row[int(0.2 * map_px)] + 200  # viridis: yellow vs purple
    assert out.shape[1] > map_px + 40  # the colour bar with its labels


def test_field_arrows_point_along_the_displacement() -> None:
    field = np.zeros((10, 10, 3), np.float32)
    field[..., 1] = 2.0  # every cell moves 2 px down; magnitude 0 keeps the map black
    out = viz.render_field(field, height_px=216, arrow_step=5, range_px=2.0, colormap=viz.cv2.COLORMAP_BONE)
    white = np.all(out[8:208, 8:208] > 150, axis=2)  # the map is 200 px, cells 20 px, arrows every 5 cells
    ys, xs = np.nonzero(white)
    assert set(np.unique(xs // 10)) <= {4, 5, 14, 15}  # at the columns of cells 2 and 7 only...
    assert np.ptp(ys[xs < 100]) > 150  # ...as vertical strokes through both rows of arrows


def test_field_range_aspect_and_bad_values() -> None:
    assert viz.field_range_px(np.array([0.1, np.nan, 0.2])) == 1.0  # noise stays dark
    assert viz.field_range_px(np.array([[3.5, np.inf]])) == 3.5
    wide = viz.render_field(np.zeros((10, 20, 3)), np.linspace(0, 190, 20), np.linspace(0, 90, 10), height_px=116)
    assert wide.shape[1] > 2 * 100  # the map is twice as wide as tall
    bad = _bump_field(12)
    bad[3, 3] = np.nan
    bad[5, 5] = np.inf
    bad[6, 6, :2] = 1e30
    assert viz.render_field(bad, height_px=100).shape[0] == 100
    assert viz.render_field(np.full((5, 5, 3), np.nan), valid=False, height_px=100).shape[0] == 100
    assert viz.render_field(np.zeros((0, 0, 3)), height_px=80, width_px=90).shape == (80, 90, 3)
    assert viz.render_field(np.ones((1, 1, 3)), np.zeros(1), np.zeros(1), height_px=80).shape[0] == 80
    assert viz.render_field(bad, height_px=100, width_px=300).shape == (100, 300, 3)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        viz.render_field(np.zeros((5, 5)))


def test_slip_history_keeps_the_window_and_restarts_on_a_jump_back() -> None:
    h = viz.SlipHistory(window_s=2.0)
    for k in range(50):
        h.add(k * 0.1, k / 50, k > 40)
    t, p, s = h.arrays()
    assert t[0] >= 4.9 - 2.0 - 1e-9 and t[-1] == pytest.approx(4.9) and len(h) == 21
    assert s[-1] and not s[0] and p[-1] == pytest.approx(49 / 50)
    h.add(0.0, 0.5, False)  # a bag played again
    assert h.samples() == [(0.0, 0.5, False)]
    with pytest.raises(ValueError):
        viz.SlipHistory(0.0)


def test_slip_strip_draws_the_curve_and_shades_slip() -> None:
    t = np.linspace(-9.9, 0, 100)
    p = np.where(t > -3, 0.9, 0.1)
    out = viz.render_slip_strip(t, p, p > 0.5, width_px=400, height_px=160, window_s=10.0)
    assert out.shape == (160, 400, 3)
    curve = np.all(np.abs(out.astype(int) - np.array(viz.CURVE)) < 40, axis=2)
    assert curve.sum() > 200
    shade = np.all(out == np.array(viz.SLIP_FILL), axis=2)
    cols = np.nonzero(shade.any(axis=0))[0]
    assert cols.min() > 0.6 * 400 and cols.max() > 0.9 * 400  # only the last ~3 s of 10


def test_slip_strip_survives_bad_input() -> None:
    empty = viz.render_slip_strip(np.zeros(0), np.zeros(0), width_px=200, height_px=100)
    assert empty.shape == (100, 200, 3)
    t = np.array([0.0, 1.0, np.nan, 3.0, 4.0])
    p = np.array([0.2, np.nan, 0.5, np.inf, 0.7])
    assert viz.render_slip_strip(t, p, width_px=200, height_px=100).shape == (100, 200, 3)
    assert viz.render_slip_strip(t, p, width_px=20, height_px=20).shape == (20, 20, 3)
    with pytest.raises(ValueError, match="samples"):
        viz.render_slip_strip(t, p[:2])


def test_layout_helpers() -> None:
    a = np.full((10, 20, 3), 255, np.uint8)
    b = np.zeros((30, 5, 3), np.uint8)
    assert viz.hstack([a, b], gap_px=2).shape == (30, 27, 3)
    assert viz.vstack([a, b], gap_px=2).shape == (42, 20, 3)
    fitted = viz.fit(a, 40, 40)
    assert fitted.shape == (40, 40, 3) and (fitted[15:25, :] == 255).all() and (fitted[0] != 255).any()
    assert viz.titled(a, "x").shape == (34, 20, 3)
    assert viz.notice_panel("nothing", 50, 60).shape == (50, 60, 3)
