"""Elastic half-space surface Green's functions (Boussinesq-Cerruti) by FFT convolution.

Surface tractions are piecewise constant over the square cells of a `SurfaceGrid`; the
influence of one cell is the exact integral of the point-load solution over the cell
(Love's closed-form rectangle integrals), so no singular kernel value is ever sampled.
Convolutions are linear (zero-padded to 2n x 2n) and the kernel spectra are computed once
per (grid, material) and cached.

Point-load surface displacements (Landau & Lifshitz, Theory of Elasticity, sec. 8), with
z pointing into the body (= toward the camera in skin coordinates), G the shear modulus,
a load (Fx, Fy, Fz) at the origin, r = |(x, y)|:
    ux = [2(1-nu)/r Fx + 2 nu x (x Fx + y Fy)/r^3 - (1-2nu) x/r^2 Fz] / (4 pi G)
    uy = [2(1-nu)/r Fy + 2 nu y (x Fx + y Fy)/r^3 - (1-2nu) y/r^2 Fz] / (4 pi G)
    uz = [2(1-nu)/r Fz + (1-2nu) (x Fx + y Fy)/r^2] / (4 pi G)
Units: mm, MPa (N/mm^2) tractions, N forces, mm displacements.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft as sfft

from fv_algos.sim.skin import Elastomer


@dataclass(frozen=True)
class SurfaceGrid:
    """Square cell-centred grid over the skin plane, centred on the origin.

    Attributes:
        n_cells: cells per side.
        cell_mm: cell side, mm.
    """

    n_cells: int
    cell_mm: float

    def __post_init__(self) -> None:
        if int(self.n_cells) < 1:
            raise ValueError(f"n_cells must be >= 1, got {self.n_cells}")
        if not (np.isfinite(self.cell_mm) and self.cell_mm > 0):
            raise ValueError(f"cell_mm must be finite and > 0, got {self.cell_mm}")

    @property
    def size_mm(self) -> float:
        """Side of the grid, mm."""
        return self.n_cells * self.cell_mm

    @property
    def cell_area_mm2(self) -> float:
        """Area of one cell, mm^2."""
        return self.cell_mm**2

    def coords_mm(self) -> np.ndarray:
        """(n_cells,) float64 cell-centre coordinates along x (and y), mm."""
        return (np.arange(self.n_cells) - (self.n_cells - 1) / 2.0) * self.cell_mm

    def mesh_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell centres (x, y), each (n_cells, n_cells) float64 mm, indexed [row=y, col=x]."""
        c = self.coords_mm()
        return np.meshgrid(c, c)

    def sample(self, fields: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of grid fields at skin points; zero outside the grid.

        Args:
            fields: (..., n_cells, n_cells) float64 values at cell centres.
            points_mm: (M, 2) skin-plane (x, y), mm.
        Returns:
            (..., M) float64. Points beyond the outermost cell centres are clamped to the
            border cell; points outside the grid square get 0 (no material there).
        """
        points = np.asarray(points_mm, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise ValueError(f"points_mm must have shape (M, 2), got {points.shape}")
        n = self.n_cells
        if fields.shape[-2:] != (n, n):
            raise ValueError(f"fields must end in ({n}, {n}), got {fields.shape}")
        fx = np.clip(points[:, 0] / self.cell_mm + (n - 1) / 2.0, 0.0, n - 1.0)
        fy = np.clip(points[:, 1] / self.cell_mm + (n - 1) / 2.0, 0.0, n - 1.0)
        x0 = np.minimum(np.floor(fx).astype(np.intp), max(n - 2, 0))
        y0 = np.minimum(np.floor(fy).astype(np.intp), max(n - 2, 0))
        x1 = np.minimum(x0 + 1, n - 1)
        y1 = np.minimum(y0 + 1, n - 1)
        tx = fx - x0
        ty = fy - y0
        top = fields[..., y0, x0] * (1 - tx) + fields[..., y0, x1] * tx
        bottom = fields[..., y1, x0] * (1 - tx) + fields[..., y1, x1] * tx
        values = top * (1 - ty) + bottom * ty
        half = self.size_mm / 2.0
        inside = (np.abs(points[:, 0]) <= half) & (np.abs(points[:, 1]) <= half)
        return np.where(inside, values, 0.0)


def _xlogish(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a * asinh(b / |a|), with the limit 0 at a = 0 (part of the 1/r rectangle primitive)."""
    abs_a = np.abs(a)
    safe = np.where(abs_a > 0, abs_a, 1.0)
    return np.where(abs_a > 0, a * np.arcsinh(b / safe), 0.0)


def _primitives(x: np.ndarray, y: np.ndarray) -> dict[str, np.ndarray]:
    """Double primitives F(x, y) (d2F/dxdy = integrand) of the point-load kernels.

    Terms depending on one variable only are dropped: they cancel in the 4-corner sum.
    """
    r = np.hypot(x, y)
    r2 = np.where(r > 0, r * r, 1.0)
    xs = np.where(x != 0, x, 1.0)
    atan_xy = np.where(x != 0, x * np.arctan(y / xs), 0.0)
    ys = np.where(y != 0, y, 1.0)
    atan_yx = np.where(y != 0, y * np.arctan(x / ys), 0.0)
    log_r = np.where(r > 0, 0.5 * np.log(r2), 0.0)
    return {
        "inv_r": _xlogish(x, y) + _xlogish(y, x),  # 1/r
        "xx_r3": _xlogish(y, x),  # x^2 / r^3
        "yy_r3": _xlogish(x, y),  # y^2 / r^3
        "xy_r3": -r,  # x y / r^3
        "x_r2": np.where(y != 0, y * log_r, 0.0) + atan_xy,  # x / r^2
        "y_r2": np.where(x != 0, x * log_r, 0.0) + atan_yx,  # y / r^2
    }


def _cell_integrals(n_cells: int, cell_mm: float) -> dict[str, np.ndarray]:
    """Integrals of the kernels over a source cell, for field-minus-source offsets.

    Returns:
        name -> (2n, 2n) float64 in FFT wrap-around order (offset index k for k < n,
        k - 2n otherwise), mm (for 1/r-type kernels) or dimensionless (x/r^2-type are mm).
    """
    m = 2 * n_cells
    k = np.arange(m)
    offsets = np.where(k < n_cells, k, k - m) * cell_mm
    ox, oy = np.meshgrid(offsets, offsets)
    half = cell_mm / 2.0
    corners = [(+1, +1, +1), (-1, +1, -1), (+1, -1, -1), (-1, -1, +1)]
    total: dict[str, np.ndarray] = {}
    for sx, sy, sign in corners:
        prims = _primitives(ox + sx * half, oy + sy * half)
        for name, value in prims.items():
            total[name] = total.get(name, 0.0) + sign * value
    return total


@lru_cache(maxsize=16)
def _kernel_spectra(n_cells: int, cell_mm: float, youngs_mpa: float, poisson: float) -> dict[str, np.ndarray]:
    """rfft2 spectra of the 3x3 surface influence matrix, mm/MPa, cached per grid+material."""
    ints = _cell_integrals(n_cells, cell_mm)
    g = youngs_mpa / (2.0 * (1.0 + poisson))
    c = 1.0 / (4.0 * np.pi * g)
    kernels = {
        "xx": c * (2 * (1 - poisson) * ints["inv_r"] + 2 * poisson * ints["xx_r3"]),
        "yy": c * (2 * (1 - poisson) * ints["inv_r"] + 2 * poisson * ints["yy_r3"]),
        "xy": c * 2 * poisson * ints["xy_r3"],
        "zz": c * 2 * (1 - poisson) * ints["inv_r"],
        "xz": -c * (1 - 2 * poisson) * ints["x_r2"],  # ux from Fz
        "yz": -c * (1 - 2 * poisson) * ints["y_r2"],
    }
    spectra = {name: sfft.rfft2(k) for name, k in kernels.items()}
    for spec in spectra.values():
        spec.setflags(write=False)
    return spectra


class HalfSpace:
    """Surface displacements of an elastic half-space from cell-wise surface tractions.

    Build once per grid; every call is a handful of (2n x 2n) real FFTs.
    """

    def __init__(self, grid: SurfaceGrid, material: Elastomer) -> None:
        self.grid = grid
        self.material = material
        self._spectra = _kernel_spectra(grid.n_cells, float(grid.cell_mm), material.youngs_modulus_mpa, material.poisson_ratio)
        self._shape = (2 * grid.n_cells, 2 * grid.n_cells)
        sxx, syy, sxy = (self._spectra[k].real for k in ("xx", "yy", "xy"))
        # Largest eigenvalue of the 2x2 tangential symbol: a bound on the tangential operator norm
        # (hypot: the squares overflowed for moduli near the smallest float).
        self.tangential_norm_mm_per_mpa = float(np.max(0.5 * (sxx + syy) + np.hypot(0.5 * (sxx - syy), sxy)))

    def _forward(self, values: np.ndarray) -> np.ndarray:
        return sfft.rfft2(values, s=self._shape, workers=1)

    def _inverse(self, spectrum: np.ndarray) -> np.ndarray:
        n = self.grid.n_cells
        return sfft.irfft2(spectrum, s=self._shape, workers=1)[:n, :n]

    def _check(self, values: np.ndarray, name: str, lead: tuple[int, ...]) -> np.ndarray:
        n = self.grid.n_cells
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != lead + (n, n):
            raise ValueError(f"{name} must have shape {lead + (n, n)}, got {arr.shape}")
        return arr

    def normal_displacement_mm(self, pressure_mpa: np.ndarray) -> np.ndarray:
        """uz (toward the camera) from normal pressure only, ignoring coupling.

        Args:
            pressure_mpa: (n, n) float64 normal pressure, MPa (positive pushes toward the camera).
        Returns:
            (n, n) float64 uz, mm.
        """
        p = self._check(pressure_mpa, "pressure_mpa", ())
        return self._inverse(self._forward(p) * self._spectra["zz"])

    def tangential_displacement_mm(self, traction_mpa: np.ndarray) -> np.ndarray:
        """(ux, uy) from tangential traction only, ignoring coupling.

        Args:
            traction_mpa: (2, n, n) float64 (qx, qy), MPa.
        Returns:
            (2, n, n) float64 (ux, uy), mm.
        """
        q = self._check(traction_mpa, "traction_mpa", (2,))
        fx, fy = self._forward(q[0]), self._forward(q[1])
        s = self._spectra
        return np.stack([self._inverse(s["xx"] * fx + s["xy"] * fy), self._inverse(s["xy"] * fx + s["yy"] * fy)])

    def displacement_mm(self, pressure_mpa: np.ndarray | None, traction_mpa: np.ndarray | None) -> np.ndarray:
        """Full coupled surface displacement (ux, uy, uz) from pressure and/or traction.

        Args:
            pressure_mpa: (n, n) float64 normal pressure, MPa, or None for none.
            traction_mpa: (2, n, n) float64 tangential traction, MPa, or None for none
                (then no Cerruti FFT is computed at all).
        Returns:
            (3, n, n) float64 displacement (ux, uy, uz), mm; z toward the camera.
        """
        n = self.grid.n_cells
        s = self._spectra
        out_spec = [0.0, 0.0, 0.0]
        if pressure_mpa is not None:
            fz = self._forward(self._check(pressure_mpa, "pressure_mpa", ()))
            out_spec = [s["xz"] * fz, s["yz"] * fz, s["zz"] * fz]
        if traction_mpa is not None:
            q = self._check(traction_mpa, "traction_mpa", (2,))
            fx, fy = self._forward(q[0]), self._forward(q[1])
            # Reciprocity: uz from Fx is minus ux from Fz.
            out_spec = [
                out_spec[0] + s["xx"] * fx + s["xy"] * fy,
                out_spec[1] + s["xy"] * fx + s["yy"] * fy,
                out_spec[2] - s["xz"] * fx - s["yz"] * fy,
            ]
        return np.stack([self._inverse(sp) if not np.isscalar(sp) else np.zeros((n, n)) for sp in out_spec])
