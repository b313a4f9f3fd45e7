"""Normal, tangential and torsional contact of a rigid indenter on the elastic skin.

All fields live on a `SurfaceGrid` (cell-centred, (n, n), indexed [row=y, col=x]);
pressures and tractions in MPa (N/mm^2), forces in N, torques in N*mm (positive turning
+x toward +y), lengths in mm.

Normal contact
    * Hertz (sphere) and flat punch (Boussinesq, coin) in closed form when the contact
      patch lies inside the skin;
    * otherwise the Polonsky-Keer conjugate-gradient solver (Polonsky & Keer, Wear 231,
      1999) with FFT half-space compliance, p >= 0, the load as a constraint, warm-started
      from the previous frame and run on a window around the contact.
    Discrete pressures are scaled so that sum(p) * cell_area equals the load exactly.

Tangential contact (the elastic coupling term (1 - 2 nu) = 0.02 is neglected in the
traction solution, as in Mindlin's theory; it is kept in the displacements)
    * translational partial slip: Ciavarella-Jaeger superposition
      q = mu [p(P) - p(P*)] along Q, P* = P - |Q| / mu (any shape; for a sphere it is
      Cattaneo-Mindlin with stick radius c = a (1 - Q / (mu P))^(1/3));
    * torsional (and combined) partial slip: numerical solution of the frictional
      complementarity problem (minimise the elastic energy of the tangential traction
      against the rigid motion (dx, dy, theta) of the indenter, with |q| <= mu p per cell,
      by accelerated projected gradient, FISTA), with (dx, dy, theta) found by a Broyden
      iteration so that the integrated traction matches (Qx, Qy, M);
    * gross slip: q = mu p along the sliding direction (translational) or the
      circumferential direction about the spin centre (rotational).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fv_algos.sim.halfspace import HalfSpace, SurfaceGrid
from fv_algos.sim.objects import Coin, Indenter, Sphere
from fv_algos.sim.skin import Elastomer, SkinParams


@dataclass(frozen=True)
class ContactParams:
    """Solver settings.

    Attributes:
        normal_tolerance: Polonsky-Keer stop: relative L1 change of the load distribution.
        normal_max_iterations: Polonsky-Keer iteration cap.
        tangential_tolerance: partial-slip stop: load error relative to the friction limit.
        tangential_max_outer: Broyden iterations on the rigid motion.
        tangential_max_inner: FISTA iterations per rigid motion.
        incipient_share: slip-zone share of the contact area from which a partial-slip
            contact is labelled `incipient` (it then counts as slip).
    """

    normal_tolerance: float = 1e-4
    normal_max_iterations: int = 300
    tangential_tolerance: float = 0.005
    tangential_max_outer: int = 30
    tangential_max_inner: int = 200
    incipient_share: float = 0.5


@dataclass
class NormalSolution:
    """Normal contact on a grid.

    Attributes:
        pressure_mpa: (n, n) float64 pressure >= 0, MPa.
        approach_mm: rigid approach of the indenter past first touch, mm.
        load_N: normal load, N.
        converged: False when the iterative solver hit its cap (result still finite).
    """

    pressure_mpa: np.ndarray
    approach_mm: float
    load_N: float
    converged: bool = True

    @property
    def contact(self) -> np.ndarray:
        """(n, n) bool cells in contact."""
        return self.pressure_mpa > 0


def _check_load(name: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


def hertz_contact_radius_mm(load_N: float, radius_mm: float, contact_modulus_mpa: float) -> float:
    """Hertz contact radius a = (3 P R / (4 E*))^(1/3), mm."""
    _check_load("load_N", load_N)
    if not (radius_mm > 0 and contact_modulus_mpa > 0):
        raise ValueError(f"radius_mm and contact_modulus_mpa must be > 0, got {radius_mm}, {contact_modulus_mpa}")
    return float((3.0 * load_N * radius_mm / (4.0 * contact_modulus_mpa)) ** (1.0 / 3.0))


def cattaneo_mindlin_stick_radius_mm(contact_radius_mm: float, tangential_N: float, normal_N: float, mu: float) -> float:
    """Stick radius c = a (1 - Q / (mu P))^(1/3) of a Hertz contact under shear, mm (0 at gross slip)."""
    if normal_N <= 0 or mu <= 0:
        raise ValueError(f"normal_N and mu must be > 0, got {normal_N}, {mu}")
    ratio = min(abs(tangential_N) / (mu * normal_N), 1.0)
    return float(contact_radius_mm * (1.0 - ratio) ** (1.0 / 3.0))


def hertz_torsion_limit_Nmm(mu: float, normal_N: float, contact_radius_mm: float) -> float:
    """Torque at gross rotational slip of a Hertz contact, M = 3 pi mu P a / 16, N*mm."""
    return float(3.0 * np.pi * mu * normal_N * contact_radius_mm / 16.0)


def _normalised(pressure: np.ndarray, load_N: float, grid: SurfaceGrid, centre_mm: np.ndarray) -> np.ndarray:
    """Scale a discrete pressure to carry exactly `load_N`; a sub-cell contact goes to one cell."""
    total = pressure.sum() * grid.cell_area_mm2
    if total > 0:
        return pressure * (load_N / total)
    out = np.zeros_like(pressure)
    if load_N > 0:
        c = grid.coords_mm()
        out[np.argmin(np.abs(c - centre_mm[1])), np.argmin(np.abs(c - centre_mm[0]))] = load_N / grid.cell_area_mm2
    return out


def hertz_solution(grid: SurfaceGrid, centre_mm: np.ndarray, load_N: float, radius_mm: float, contact_modulus_mpa: float) -> NormalSolution:
    """Closed-form Hertz pressure p0 sqrt(1 - r^2/a^2) of a sphere of radius R on the grid."""
    a = hertz_contact_radius_mm(load_N, radius_mm, contact_modulus_mpa)
    x, y = grid.mesh_mm()
    rho2 = ((x - centre_mm[0]) ** 2 + (y - centre_mm[1]) ** 2) / max(a * a, 1e-300)
    p = np.sqrt(np.clip(1.0 - rho2, 0.0, None)) if a > 0 else np.zeros_like(x)
    return NormalSolution(_normalised(p, load_N, grid, centre_mm), a * a / radius_mm, load_N)


def flat_punch_solution(grid: SurfaceGrid, centre_mm: np.ndarray, load_N: float, radius_mm: float, contact_modulus_mpa: float) -> NormalSolution:
    """Closed-form Boussinesq flat-punch pressure P / (2 pi a sqrt(a^2 - r^2)).

    The edge singularity is integrable; cell values are the cell-average of the exact
    pressure over the ring r in [r - h/2, r + h/2] (1 - sqrt(1 - r^2/a^2) is the load share
    inside radius r), which stays finite at the rim.
    """
    _check_load("load_N", load_N)
    x, y = grid.mesh_mm()
    r = np.hypot(x - centre_mm[0], y - centre_mm[1])
    h = grid.cell_mm
    lo = np.clip(r - h / 2.0, 0.0, radius_mm)
    hi = np.clip(r + h / 2.0, 0.0, radius_mm)
    share = np.sqrt(1.0 - (lo / radius_mm) ** 2) - np.sqrt(1.0 - (hi / radius_mm) ** 2)
    ring_area = np.pi * ((r + h / 2.0) ** 2 - np.maximum(r - h / 2.0, 0.0) ** 2)
    p = share / ring_area
    approach = load_N / (2.0 * contact_modulus_mpa * radius_mm)
    return NormalSolution(_normalised(p, load_N, grid, centre_mm), approach, load_N)


def _window(mask: np.ndarray, pad: int, multiple: int = 8) -> tuple[slice, slice]:
    """Square-ish window (rows, cols) around True cells, padded, sizes rounded up to `multiple`."""
    n_rows, n_cols = mask.shape
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    out = []
    for idx, n in ((rows, n_rows), (cols, n_cols)):
        lo, hi = max(int(idx[0]) - pad, 0), min(int(idx[-1]) + pad + 1, n)
        size = min(int(np.ceil((hi - lo) / multiple) * multiple), n)
        lo = max(min(lo, n - size), 0)
        out.append(slice(lo, lo + size))
    return out[0], out[1]


def _sub_halfspace(halfspace: HalfSpace, size: int) -> HalfSpace:
    """Half-space on a `size`-cell grid with the same cell size (kernel spectra are cached)."""
    if size == halfspace.grid.n_cells:
        return halfspace
    return HalfSpace(SurfaceGrid(size, halfspace.grid.cell_mm), halfspace.material)


def _polonsky_keer(halfspace: HalfSpace, gap_mm: np.ndarray, load_N: float, p0: np.ndarray, params: ContactParams) -> tuple[np.ndarray, float, bool]:
    """Polonsky-Keer CG on a square grid: returns (pressure MPa, approach mm, converged).

    Stops at once with approach NaN (not converged) when the pressure or the displacements
    leave the float64 range (a load or a compliance too large, or a load too small to spread).
    """
    area = halfspace.grid.cell_area_mm2
    p = p0 * (load_N / (p0.sum() * area))
    t = np.zeros_like(p)
    g_old, conjugate = 1.0, False
    approach = 0.0
    self_compliance = None
    for _ in range(params.normal_max_iterations):
        contact = p > 0
        with np.errstate(over="ignore", invalid="ignore"):  # out of range: caught just below
            g = halfspace.normal_displacement_mm(p) + gap_mm
            in_range = contact.any() and np.isfinite(np.sum(g[contact] ** 2))
        if not in_range:
            return p, float("nan"), False
        approach = float(g[contact].mean())
        g -= approach
        g_norm = float(np.sum(g[contact] ** 2))
        t = np.where(contact, g + (g_norm / g_old) * t if conjugate else g, 0.0)
        g_old = max(g_norm, 1e-300)
        r = halfspace.normal_displacement_mm(t)
        r -= r[contact].mean()
        denom = float(np.sum(r[contact] * t[contact]))
        if denom <= 0:  # the contact set is solved (e.g. one cell, where g is 0): done unless the
            overlap = (p == 0) & (g < 0)  # indenter goes through the skin outside it
            if not overlap.any():
                return p, approach, True
            if self_compliance is None:  # uz of a cell under its own unit pressure, mm/MPa
                unit = np.zeros_like(p)
                unit[0, 0] = 1.0
                self_compliance = float(halfspace.normal_displacement_mm(unit)[0, 0])
            p = np.where(overlap, -g / self_compliance, p)
            p *= load_N / (p.sum() * area)
            conjugate = False
            continue
        tau = float(np.sum(g[contact] * t[contact])) / denom
        p_old = p
        p = np.maximum(p - tau * t, 0.0)
        overlap = (p == 0) & (g < 0)
        conjugate = not overlap.any()
        p = np.where(overlap, p - tau * g, p)
        p *= load_N / (p.sum() * area)
        if np.abs(p - p_old).sum() * area < params.normal_tolerance * load_N:
            return p, approach, True
    return p, approach, False


def _solve_on_window(halfspace: HalfSpace, gap_mm: np.ndarray, load_N: float, params: ContactParams, candidate: np.ndarray, seed: np.ndarray) -> NormalSolution:
    """Polonsky-Keer on the window around the `candidate` cells (n, n) bool, seeded with `seed` (n, n)
    MPa; gap_mm (n, n) >= 0 mm, load_N > 0. ValueError naming the load and the half-space's Young's
    modulus when the solve leaves the float64 range."""
    n = halfspace.grid.n_cells
    rows, cols = _window(candidate, pad=2)
    h, w = rows.stop - rows.start, cols.stop - cols.start
    sub = _sub_halfspace(halfspace, max(h, w))
    m = sub.grid.n_cells
    # Square window; padding cells beyond the skin are lifted far out of reach.
    sub_gap = np.full((m, m), gap_mm.max() + 1e3)
    sub_seed = np.zeros((m, m))
    sub_gap[:h, :w] = gap_mm[rows, cols]
    sub_seed[:h, :w] = seed[rows, cols]
    p_sub, approach, converged = _polonsky_keer(sub, sub_gap, load_N, sub_seed, params)
    if not np.isfinite(approach):
        modulus = halfspace.material.youngs_modulus_mpa
        raise ValueError(f"normal contact out of the solver's float64 range: load_N {load_N:g} N against a Young's "
                         f"modulus of {modulus:g} MPa (the skin's, or a softer object's); neither is a physical value")
    pressure = np.zeros((n, n))
    pressure[rows, cols] = p_sub[:h, :w]
    return NormalSolution(pressure, approach, load_N, converged)


def solve_normal(halfspace: HalfSpace, gap_mm: np.ndarray, load_N: float, params: ContactParams, warm: NormalSolution | None = None) -> NormalSolution:
    """Rigid indenter of arbitrary shape pressed with `load_N` (Polonsky-Keer CG).

    Args:
        halfspace: compliance on the skin grid.
        gap_mm: (n, n) float64 gap between the undeformed skin and the indenter, mm
            (only differences matter: the approach is solved for).
        load_N: normal load, N (0 gives zero pressure).
        params: solver settings.
        warm: previous frame's solution (its contact region seeds the iteration and the
            solve runs on a window around it).
    Returns:
        NormalSolution on the full grid; `approach_mm` is measured from the gap's minimum.
    Raises:
        ValueError naming the load and the half-space's Young's modulus when the solve leaves the
        float64 range (e.g. 1e160 N, 5e-324 N, or a modulus of 1e-300 MPa).
    """
    n = halfspace.grid.n_cells
    gap = np.asarray(gap_mm, dtype=np.float64)
    if gap.shape != (n, n) or not np.all(np.isfinite(gap)):
        raise ValueError(f"gap_mm must be a finite ({n}, {n}) array, got shape {gap.shape}")
    load = _check_load("load_N", load_N)
    if load == 0:
        return NormalSolution(np.zeros((n, n)), 0.0, 0.0)
    gap = gap - gap.min()
    if warm is not None and warm.load_N > 0:
        # The approach grows at most linearly with the load (flat punch); 20 % margin.
        bound = 1.2 * warm.approach_mm * max(load / warm.load_N, 1.0) + 0.05 * halfspace.grid.cell_mm
        seed = np.where(warm.contact & (gap <= bound), warm.pressure_mpa, 0.0)
        candidate = gap <= bound
    else:
        bound = np.inf
        seed = np.zeros((n, n))
        candidate = np.ones((n, n), dtype=bool)
    if not seed.any():
        seed = (gap <= gap.min() + halfspace.grid.cell_mm * 0.1).astype(np.float64)
    solution = _solve_on_window(halfspace, gap, load, params, candidate, seed)
    # Contact lies where gap < approach, so the window holds it whenever approach < bound.
    if solution.approach_mm < bound:
        return solution
    full = np.ones((n, n), dtype=bool)
    return _solve_on_window(halfspace, gap, load, params, full, solution.pressure_mpa)


def ciavarella_jaeger_traction(full: NormalSolution, reduced: NormalSolution, mu: float, direction: np.ndarray, cell_area_mm2: float) -> np.ndarray:
    """Partial-slip shear traction q = mu [p(P) - p(P*)] along `direction`.

    Args:
        full: normal solution at the load P.
        reduced: normal solution at P* = P - |Q| / mu (same indenter and position).
        mu: friction coefficient.
        direction: (2,) unit vector of the tangential load.
        cell_area_mm2: grid cell area, mm^2.
    Returns:
        (2, n, n) float64 traction, MPa; it integrates to |Q| = mu (P - P*) (numerical
        negatives of p(P) - p(P*) are clipped and the rest rescaled to that total).
    """
    q = np.clip(full.pressure_mpa - reduced.pressure_mpa, 0.0, None)
    total = q.sum() * cell_area_mm2
    if total > 0:
        q *= mu * (full.load_N - reduced.load_N) / total
    return np.stack([q * direction[0], q * direction[1]])


def sliding_traction(pressure_mpa: np.ndarray, mu: float, direction: np.ndarray) -> np.ndarray:
    """Gross translational slip: q = mu p along the (2,) unit sliding direction; (2, n, n) MPa."""
    return np.stack([mu * pressure_mpa * direction[0], mu * pressure_mpa * direction[1]])


def spinning_traction(grid: SurfaceGrid, pressure_mpa: np.ndarray, mu: float, centre_mm: np.ndarray, sign: float) -> np.ndarray:
    """Gross rotational slip about `centre_mm`: q = mu p e_theta (sign +1: +x toward +y); (2, n, n) MPa."""
    x, y = grid.mesh_mm()
    rx, ry = x - centre_mm[0], y - centre_mm[1]
    r = np.hypot(rx, ry)
    safe = np.where(r > 0, r, 1.0)
    scale = np.where(r > 0, sign * mu * pressure_mpa / safe, 0.0)
    return np.stack([-ry * scale, rx * scale])


def torsion_limit_Nmm(grid: SurfaceGrid, pressure_mpa: np.ndarray, mu: float, centre_mm: np.ndarray) -> float:
    """Torque at gross rotational slip about `centre_mm`: sum(mu p r) * cell_area, N*mm."""
    x, y = grid.mesh_mm()
    r = np.hypot(x - centre_mm[0], y - centre_mm[1])
    return float(mu * np.sum(pressure_mpa * r) * grid.cell_area_mm2)


@dataclass
class PartialSlipSolution:
    """Numerical partial-slip tangential contact.

    Attributes:
        traction_mpa: (2, n, n) float64 tangential traction, MPa.
        rigid_motion: (3,) float64 indenter motion (dx_mm, dy_mm, theta_rad) relative to
            the far skin that produces it.
        slip: (n, n) bool cells where |q| has reached mu p (the slip zone).
        converged: False when the iteration cap was hit (result still finite).
    """

    traction_mpa: np.ndarray
    rigid_motion: np.ndarray
    slip: np.ndarray
    converged: bool


def _loads(q: np.ndarray, rx: np.ndarray, ry: np.ndarray, area: float) -> np.ndarray:
    """(Qx, Qy, M) of a traction field: N, N, N*mm."""
    return np.array([q[0].sum(), q[1].sum(), np.sum(rx * q[1] - ry * q[0])]) * area


def solve_partial_slip(
    halfspace: HalfSpace,
    pressure_mpa: np.ndarray,
    mu: float,
    force_N: np.ndarray,
    torque_Nmm: float,
    centre_mm: np.ndarray,
    params: ContactParams,
    warm: PartialSlipSolution | None = None,
) -> PartialSlipSolution:
    """Tangential traction under combined shear force and torque below gross slip.

    The traction minimises 1/2 <q, C q> - <w, q> subject to |q| <= mu p per cell, where C
    is the tangential half-space compliance and w = (dx - theta ry, dy + theta rx) the rigid
    indenter motion; (dx, dy, theta) are found by Broyden's method so that the traction
    integrates to (force_N, torque_Nmm). Works on a window around the contact.

    Args:
        halfspace: compliance on the skin grid.
        pressure_mpa: (n, n) float64 normal pressure, MPa.
        mu: friction coefficient (> 0).
        force_N: (2,) tangential load, N.
        torque_Nmm: torque about `centre_mm`, N*mm (+x toward +y).
        centre_mm: (2,) torque reference point, mm.
        params: solver settings.
        warm: previous frame's solution (seeds traction and rigid motion).
    Returns:
        PartialSlipSolution on the full grid.
    """
    grid = halfspace.grid
    n, area = grid.n_cells, grid.cell_area_mm2
    contact = pressure_mpa > 0
    if not contact.any():
        raise ValueError("solve_partial_slip needs a contact (pressure_mpa has no positive cell)")
    rows, cols = _window(contact, pad=1)
    h, w = rows.stop - rows.start, cols.stop - cols.start
    sub = _sub_halfspace(halfspace, max(h, w))
    m = sub.grid.n_cells
    x, y = grid.mesh_mm()
    limit = np.zeros((m, m))
    limit[:h, :w] = mu * pressure_mpa[rows, cols]
    rx = np.zeros((m, m))
    ry = np.zeros((m, m))
    rx[:h, :w] = x[rows, cols] - centre_mm[0]
    ry[:h, :w] = y[rows, cols] - centre_mm[1]
    target = np.array([force_N[0], force_N[1], torque_Nmm], dtype=np.float64)
    radius = np.sqrt(contact.sum() * area / np.pi)
    g_mod, nu = halfspace.material.shear_modulus_mpa, halfspace.material.poisson_ratio
    # Full-stick stiffnesses of a circular contact (Mindlin; Lubkin): the size of the probes below.
    circular = np.array([8 * g_mod * radius / (2 - nu), 8 * g_mod * radius / (2 - nu), 16 * g_mod * radius**3 / 3])
    scale = np.array([mu * pressure_mpa.sum() * area] * 2 + [max(torsion_limit_Nmm(grid, pressure_mpa, mu, centre_mm), 1e-12)])
    step = 1.0 / sub.tangential_norm_mm_per_mpa

    def project(v: np.ndarray) -> np.ndarray:
        mag = np.hypot(v[0], v[1])
        factor = np.where(mag > limit, limit / np.where(mag > 0, mag, 1.0), 1.0)
        return v * factor

    def inner(mv: np.ndarray, q_start: np.ndarray) -> np.ndarray:
        wx = mv[0] - mv[2] * ry
        wy = mv[1] + mv[2] * rx
        qk = project(q_start)
        yk, tk = qk, 1.0
        for _ in range(params.tangential_max_inner):
            u = sub.tangential_displacement_mm(yk)
            q_next = project(yk - step * np.stack([u[0] - wx, u[1] - wy]))
            t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * tk * tk))
            change = np.abs(q_next - qk).sum()
            yk = q_next + ((tk - 1.0) / t_next) * (q_next - qk)
            qk, tk = q_next, t_next
            if change < 0.1 * params.tangential_tolerance * np.abs(qk).sum():  # relative: a small load's
                break  # traction is as converged as a large one's
        return qk

    # The contact's own stick stiffness (3, 3), from three small rigid motions: the circular
    # estimate is far too soft for a long patch (a key's blade), and Broyden then overshoots into
    # gross slip, where the loads no longer change with the motion.
    probes = 1e-3 * scale / circular
    stick = np.stack([_loads(inner(np.eye(3)[i] * probes[i], np.zeros((2, m, m))), rx, ry, area) / probes[i]
                      for i in range(3)], axis=1)
    jac = stick.copy()
    q = np.zeros((2, m, m))
    motion = np.linalg.lstsq(jac, target, rcond=None)[0]
    if warm is not None:
        q[:, :h, :w] = warm.traction_mpa[:, rows, cols]
        motion = warm.rigid_motion.copy()
    q = inner(motion, q)
    residual = _loads(q, rx, ry, area) - target
    converged = False
    for _ in range(params.tangential_max_outer):
        if np.all(np.abs(residual) <= params.tangential_tolerance * scale):
            converged = True
            break
        if np.linalg.cond(jac) > 1e12:  # Broyden's updates lost a direction: start again from the stick
            jac = stick.copy()
        delta = -np.linalg.lstsq(jac, residual, rcond=None)[0]
        for halvings in range(8):  # halve a step that makes the loads worse (the 8th is taken as it is)
            if halvings:
                delta = delta / 2.0
            q_try = inner(motion + delta, q)
            new_residual = _loads(q_try, rx, ry, area) - target
            if np.linalg.norm(new_residual / scale) < np.linalg.norm(residual / scale):
                break
        motion, q = motion + delta, q_try
        if delta @ delta > 0:
            jac = jac + np.outer(new_residual - residual - jac @ delta, delta) / float(delta @ delta)
        residual = new_residual
    traction = np.zeros((2, n, n))
    traction[:, rows, cols] = q[:, :h, :w]
    slip = np.zeros((n, n), dtype=bool)
    slip[rows, cols] = (np.hypot(q[0], q[1]) >= limit * (1.0 - 1e-3))[:h, :w] & (limit[:h, :w] > 0)
    return PartialSlipSolution(traction, motion, slip & contact, converged)


MOTIONS = ("none", "slide", "spin", "roll")


@dataclass
class ContactState:
    """Mechanics of one frame on the skin grid.

    Attributes:
        pressure_mpa: (n, n) float64 normal pressure, MPa.
        traction_mpa: (2, n, n) float64 tangential traction (qx, qy), MPa.
        displacement_mm: (3, n, n) float64 skin surface displacement (ux, uy, uz), mm;
            uz toward the camera.
        contact: (n, n) bool contact patch.
        slip: (n, n) bool slip zone (all of the contact in gross slip).
        slip_share: slip-zone area / contact area (0 without contact).
        slip_state: "stick", "incipient" (slip_share >= ContactParams.incipient_share,
            short of gross slip) or "gross" (the friction limit is reached: the object slides
            or spins).
        slip_type: "none" (stick), "translational" or "rotational" (the dominant load ratio).
        normal_N: normal load, N.
        force_N: (2,) tangential load carried by the contact, N (clipped at mu P).
        torque_Nmm: torque carried about the object centre, N*mm.
        converged: False when an iterative solver hit its cap (fields still finite).
    """

    pressure_mpa: np.ndarray
    traction_mpa: np.ndarray
    displacement_mm: np.ndarray
    contact: np.ndarray
    slip: np.ndarray
    slip_share: float
    slip_state: str
    slip_type: str
    normal_N: float
    force_N: np.ndarray
    torque_Nmm: float
    converged: bool

    @property
    def is_slip(self) -> bool:
        """True for incipient or gross slip (the paper labels both as slip)."""
        return self.slip_state != "stick"


class ContactModel:
    """One frame of skin mechanics for an indenter pose and loads, warm-started frame to frame.

    Only the effects asked for are computed: without "shear" and "torsion" no tangential
    traction and no Cerruti FFT; without "normal" nothing at all (zero displacement).
    """

    def __init__(self, skin: SkinParams, params: ContactParams | None = None) -> None:
        self.skin = skin
        self.params = params if params is not None else ContactParams()
        self.grid = SurfaceGrid(skin.mechanics_cells, skin.size_mm / skin.mechanics_cells)
        self.halfspace = HalfSpace(self.grid, skin.material)
        self._soft_halfspaces: dict[float, HalfSpace] = {}  # by contact modulus E*, MPa (`_normal_halfspace`)
        self._mesh = self.grid.mesh_mm()
        self._warm_full: NormalSolution | None = None
        self._warm_reduced: NormalSolution | None = None
        self._warm_partial: PartialSlipSolution | None = None

    def reset(self) -> None:
        """Forget the warm starts (e.g. when a new scene begins)."""
        self._warm_full = self._warm_reduced = None
        self._warm_partial = None

    def _inside(self, centre_mm: np.ndarray, radius_mm: float) -> bool:
        half = self.grid.size_mm / 2.0 - self.grid.cell_mm
        return bool(np.all(np.abs(centre_mm) + radius_mm <= half))

    def normal_solution(self, obj: Indenter, centre_mm: np.ndarray, angle_rad: float, load_N: float, warm: NormalSolution | None) -> NormalSolution:
        """Closed form (Hertz sphere, flat-punch coin) when the patch is on the skin, else Polonsky-Keer."""
        e_star = self.skin.material.contact_modulus_mpa(obj.youngs_modulus_mpa)
        if isinstance(obj, Sphere):
            a = hertz_contact_radius_mm(load_N, obj.radius_mm, e_star)
            if self._inside(centre_mm, a):
                return hertz_solution(self.grid, centre_mm, load_N, obj.radius_mm, e_star)
        if isinstance(obj, Coin) and self._inside(centre_mm, obj.radius_mm):
            return flat_punch_solution(self.grid, centre_mm, load_N, obj.radius_mm, e_star)
        gap = obj.gap_mm(self._mesh[0], self._mesh[1], centre_mm, angle_rad)
        return solve_normal(self._normal_halfspace(e_star), gap, load_N, self.params, warm)

    def _normal_halfspace(self, contact_modulus_mpa: float) -> HalfSpace:
        """The compliance the normal solver presses against: the skin's, and the object's as well when it
        is not rigid by comparison (its compliance over 1e-3 of the skin's: a soft object flattens too,
        as in the Hertz and flat-punch forms, whose E* it shares). The skin's displacements stay the skin's
        own (`halfspace`)."""
        skin = self.skin.material
        skin_modulus = skin.youngs_modulus_mpa / (1.0 - skin.poisson_ratio**2)
        if contact_modulus_mpa >= skin_modulus / (1.0 + 1e-3):
            return self.halfspace
        if contact_modulus_mpa not in self._soft_halfspaces:  # built once per object, not every frame
            material = Elastomer(contact_modulus_mpa * (1.0 - skin.poisson_ratio**2), skin.poisson_ratio)
            self._soft_halfspaces[contact_modulus_mpa] = HalfSpace(self.grid, material)
        return self._soft_halfspaces[contact_modulus_mpa]

    def solve(
        self,
        obj: Indenter,
        centre_mm: np.ndarray,
        angle_rad: float,
        normal_N: float,
        force_N: np.ndarray,
        torque_Nmm: float,
        motion: str,
        motion_direction: np.ndarray,
        effects: frozenset[str],
    ) -> ContactState:
        """Pressure, traction, displacement and slip state of one frame.

        Args:
            obj: the indenter.
            centre_mm: (2,) object centre on the skin, mm.
            angle_rad: object rotation about the skin normal, rad.
            normal_N: normal load, N (>= 0; at 0 nothing is carried, and a tangential load or torque
                is past the friction limit: gross slip).
            force_N: (2,) commanded tangential load, N (ignored while sliding/spinning).
            torque_Nmm: commanded torque about the object centre, N*mm.
            motion: "none", "slide" (kinematic gross translational slip), "spin"
                (kinematic gross rotational slip), "roll" (free rolling: no traction).
            motion_direction: (2,) unit sliding direction for "slide"; its x component's sign
                gives the spin sense for "spin".
            effects: mechanics effects in use ("normal", "shear", "torsion").
        """
        n = self.grid.n_cells
        centre = np.asarray(centre_mm, dtype=np.float64)
        force = np.asarray(force_N, dtype=np.float64)
        if motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
        if centre.shape != (2,) or force.shape != (2,) or not (np.all(np.isfinite(centre)) and np.all(np.isfinite(force)) and np.isfinite(torque_Nmm)):
            raise ValueError(f"centre_mm and force_N must be finite (2,) vectors and torque_Nmm finite, got {centre}, {force}, {torque_Nmm}")
        _check_load("normal_N", normal_N)
        zeros2 = np.zeros((2, n, n))
        tangential = ("shear" in effects or "torsion" in effects) and motion != "roll"
        if "shear" not in effects:
            force = np.zeros(2)
        if "torsion" not in effects:
            torque_Nmm = 0.0
        q_abs = float(np.hypot(*force))
        if "normal" not in effects or normal_N == 0:
            self.reset()
            empty = np.zeros((n, n), dtype=bool)
            state, kind = "stick", "none"
            if "normal" in effects and tangential and motion == "none" and (q_abs > 0 or torque_Nmm):
                # nothing carries a tangential load or a torque with no normal load (its friction limit, mu * 0 N,
                # is passed): gross slip as under any load past the limit, translational before rotational as below
                state, kind = "gross", "translational" if q_abs > 0 else "rotational"
            return ContactState(np.zeros((n, n)), zeros2, np.zeros((3, n, n)), empty, empty, 0.0, state, kind, 0.0, np.zeros(2), 0.0, True)
        full = self.normal_solution(obj, centre, angle_rad, normal_N, self._warm_full)
        self._warm_full = full
        contact = full.contact
        mu = obj.mu
        ratio_t = q_abs / (mu * normal_N)
        ratio_r = 0.0
        if torque_Nmm:  # the torsional limit (a sum over the grid) only for a torque ("torsion": else it is 0 here)
            m_max = torsion_limit_Nmm(self.grid, full.pressure_mpa, mu, centre)
            ratio_r = abs(torque_Nmm) / m_max if m_max > 0 else np.inf
        traction = zeros2
        slip = np.zeros((n, n), dtype=bool)
        converged = full.converged
        state, kind = "stick", "none"
        if tangential and (motion == "slide" or (motion == "none" and ratio_t > 0 and ratio_t + ratio_r >= 1.0 and ratio_t >= ratio_r)):
            direction = motion_direction if motion == "slide" else force / q_abs
            traction = sliding_traction(full.pressure_mpa, mu, direction)
            slip, state, kind = contact, "gross", "translational"
        elif tangential and (motion == "spin" or (motion == "none" and ratio_r > 0 and ratio_t + ratio_r >= 1.0)):
            sign = float(np.sign(motion_direction[0])) if motion == "spin" else float(np.sign(torque_Nmm))
            traction = spinning_traction(self.grid, full.pressure_mpa, mu, centre, sign)
            slip, state, kind = contact, "gross", "rotational"
        elif tangential and ratio_r > 0:
            partial = solve_partial_slip(self.halfspace, full.pressure_mpa, mu, force, torque_Nmm, centre, self.params, self._warm_partial)
            self._warm_partial = partial
            traction, slip, converged = partial.traction_mpa, partial.slip, converged and partial.converged
            kind = "translational" if ratio_t >= ratio_r else "rotational"
        elif tangential and ratio_t > 0:
            reduced = self.normal_solution(obj, centre, angle_rad, normal_N - q_abs / mu, self._warm_reduced)
            self._warm_reduced = reduced
            traction = ciavarella_jaeger_traction(full, reduced, mu, force / q_abs, self.grid.cell_area_mm2)
            slip, converged, kind = contact & ~reduced.contact, converged and reduced.converged, "translational"
        share = float(slip.sum() / max(contact.sum(), 1))
        if state == "stick" and share >= self.params.incipient_share:
            state = "incipient"
        if state == "stick":
            kind = "none"
        has_traction = bool(np.any(traction))
        displacement = self.halfspace.displacement_mm(full.pressure_mpa, traction if has_traction else None)
        carried = traction.sum(axis=(1, 2)) * self.grid.cell_area_mm2
        x, y = self._mesh
        carried_torque = float(np.sum((x - centre[0]) * traction[1] - (y - centre[1]) * traction[0]) * self.grid.cell_area_mm2)
        return ContactState(full.pressure_mpa, traction, displacement, contact, slip, share, state, kind, float(normal_N), carried, carried_torque, converged)
