"""Everyday indenter shapes for the simulated sensor.

Each shape is a frozen dataclass giving its gap (height profile) over the skin plane:
the distance, mm, between the undeformed skin surface and the object's surface when the
object's lowest point just touches the skin (so the gap is >= 0 with minimum 0). The
profile is written in the object's own frame (x along its long axis) and placed on the
skin by `Indenter.gap_mm(x, y, centre_mm, angle_rad)`.

Every shape also carries Coulomb friction `mu` against the silicone skin and the object's
Young's modulus (all these objects are effectively rigid against a 0.56 MPa skin; the
modulus only enters E*), plus nominal ranges `RANGES` (field -> (low, high)) used by
`random(rng)`. Friction ranges: silicone elastomers on dry rigid surfaces, 0.4-1.5.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np

_STEEP_SLOPE = 5.0  # slope of a vertical-looking wall beyond a fillet (dimensionless)


def finite_number(value: Any, key: str) -> float:
    """`value`, a number read from a description (YAML/JSON), as a finite float.

    Raises:
        ValueError: naming `key` when `value` is not a number (a bool, a text, a list...) or is not
            finite: NaN, infinite, or an integer past the float range (YAML and JSON read 400 digits
            as an int, which float() refuses with an OverflowError).
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not math.isfinite(value)):
        raise ValueError(f"{key}: {value!r} is not a finite number")
    try:
        return float(value)
    except OverflowError:
        raise ValueError(f"{key}: an integer past the float range (1.8e308) is not a finite number") from None


def _filleted_slope(d_mm: np.ndarray, slope: float, fillet_mm: float) -> np.ndarray:
    """Gap of a rounded corner: parabola d^2/(2 rho) continued by a line of `slope`.

    Args:
        d_mm: (...) float64 signed distance past the first-contact line/point, mm (<= 0 inside).
        slope: slope of the flank beyond the fillet (dimensionless).
        fillet_mm: fillet radius rho, mm.
    Returns:
        (...) float64 gap >= 0, mm; zero where d <= 0.
    """
    d = np.maximum(d_mm, 0.0)
    knee = slope * fillet_mm
    return np.where(d < knee, d * d / (2.0 * fillet_mm), slope * d - 0.5 * slope * knee)


def _rounded_rect_gap(x: np.ndarray, y: np.ndarray, half_x_mm: float, half_y_mm: float, fillet_mm: float) -> np.ndarray:
    """Gap of a flat rectangular face with filleted edges (zero on the face)."""
    dx = np.maximum(np.abs(x) - half_x_mm, 0.0)
    dy = np.maximum(np.abs(y) - half_y_mm, 0.0)
    return _filleted_slope(np.hypot(dx, dy), _STEEP_SLOPE, fillet_mm)


@dataclass(frozen=True)
class Indenter(ABC):
    """Base of all shapes: friction, stiffness, placement and random sampling.

    Attributes:
        mu: Coulomb friction coefficient against the skin.
        youngs_modulus_mpa: Young's modulus of the object, MPa.
    """

    mu: float = 0.8
    youngs_modulus_mpa: float = 3000.0

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {}
    AXISYMMETRIC: ClassVar[bool] = False
    FLAT: ClassVar[bool] = False

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{type(self).__name__}.{f.name} must be finite and > 0, got {value}")

    @abstractmethod
    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Gap in the object's own frame: (...) mm arrays in, (...) float64 gap >= 0 out."""

    def gap_mm(self, x_mm: np.ndarray, y_mm: np.ndarray, centre_mm: np.ndarray, angle_rad: float) -> np.ndarray:
        """Gap over skin points with the object centred at `centre_mm`, rotated by `angle_rad`.

        Args:
            x_mm, y_mm: (...) float64 skin-plane coordinates, mm.
            centre_mm: (2,) object centre on the skin, mm.
            angle_rad: rotation of the object's x axis from the skin x axis (toward +y), rad.
        Returns:
            (...) float64 gap, mm.
        """
        c, s = np.cos(angle_rad), np.sin(angle_rad)
        dx, dy = x_mm - centre_mm[0], y_mm - centre_mm[1]
        return self.profile_mm(c * dx + s * dy, -s * dx + c * dy)

    @classmethod
    def random(cls, rng: np.random.Generator) -> "Indenter":
        """A sample with every field drawn uniformly from `RANGES`."""
        values: dict[str, Any] = {name: float(rng.uniform(lo, hi)) for name, (lo, hi) in cls.RANGES.items()}
        return cls(**values)


_RIGID_PLASTIC_TO_METAL = (1000.0, 200000.0)


@dataclass(frozen=True)
class Sphere(Indenter):
    """Ball, Hertz paraboloid r^2 / (2R) (valid for contact radius << R)."""

    radius_mm: float = 10.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"radius_mm": (5.0, 25.0), "mu": (0.5, 1.2), "youngs_modulus_mpa": _RIGID_PLASTIC_TO_METAL}
    AXISYMMETRIC: ClassVar[bool] = True

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        return (x_mm**2 + y_mm**2) / (2.0 * self.radius_mm)


