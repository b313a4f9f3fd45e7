"""A few numbers that summarise a displacement field: contact area and centre, shear, twist, press.

Beyond the paper. Works on a `DisplacementField` (grid in reference px); derivatives are
central differences on the grid (np.gradient with the grid's px spacing).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fv_algos.field import DisplacementField


@dataclass(frozen=True)
class ContactParams:
    """threshold_px: a grid cell is in contact when its displacement magnitude exceeds this."""

    threshold_px: float = 1.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.threshold_px) and self.threshold_px >= 0.0):
            raise ValueError(f"ContactParams.threshold_px must be finite >= 0, got {self.threshold_px}")


@dataclass(frozen=True)
class ContactSummary:
    """Summary of one field; every number is finite.

    in_contact: any cell above the threshold (and the field valid). area_px2: contact area
    in reference px^2 (cells x cell area). area_share: contact cells / all cells.
    centre_px: (2,) magnitude-weighted centre (x, y) of the contact cells, the grid centre
    when there is no contact. shear_px: (2,) mean (dx, dy) over the contact cells (whole
    grid when no contact). rotation_rad: half the mean curl over the same cells, sin of the
    rigid rotation angle, positive when clockwise on screen (x right, y down). divergence: mean divergence over the same cells (dimensionless; > 0 when
    the skin spreads out, the normal-press index).
    """

    in_contact: bool
    area_px2: float
    area_share: float
    centre_px: np.ndarray
    shear_px: np.ndarray
    rotation_rad: float
    divergence: float


def summarise_contact(field: DisplacementField, params: ContactParams = ContactParams()) -> ContactSummary:
    """`ContactSummary` of `field` (an invalid field gives a no-contact, all-zero summary)."""
    h, w, _ = field.field.shape
    centre = np.array([field.x_px.mean(), field.y_px.mean()])
    if not field.valid:
        return ContactSummary(False, 0.0, 0.0, centre, np.zeros(2), 0.0, 0.0)
    dx = field.field[:, :, 0].astype(np.float64)
    dy = field.field[:, :, 1].astype(np.float64)
    magnitude = field.field[:, :, 2].astype(np.float64)
    step_x = float(field.x_px[1] - field.x_px[0])
    step_y = float(field.y_px[1] - field.y_px[0])
    ddx_dy, ddx_dx = np.gradient(dx, step_y, step_x)
    ddy_dy, ddy_dx = np.gradient(dy, step_y, step_x)
    curl = ddy_dx - ddx_dy
    divergence = ddx_dx + ddy_dy
    contact = magnitude > params.threshold_px
    count = int(contact.sum())
    region = contact if count > 0 else np.ones_like(contact)
    if count > 0:
        gx, gy = np.meshgrid(field.x_px, field.y_px)
        weights = magnitude * contact
        centre = np.array([(gx * weights).sum(), (gy * weights).sum()]) / weights.sum()
    return ContactSummary(
        in_contact=count > 0,
        area_px2=float(count * abs(step_x * step_y)),
        area_share=count / float(h * w),
        centre_px=centre,
        shear_px=np.array([dx[region].mean(), dy[region].mean()]),
        rotation_rad=float(0.5 * curl[region].mean()),
        divergence=float(divergence[region].mean()),
    )
