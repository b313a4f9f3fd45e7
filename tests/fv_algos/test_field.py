"""Displacement field: the precomputed RBF operator against closed forms and scipy's refit."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.field import FieldInterpolator, FieldParams, grid_axes, rbf_operator
from tests.fv_algos.test_detection import grid_centres

REF = grid_centres(16, 16, 25.0) + np.random.default_rng(0).normal(0.0, 1.0, (256, 2))
VALID = np.ones(len(REF), dtype=bool)
KERNELS = ["thin_plate_spline", "multiquadric", "inverse_multiquadric", "gaussian", "linear", "cubic"]


def _smooth(points: np.ndarray) -> np.ndarray:
    """A smooth test displacement field (N, 2) px."""
    c = REF.mean(axis=0)
    return np.column_stack([3.0 * np.sin((points[:, 0] - c[0]) / 60.0), 2.0 * np.cos((points[:, 1] - c[1]) / 80.0)])


def _grid_points(field_x: np.ndarray, field_y: np.ndarray) -> np.ndarray:
    gx, gy = np.meshgrid(field_x, field_y)
    return np.column_stack([gx.ravel(), gy.ravel()])


def test_grid_spans_reference_bounding_box() -> None:
    x, y = grid_axes(REF, (30, 20))
    assert x.shape == (20,) and y.shape == (30,)
    assert x[0] == REF[:, 0].min() and x[-1] == REF[:, 0].max()
    assert y[0] == REF[:, 1].min() and y[-1] == REF[:, 1].max()


@pytest.mark.parametrize("kernel", KERNELS)
def test_affine_motion_is_reproduced_exactly(kernel: str) -> None:
    """Every kernel carries a linear polynomial, so translation + linear strain is exact."""
    a = np.array([[0.02, -0.05], [0.03, 0.01]])
    t = np.array([1.5, -2.0])
    interp = FieldInterpolator(REF, FieldParams(kernel=kernel))  # type: ignore[arg-type]
    out = interp.interpolate(REF + REF @ a.T + t, VALID)
    truth = _grid_points(out.x_px, out.y_px) @ a.T + t
    assert out.valid and out.markers_used == 256
    assert out.field.shape == (30, 30, 3) and out.field.dtype == np.float32
    assert np.abs(out.field[:, :, :2].reshape(-1, 2) - truth).max() < 1e-3
    assert np.allclose(out.field[:, :, 2], np.hypot(out.field[:, :, 0], out.field[:, :, 1]))


@pytest.mark.parametrize("kernel", KERNELS)
def test_operator_equals_scipy_refit(kernel: str) -> None:
    cur = REF + _smooth(REF)
    op = FieldInterpolator(REF, FieldParams(kernel=kernel)).interpolate(cur, VALID)  # type: ignore[arg-type]
    refit = FieldInterpolator(REF, FieldParams(kernel=kernel, method="rbf_refit")).interpolate(cur, VALID)  # type: ignore[arg-type]
    assert np.abs(op.field - refit.field).max() < 1e-4


def test_smooth_field_accuracy_and_griddata_alternative() -> None:
    cur = REF + _smooth(REF)
    out = FieldInterpolator(REF).interpolate(cur, VALID)
    truth = _smooth(_grid_points(out.x_px, out.y_px))
    assert np.abs(out.field[:, :, :2].reshape(-1, 2) - truth).max() < 0.06
    grid = FieldInterpolator(REF, FieldParams(method="griddata")).interpolate(cur, VALID)
    assert grid.valid and np.all(np.isfinite(grid.field))
    assert grid.filled_cells > 0
    inside = np.abs(grid.field[:, :, :2].reshape(-1, 2) - truth)
    assert np.median(inside) < 0.05


@pytest.mark.slow
def test_missing_markers_give_the_exact_interpolant_of_the_valid_ones() -> None:
    cur = REF + _smooth(REF)
    interp = FieldInterpolator(REF, FieldParams(min_valid_share=0.0))  # down to 5 of 256 markers
    rng = np.random.default_rng(3)
    for dropped in (1, len(REF) // 3, len(REF) - 5):  # a new validity pattern every frame
        mask = VALID.copy()
        mask[rng.choice(len(REF), dropped, replace=False)] = False
        out = interp.interpolate(cur, mask)
        assert out.markers_used == int(mask.sum())
        op, _ = rbf_operator(REF[mask], _grid_points(out.x_px, out.y_px), "thin_plate_spline", interp.width_px)
        exact = op @ (cur[mask] - REF[mask])
        assert np.abs(out.field[:, :, :2].reshape(-1, 2) - exact).max() < 1e-4
    mask = VALID.copy()
    mask[::3] = False
    truth = _smooth(_grid_points(interp.x_px, interp.y_px))
    assert np.abs(interp.interpolate(cur, mask).field[:, :, :2].reshape(-1, 2) - truth).max() < 0.2


@pytest.mark.parametrize("kept", [0, 2, 25])
def test_all_or_almost_all_markers_lost(kept: int) -> None:
    mask = np.zeros(len(REF), dtype=bool)
    mask[np.random.default_rng(1).choice(len(REF), kept, replace=False)] = True
    cur = REF + 2.0
    for method in ("rbf_operator", "rbf_refit", "griddata"):
        params = FieldParams(method=method, min_valid_share=0.0)  # type: ignore[arg-type]
        out = FieldInterpolator(REF, params).interpolate(cur, mask)
        assert np.all(np.isfinite(out.field))
        assert out.valid == (kept >= 3)
        if out.valid:
            assert np.abs(out.field[:, :, :2] - 2.0).max() < 1e-3


def test_nan_positions_are_treated_as_missing() -> None:
    cur = REF + 1.0
    cur[:10] = np.nan
    cur[10, 1] = np.inf
    out = FieldInterpolator(REF).interpolate(cur, VALID)
    assert out.valid and out.markers_used == 245
    assert np.abs(out.field[:, :, :2] - 1.0).max() < 1e-3


@pytest.mark.parametrize("kept", [63, 64])
def test_a_small_share_of_valid_markers_gives_an_invalid_field(kept: int) -> None:
    """A noise frame's few chance matches (24 of 256) made a large wrong field flagged valid."""
    mask = np.zeros(len(REF), dtype=bool)
    mask[np.random.default_rng(2).choice(len(REF), kept, replace=False)] = True
    for method in ("rbf_operator", "rbf_refit", "griddata"):
        out = FieldInterpolator(REF, FieldParams(method=method)).interpolate(REF + 2.0, mask)  # type: ignore[arg-type]
        assert out.valid == (kept >= 0.25 * len(REF)) and out.markers_used == kept
        assert np.abs(out.field[:, :, :2] - 2.0 * out.valid).max() < 1e-3
    assert not FieldInterpolator(REF, FieldParams(min_valid_share=0.3)).interpolate(REF + 2.0, mask).valid
    for share in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="min_valid_share"):
            FieldParams(min_valid_share=share)