@dataclass(frozen=True)
class Ellipsoid(Indenter):
    """Egg-like body: principal radii of curvature Rx, Ry at the contact point."""

    radius_x_mm: float = 20.0
    radius_y_mm: float = 8.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"radius_x_mm": (12.0, 30.0), "radius_y_mm": (5.0, 12.0), "mu": (0.5, 1.2), "youngs_modulus_mpa": _RIGID_PLASTIC_TO_METAL}

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        return x_mm**2 / (2.0 * self.radius_x_mm) + y_mm**2 / (2.0 * self.radius_y_mm)


@dataclass(frozen=True)
class Cylinder(Indenter):
    """Side of a can or rod, axis along x, with rounded ends (1 mm end fillet)."""

    radius_mm: float = 15.0
    length_mm: float = 40.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"radius_mm": (8.0, 35.0), "length_mm": (8.0, 60.0), "mu": (0.5, 1.2), "youngs_modulus_mpa": _RIGID_PLASTIC_TO_METAL}

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        end = _filleted_slope(np.abs(x_mm) - self.length_mm / 2.0, _STEEP_SLOPE, 1.0)
        return y_mm**2 / (2.0 * self.radius_mm) + end


@dataclass(frozen=True)
class Pen(Cylinder):
    """Pen or pencil body: a thin long cylinder."""

    radius_mm: float = 4.0
    length_mm: float = 140.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"radius_mm": (3.5, 6.0), "length_mm": (100.0, 160.0), "mu": (0.4, 1.0), "youngs_modulus_mpa": (1000.0, 3000.0)}


@dataclass(frozen=True)
class Coin(Indenter):
    """Flat disc face (coin, bottle bottom): flat punch with a small edge fillet."""

    radius_mm: float = 10.0
    fillet_mm: float = 0.3
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"radius_mm": (7.5, 13.0), "fillet_mm": (0.2, 0.5), "mu": (0.4, 1.0), "youngs_modulus_mpa": (80000.0, 200000.0)}
    AXISYMMETRIC: ClassVar[bool] = True
    FLAT: ClassVar[bool] = True

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        return _filleted_slope(np.hypot(x_mm, y_mm) - self.radius_mm, _STEEP_SLOPE, self.fillet_mm)


@dataclass(frozen=True)
class CubeFace(Indenter):
    """Flat square face of a box or die with filleted edges."""

    side_mm: float = 10.0
    fillet_mm: float = 0.5
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"side_mm": (6.0, 20.0), "fillet_mm": (0.3, 1.0), "mu": (0.4, 1.2), "youngs_modulus_mpa": (1000.0, 70000.0)}
    FLAT: ClassVar[bool] = True

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        half = self.side_mm / 2.0
        return _rounded_rect_gap(x_mm, y_mm, half, half, self.fillet_mm)


@dataclass(frozen=True)
class UsbStick(Indenter):
    """Flat face of a USB plug: a 12 x 4.5 mm-like rectangle, long axis along x."""

    length_mm: float = 12.0
    width_mm: float = 4.5
    fillet_mm: float = 0.3
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"length_mm": (11.0, 16.0), "width_mm": (4.0, 5.0), "fillet_mm": (0.2, 0.5), "mu": (0.3, 0.8), "youngs_modulus_mpa": (2000.0, 200000.0)}
    FLAT: ClassVar[bool] = True

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        return _rounded_rect_gap(x_mm, y_mm, self.length_mm / 2.0, self.width_mm / 2.0, self.fillet_mm)


@dataclass(frozen=True)
class Edge(Indenter):
    """Straight edge of a box or ruler along x: a wedge with a rounded tip."""

    fillet_mm: float = 1.0
    wedge_angle_deg: float = 90.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"fillet_mm": (0.5, 3.0), "wedge_angle_deg": (60.0, 120.0), "mu": (0.4, 1.2), "youngs_modulus_mpa": _RIGID_PLASTIC_TO_METAL}

    def __post_init__(self) -> None:
        """Also refuses an angle of 180 deg or more: its flanks would not slope up from the tip (at 180
        the wedge is a flat plane; past it they slope down, and the contact went to the skin's rims)."""
        super().__post_init__()
        if not self.wedge_angle_deg < 180.0:
            raise ValueError(f"Edge.wedge_angle_deg must be in (0, 180) deg, exclusive, got {self.wedge_angle_deg}")

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        slope = 1.0 / np.tan(np.radians(self.wedge_angle_deg) / 2.0)
        return _filleted_slope(np.abs(y_mm) + np.zeros_like(x_mm), slope, self.fillet_mm)


