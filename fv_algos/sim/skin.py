"""The sensor skin: elastomer material and the printed marker array.

Skin coordinates (used throughout `fv_algos.sim`): x right, y down in the skin plane,
origin at the skin centre, z normal to the skin and POSITIVE TOWARD THE CAMERA (an
indenter pushes markers toward the camera). All lengths in mm, moduli in MPa (N/mm^2).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _shore_a_to_youngs_mpa(shore_a: float) -> float:
    """Gent's relation between Shore A hardness and Young's modulus, MPa.

    A. N. Gent, "On the relation between indentation hardness and Young's modulus",
    Rubber Chem. Technol. 31 (1958): E = 0.0981 (56 + 7.62336 S) / (0.137505 (254 - 2.54 S)).
    Shore 15A gives 0.56 MPa.
    """
    return 0.0981 * (56.0 + 7.62336 * shore_a) / (0.137505 * (254.0 - 2.54 * shore_a))


SHORE_15A_YOUNGS_MPA: float = round(_shore_a_to_youngs_mpa(15.0), 3)


@dataclass(frozen=True)
class Elastomer:
    """Linear-elastic, nearly incompressible skin material.

    Attributes:
        youngs_modulus_mpa: Young's modulus E, MPa. Default 0.563 MPa: Shore 15A silicone
            through Gent's relation (see `_shore_a_to_youngs_mpa`).
        poisson_ratio: Poisson's ratio nu; silicone rubbers are nearly incompressible (0.49).
    """

    youngs_modulus_mpa: float = SHORE_15A_YOUNGS_MPA
    poisson_ratio: float = 0.49

    def __post_init__(self) -> None:
        if not (np.isfinite(self.youngs_modulus_mpa) and self.youngs_modulus_mpa > 0):
            raise ValueError(f"youngs_modulus_mpa must be finite and > 0, got {self.youngs_modulus_mpa}")
        if not (0.0 <= self.poisson_ratio < 0.5):
            raise ValueError(f"poisson_ratio must be in [0, 0.5), got {self.poisson_ratio}")

    @property
    def shear_modulus_mpa(self) -> float:
        """Shear modulus G = E / (2 (1 + nu)), MPa."""
        return self.youngs_modulus_mpa / (2.0 * (1.0 + self.poisson_ratio))

    def contact_modulus_mpa(self, other_youngs_mpa: float, other_poisson: float = 0.3) -> float:
        """Hertz contact modulus E* = 1 / ((1 - nu1^2)/E1 + (1 - nu2^2)/E2), MPa.

        Args:
            other_youngs_mpa: Young's modulus of the indenting object, MPa (np.inf for rigid).
            other_poisson: Poisson's ratio of the object.
        """
        if not (other_youngs_mpa > 0):
            raise ValueError(f"other_youngs_mpa must be > 0, got {other_youngs_mpa}")
        compliance = (1.0 - self.poisson_ratio**2) / self.youngs_modulus_mpa
        compliance += (1.0 - other_poisson**2) / other_youngs_mpa
        return 1.0 / compliance


@dataclass(frozen=True)
class SkinParams:
    """Geometry of the skin and its printed marker array.

    Attributes:
        pitch_mm: marker spacing, mm.
        n_markers_x: markers per row.
        n_markers_y: markers per column.
        marker_diameter_mm: printed dot diameter, mm.
        size_mm: side of the square skin, mm (the grid is centred on it).
        mechanics_cells: cells per side of the contact-mechanics grid over the skin.
        material: the elastomer.
    """

    pitch_mm: float = 1.5
    n_markers_x: int = 16
    n_markers_y: int = 16
    marker_diameter_mm: float = 0.5
    size_mm: float = 24.0
    mechanics_cells: int = 64
    material: Elastomer = field(default_factory=Elastomer)

    def __post_init__(self) -> None:
        for name in ("pitch_mm", "marker_diameter_mm", "size_mm"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        for name in ("n_markers_x", "n_markers_y", "mechanics_cells"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        span_x = (self.n_markers_x - 1) * self.pitch_mm + self.marker_diameter_mm
        span_y = (self.n_markers_y - 1) * self.pitch_mm + self.marker_diameter_mm
        if max(span_x, span_y) > self.size_mm:
            raise ValueError(f"marker array ({span_x:.2f} x {span_y:.2f} mm) does not fit on a skin of size_mm={self.size_mm}")


def marker_grid_mm(params: SkinParams) -> np.ndarray:
    """Rest positions of the printed markers, row-major (row = y, column = x).

    Returns:
        (n_markers_y * n_markers_x, 2) float64, skin-plane (x, y) in mm, centred on the skin.
    """
    xs = (np.arange(params.n_markers_x) - (params.n_markers_x - 1) / 2.0) * params.pitch_mm
    ys = (np.arange(params.n_markers_y) - (params.n_markers_y - 1) / 2.0) * params.pitch_mm
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()]).astype(np.float64)