def test_collinear_markers_give_an_invalid_field() -> None:
    """The linear term needs valid reference points spanning 2-D: rbf_operator's field of exactly
    collinear markers was wrong (a uniform (2, -1) came out as -0.49 .. 2 in x) and flagged valid."""
    lattice = grid_centres(5, 5, 25.0) + 100.0
    shift = np.array([2.0, -1.0])
    line = np.column_stack([np.linspace(0.0, 300.0, 20), np.full(20, 50.0)])
    op, condition = rbf_operator(line, np.array([[10.0, 60.0], [150.0, 40.0]]))
    assert np.all(np.isfinite(op)) and condition > 1e8
    for method in ("rbf_operator", "rbf_refit", "griddata"):
        params = FieldParams(method=method, min_valid_share=0.0)  # type: ignore[arg-type]
        for rows in ([0, 1, 2], [0, 1, 2, 3, 4], [0, 6, 12, 18, 24]):  # a row, a longer row, the diagonal
            mask = np.zeros(25, dtype=bool)
            mask[rows] = True
            out = FieldInterpolator(lattice, params).interpolate(lattice + shift, mask)
            assert not out.valid and not out.field.any(), (method, rows)
        mask[7] = True  # one marker off the diagonal: 2-D again
        out = FieldInterpolator(lattice, params).interpolate(lattice + shift, mask)
        assert out.valid and np.abs(out.field[:, :, :2] - shift).max() < 1e-3
        assert not FieldInterpolator(line, params).interpolate(line + 1.0, np.ones(20, dtype=bool)).valid