@dataclass(frozen=True)
class Corner(Indenter):
    """Cube corner pressed vertex-first: a three-sided pyramid with a rounded tip.

    The faces of a cube corner standing on its body diagonal are inclined at
    atan(1/sqrt(2)) = 35.3 deg to the skin, slope 0.707.
    """

    fillet_mm: float = 1.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"fillet_mm": (0.5, 3.0), "mu": (0.4, 1.2), "youngs_modulus_mpa": _RIGID_PLASTIC_TO_METAL}

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        angles = np.radians([0.0, 120.0, 240.0])
        # Distance measured along each face's horizontal normal; the inscribed-distance
        # factor 2 makes the pyramid's edges at distance 2 * max(.) = r.
        reach = np.max([np.cos(a) * x_mm + np.sin(a) * y_mm for a in angles], axis=0)
        return _filleted_slope(2.0 * reach / np.sqrt(3.0), 1.0 / np.sqrt(2.0), self.fillet_mm)


@dataclass(frozen=True)
class BottleCap(Indenter):
    """Rim of a bottle cap or jar lid pressed open side down: a torus-shaped lip."""

    radius_mm: float = 8.0
    lip_radius_mm: float = 0.8
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"radius_mm": (5.0, 11.0), "lip_radius_mm": (0.5, 1.5), "mu": (0.4, 1.0), "youngs_modulus_mpa": (1000.0, 3000.0)}
    AXISYMMETRIC: ClassVar[bool] = True

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        return (np.hypot(x_mm, y_mm) - self.radius_mm) ** 2 / (2.0 * self.lip_radius_mm)


@dataclass(frozen=True)
class Key(Indenter):
    """Bitted edge of a house key along x: a rounded blade edge with triangular teeth."""

    blade_length_mm: float = 22.0
    edge_radius_mm: float = 0.8
    tooth_pitch_mm: float = 3.0
    tooth_depth_mm: float = 0.6
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "blade_length_mm": (18.0, 26.0),
        "edge_radius_mm": (0.5, 1.2),
        "tooth_pitch_mm": (2.5, 4.0),
        "tooth_depth_mm": (0.3, 1.0),
        "mu": (0.3, 0.8),
        "youngs_modulus_mpa": (100000.0, 120000.0),
    }

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        phase = np.abs(((x_mm / self.tooth_pitch_mm) + 0.5) % 1.0 - 0.5) * 2.0  # 0 at tooth tips, 1 in valleys
        ends = _filleted_slope(np.abs(x_mm) - self.blade_length_mm / 2.0, _STEEP_SLOPE, 1.0)
        return y_mm**2 / (2.0 * self.edge_radius_mm) + self.tooth_depth_mm * phase + ends


@dataclass(frozen=True)
class ScrewHead(Indenter):
    """Slotted pan-head screw pressed head first: a dome with a slot along x."""

    head_radius_mm: float = 3.5
    dome_radius_mm: float = 8.0
    slot_width_mm: float = 1.0
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"head_radius_mm": (2.5, 5.0), "dome_radius_mm": (5.0, 12.0), "slot_width_mm": (0.6, 1.4), "mu": (0.3, 0.8), "youngs_modulus_mpa": (100000.0, 200000.0)}

    def profile_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        r = np.hypot(x_mm, y_mm)
        dome = r**2 / (2.0 * self.dome_radius_mm)
        rim = _filleted_slope(r - self.head_radius_mm, _STEEP_SLOPE, 0.3)
        slot = np.where((np.abs(y_mm) < self.slot_width_mm / 2.0) & (r < self.head_radius_mm), 1.0, 0.0)
        return dome + rim + slot


SHAPES: dict[str, type[Indenter]] = {
    "sphere": Sphere,
    "ellipsoid": Ellipsoid,
    "cylinder": Cylinder,
    "pen": Pen,
    "coin": Coin,
    "cube_face": CubeFace,
    "usb_stick": UsbStick,
    "edge": Edge,
    "corner": Corner,
    "bottle_cap": BottleCap,
    "key": Key,
    "screw_head": ScrewHead,
}


def shape_name(obj: Indenter) -> str:
    """The `SHAPES` key of an indenter instance."""
    for name, cls in SHAPES.items():
        if type(obj) is cls:
            return name
    raise ValueError(f"{type(obj).__name__} is not a registered shape")


def make_object(description: dict[str, Any]) -> Indenter:
    """Build an indenter from {"shape": name, <field>: value, ...}.

    Raises:
        ValueError: missing/unknown `shape`, unknown field (named), or a bad value.
    """
    if not isinstance(description, dict):
        raise ValueError(f"object description must be a mapping, got {type(description).__name__}")
    if "shape" not in description:
        raise ValueError(f"object description needs key 'shape' (one of {sorted(SHAPES)})")
    name = description["shape"]
    if not isinstance(name, str) or name not in SHAPES:
        raise ValueError(f"object.shape must be one of {sorted(SHAPES)} (got {name!r})")
    cls = SHAPES[name]
    allowed = {f.name for f in fields(cls)}
    params = {k: v for k, v in description.items() if k != "shape"}
    for key in params:
        if key not in allowed:
            raise ValueError(f"object key {key!r} is not a field of {name}; allowed: {sorted(allowed)}")
    return cls(**{key: finite_number(value, f"object.{key}") for key, value in params.items()})
