"""Contact summary against fields with closed-form area, shear, rotation and divergence."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.contact_summary import ContactParams, summarise_contact
from fv_algos.field import DisplacementField

X = np.linspace(0.0, 290.0, 30)
Y = np.linspace(0.0, 290.0, 30)
GX, GY = np.meshgrid(X, Y)


def _field(dx: np.ndarray, dy: np.ndarray, valid: bool = True) -> DisplacementField:
    data = np.stack([dx, dy, np.hypot(dx, dy)], axis=2).astype(np.float32)
    return DisplacementField(data, X, Y, valid, 256)


def test_no_motion_is_no_contact() -> None:
    s = summarise_contact(_field(np.zeros((30, 30)), np.zeros((30, 30))))
    assert not s.in_contact and s.area_px2 == 0.0 and s.area_share == 0.0
    assert np.allclose(s.centre_px, [145.0, 145.0])
    assert np.all(np.isfinite(s.shear_px)) and s.rotation_rad == 0.0 and s.divergence == 0.0


def test_uniform_shear_patch_area_centre_and_shear() -> None:
    patch = (GX >= 100) & (GX <= 190) & (GY >= 50) & (GY <= 110)
    s = summarise_contact(_field(np.where(patch, 3.0, 0.0), np.where(patch, -4.0, 0.0)))
    cells = int(patch.sum())
    assert s.in_contact
    assert s.area_px2 == pytest.approx(cells * 100.0)
    assert s.area_share == pytest.approx(cells / 900.0)
    assert np.allclose(s.centre_px, [145.0, 80.0])
    assert np.allclose(s.shear_px, [3.0, -4.0], atol=1e-6)


def test_rigid_rotation_and_expansion() -> None:
    theta = 0.02
    cx, cy = GX - 145.0, GY - 145.0
    rot = summarise_contact(
        _field((np.cos(theta) - 1) * cx - np.sin(theta) * cy, np.sin(theta) * cx + (np.cos(theta) - 1) * cy),
        ContactParams(threshold_px=0.0),
    )
    assert rot.rotation_rad == pytest.approx(np.sin(theta), rel=1e-4)
    assert abs(rot.divergence) < 1e-3
    grow = summarise_contact(_field(0.01 * cx, 0.01 * cy), ContactParams(threshold_px=0.0))
    assert grow.divergence == pytest.approx(0.02, rel=1e-4)
    assert abs(grow.rotation_rad) < 1e-6


def test_invalid_field_gives_neutral_summary() -> None:
    s = summarise_contact(_field(np.ones((30, 30)), np.ones((30, 30)), valid=False))
    assert not s.in_contact and s.area_px2 == 0.0
    with pytest.raises(ValueError, match="threshold_px"):
        ContactParams(threshold_px=float("nan"))