@pytest.mark.parametrize("shift", [[1e39, 0.0], [2.5e38, 2.5e38]])
def test_displacements_beyond_float32_give_an_invalid_field(shift: list[float]) -> None:
    """Finite float64 displacements whose component or magnitude overflows float32 gave inf, flagged valid."""
    out = FieldInterpolator(REF).interpolate(REF + shift, VALID)
    assert not out.valid and not out.field.any() and out.markers_used == len(REF)


def test_coincident_or_absurd_reference_markers_are_refused() -> None:
    """Coincident reference points inflated a 2 px shift to 1e5 px (thin-plate spline)."""
    with pytest.raises(ValueError, match=r"markers 0 and 1 \(at 200, 200 px\), 0 and 2 .* coincide"):
        FieldInterpolator(np.full((5, 2), 200.0))
    with pytest.raises(ValueError, match="markers 0 and 256 .* coincide"):
        FieldInterpolator(np.vstack([REF, REF[:1]]), FieldParams(method="rbf_refit"))
    with pytest.raises(ValueError, match="markers 5 and 256 .* coincide"):
        FieldInterpolator(np.vstack([REF, REF[5:6] + 1e-9]))
    with pytest.raises(ValueError, match="beyond"):
        FieldInterpolator(REF * 1e200)
    assert len(FieldInterpolator(np.vstack([REF, REF[:1] + 0.01])).reference_px) == 257  # 0.01 px apart: two markers


@pytest.mark.parametrize("width_px", [1e-3, 1e6])
def test_gaussian_width_extremes_stay_finite(width_px: float) -> None:
    cur = REF + _smooth(REF)
    out = FieldInterpolator(REF, FieldParams(kernel="gaussian", width_px=width_px)).interpolate(cur, VALID)
    assert out.valid and np.all(np.isfinite(out.field))
    assert np.abs(out.field[:, :, :2]).max() < 10.0


def test_no_motion_gives_zero_field() -> None:
    out = FieldInterpolator(REF).interpolate(REF, VALID)
    assert np.abs(out.field).max() < 1e-9


def test_bad_input_raises() -> None:
    with pytest.raises(ValueError, match="kernel"):
        FieldParams(kernel="sinc")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="non-finite"):
        FieldInterpolator(np.array([[np.nan, 0.0], [1.0, 1.0]]))
    with pytest.raises(ValueError, match="current_px"):
        FieldInterpolator(REF).interpolate(REF[:5], VALID)


@pytest.mark.parametrize("method", ["rbf_operator", "rbf_refit"])
def test_a_large_smoothing_tends_to_the_markers_plane_fit_not_to_zero(method: str) -> None:
    """With smoothing 1e8 the operator's pseudo-inverse dropped the polynomial block (its eigenvalues fell below
    rcond x the kernel block's): a uniform shift of 1 px came out as a zero field, flagged valid. A smoothing past
    MAX_SMOOTHING, where the balanced system overflows, is refused."""
    from fv_algos.field import MAX_SMOOTHING
    ref = np.stack(np.meshgrid(np.arange(10) * 25.0 + 30, np.arange(10) * 25.0 + 30), -1).reshape(-1, 2)
    wavy = np.column_stack([np.sin(ref[:, 0] / 40), np.cos(ref[:, 1] / 50)])
    spreads = []
    for smoothing in (1e6, 1e8, MAX_SMOOTHING):
        interpolator = FieldInterpolator(ref, FieldParams(smoothing=smoothing, method=method))
        shifted = interpolator.interpolate(ref + [1.0, 0.0], np.ones(len(ref), bool))
        assert shifted.valid and np.allclose(shifted.field[..., 0], 1.0) and np.allclose(shifted.field[..., 1], 0.0)
        spreads.append(interpolator.interpolate(ref + wavy, np.ones(len(ref), bool)).field[..., 0].std())
    assert np.allclose(spreads, spreads[-1], rtol=1e-2) and spreads[-1] > 0.1  # the plane fit of a wavy field
    with pytest.raises(ValueError, match="smoothing must be in"):
        FieldParams(smoothing=MAX_SMOOTHING * 10)


def test_a_grid_shape_of_no_whole_numbers_is_refused_by_name() -> None:
    """(2.5, 3) passed the check and failed later in numpy ("'float' object cannot be interpreted as an integer")."""
    with pytest.raises(ValueError, match=r"grid_shape must be \(H, W\), whole numbers both >= 2, got \(2.5, 3\)"):
        FieldParams(grid_shape=(2.5, 3))
