"""Half-space Green's functions and contact solutions against closed-form answers."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from fv_algos.sim.contact import (
    ContactModel,
    ContactParams,
    cattaneo_mindlin_stick_radius_mm,
    hertz_contact_radius_mm,
    hertz_torsion_limit_Nmm,
    solve_normal,
    solve_partial_slip,
    torsion_limit_Nmm,
)
from fv_algos.sim.halfspace import HalfSpace, SurfaceGrid
from fv_algos.sim.objects import SHAPES, Coin, Corner, Sphere
from fv_algos.sim.skin import Elastomer, SkinParams, marker_grid_mm

MATERIAL = Elastomer()
E_STAR = MATERIAL.contact_modulus_mpa(Sphere().youngs_modulus_mpa)
NORMAL = frozenset({"normal"})
ALL = frozenset({"normal", "shear", "torsion"})


@pytest.fixture(scope="module")
def fine() -> HalfSpace:
    return HalfSpace(SurfaceGrid(128, 24.0 / 128), MATERIAL)


@pytest.fixture(scope="module")
def sphere_contact(fine: HalfSpace):
    x, y = fine.grid.mesh_mm()
    gap = (x**2 + y**2) / (2 * 10.0)
    return gap, solve_normal(fine, gap, 2.0, ContactParams())


def test_marker_grid_is_centred_16x16() -> None:
    m = marker_grid_mm(SkinParams())
    assert m.shape == (256, 2)
    np.testing.assert_allclose(m.mean(axis=0), 0.0, atol=1e-12)
    assert m[:, 0].max() == pytest.approx(11.25)
    with pytest.raises(ValueError, match="pitch_mm"):
        SkinParams(pitch_mm=-1)


def test_uniform_disc_centre_displacement(fine: HalfSpace) -> None:
    x, y = fine.grid.mesh_mm()
    p = (np.hypot(x, y) <= 3.0).astype(float)
    a = np.sqrt(p.sum() * fine.grid.cell_area_mm2 / np.pi)
    uz = fine.normal_displacement_mm(p)[63:65, 63:65].mean()
    expected = 2 * (1 - MATERIAL.poisson_ratio**2) * a / MATERIAL.youngs_modulus_mpa
    assert uz == pytest.approx(expected, rel=0.005)


def test_cerruti_hertzian_traction(fine: HalfSpace) -> None:
    # Johnson (1985) eq. 7.40: q0 sqrt(1 - r^2/a^2) along x gives
    # ux = pi q0 / (32 G a) [4 (2 - nu) a^2 - (4 - 3 nu) x^2 - (4 - nu) y^2] inside.
    x, y = fine.grid.mesh_mm()
    a, q0, nu, g = 3.0, 0.1, MATERIAL.poisson_ratio, MATERIAL.shear_modulus_mpa
    q = q0 * np.sqrt(np.clip(1 - (x**2 + y**2) / a**2, 0, None))
    u = fine.displacement_mm(None, np.stack([q, 0 * q]))
    inside = np.hypot(x, y) < 0.9 * a
    expected = np.pi * q0 / (32 * g * a) * (4 * (2 - nu) * a**2 - (4 - 3 * nu) * x**2 - (4 - nu) * y**2)
    assert np.max(np.abs(u[0] - expected)[inside]) < 0.01 * expected.max()
    # The surface ahead of the load sinks toward the camera (+z), behind rises: antisymmetric.
    np.testing.assert_allclose(u[2], -u[2][:, ::-1], atol=1e-12)


def test_numerical_normal_contact_matches_hertz(sphere_contact) -> None:
    _, sol = sphere_contact
    grid_area = (24.0 / 128) ** 2
    a = hertz_contact_radius_mm(2.0, 10.0, E_STAR)
    assert np.sqrt(sol.contact.sum() * grid_area / np.pi) == pytest.approx(a, rel=0.02)
    assert sol.approach_mm == pytest.approx(a * a / 10.0, rel=0.02)
    assert sol.pressure_mpa.sum() * grid_area == pytest.approx(2.0, rel=1e-9)
    assert sol.converged


def test_ciavarella_jaeger_stick_radius(fine: HalfSpace, sphere_contact) -> None:
    gap, full = sphere_contact
    mu, q = 0.8, 0.8
    reduced = solve_normal(fine, gap, 2.0 - q / mu, ContactParams(), warm=full)
    c_over_a = np.sqrt(reduced.contact.sum() / full.contact.sum())
    expected = cattaneo_mindlin_stick_radius_mm(1.0, q, 2.0, mu)
    assert c_over_a == pytest.approx(expected, rel=0.05)


def test_numerical_partial_slip_matches_cattaneo_mindlin(fine: HalfSpace, sphere_contact) -> None:
    _, full = sphere_contact
    mu, q = 0.8, 0.8
    sol = solve_partial_slip(fine, full.pressure_mpa, mu, np.array([q, 0.0]), 0.0, np.zeros(2), ContactParams())
    stick = full.contact & ~sol.slip
    assert np.sqrt(stick.sum() / full.contact.sum()) == pytest.approx((1 - q / (mu * 2.0)) ** (1 / 3), rel=0.05)
    assert sol.traction_mpa[0].sum() * fine.grid.cell_area_mm2 == pytest.approx(q, rel=0.01)
    assert sol.converged


def test_torsion_limit_and_partial_twist(fine: HalfSpace, sphere_contact) -> None:
    _, full = sphere_contact
    mu = 0.8
    a = hertz_contact_radius_mm(2.0, 10.0, E_STAR)
    m_max = torsion_limit_Nmm(fine.grid, full.pressure_mpa, mu, np.zeros(2))
    assert m_max == pytest.approx(hertz_torsion_limit_Nmm(mu, 2.0, a), rel=0.02)
    sol = solve_partial_slip(fine, full.pressure_mpa, mu, np.zeros(2), 0.6 * m_max, np.zeros(2), ContactParams())
    x, y = fine.grid.mesh_mm()
    torque = np.sum(x * sol.traction_mpa[1] - y * sol.traction_mpa[0]) * fine.grid.cell_area_mm2
    assert torque == pytest.approx(0.6 * m_max, rel=0.01)
    share = sol.slip.sum() / full.contact.sum()
    assert 0.05 < share < 0.95  # a slip annulus and a stick core
    stick = full.contact & ~sol.slip
    assert np.hypot(x[stick], y[stick]).max() < np.hypot(x[sol.slip], y[sol.slip]).min() + 2 * fine.grid.cell_mm


@pytest.fixture()
def model() -> ContactModel:
    return ContactModel(SkinParams())


def _solve(model: ContactModel, obj=Sphere(), centre=(0.0, 0.0), normal=2.0, force=(0.0, 0.0), torque=0.0, effects=ALL):
    return model.solve(obj, np.array(centre), 0.0, normal, np.array(force), torque, "none", np.zeros(2), effects)


def test_model_loads_are_carried(model: ContactModel) -> None:
    area = model.grid.cell_area_mm2
    s = _solve(model, force=(0.5, -0.3))
    assert s.pressure_mpa.sum() * area == pytest.approx(2.0, rel=0.01)
    np.testing.assert_allclose(s.traction_mpa.sum(axis=(1, 2)) * area, [0.5, -0.3], rtol=0.01)
    s = _solve(model, obj=Corner(), torque=0.5)
    assert s.torque_Nmm == pytest.approx(0.5, rel=0.01)


def test_gross_slip_starts_exactly_at_friction_limit(model: ContactModel) -> None:
    mu = Sphere().mu
    assert _solve(model, force=(0.999 * mu * 2.0, 0.0)).slip_state != "gross"
    gross = _solve(model, force=(mu * 2.0, 0.0))
    assert (gross.slip_state, gross.slip_type) == ("gross", "translational")
    m_max = torsion_limit_Nmm(model.grid, _solve(model).pressure_mpa, mu, np.zeros(2))
    assert _solve(model, torque=0.999 * m_max).slip_state != "gross"
    spin = _solve(model, torque=m_max)
    assert (spin.slip_state, spin.slip_type) == ("gross", "rotational")


def test_incipient_threshold_and_effects(model: ContactModel) -> None:
    mu = Sphere().mu
    # Hertz: slip share = 1 - (1 - Q/muP)^(2/3) crosses 0.5 at Q/muP = 0.646.
    assert _solve(model, force=(0.55 * mu * 2, 0.0)).slip_state == "stick"
    s = _solve(model, force=(0.8 * mu * 2, 0.0))
    assert (s.slip_state, s.slip_type) == ("incipient", "translational")
    normal_only = _solve(model, force=(0.8 * mu * 2, 0.0), effects=NORMAL)
    assert not np.any(normal_only.traction_mpa) and normal_only.slip_state == "stick"


def test_a_sharp_indenter_never_goes_through_the_skin(model: ContactModel) -> None:
    """The normal solver's first contact set can be one cell, where the CG step is zero: it stopped
    there as converged with the whole load on that cell, the rest of the indenter inside the skin
    (1 cell, 16.9 MPa, 9.6 mm deep at this pose; 61 cells, 1.5 mm turned by 90 degrees)."""
    rng = np.random.default_rng(0)
    poses = [((0.234, -1.367), 0.0)] + [(tuple(rng.uniform(-2, 2, 2)), rng.uniform(0, 2 * np.pi)) for _ in range(20)]
    for centre, angle in poses:
        obj = Corner(fillet_mm=0.7086, youngs_modulus_mpa=168741.0)
        model.reset()
        sol = model.normal_solution(obj, np.array(centre), angle, 2.55, None)
        gap = obj.gap_mm(*model.grid.mesh_mm(), np.array(centre), angle)
        through = gap - gap.min() + model.halfspace.normal_displacement_mm(sol.pressure_mpa) - sol.approach_mm
        assert sol.contact.sum() > 20 and through[~sol.contact].min() > -0.01, (centre, angle)


@pytest.mark.parametrize("shape", ["key", "edge", "bottle_cap", "pen"])
def test_a_torque_on_a_long_contact_is_carried(model: ContactModel, shape: str) -> None:
    """Broyden started from the stiffness of a circular contact: far too soft for a key's blade, so its
    first step overshot into gross slip, where the loads stop changing, and the solve ended in
    'Singular matrix' (fv sim of a key twisted by 0.5 N mm)."""
    obj = SHAPES[shape](mu=0.5)
    for torque in (0.03, 0.3, 0.5):
        model.reset()
        s = model.solve(obj, np.zeros(2), 0.0, 1.0, np.zeros(2), torque, "none", np.zeros(2), ALL)
        limit = torsion_limit_Nmm(model.grid, s.pressure_mpa, obj.mu, np.zeros(2))
        if s.slip_state != "gross":  # carried to the solver's tolerance, a share of the torsion limit
            assert s.converged, (shape, torque)
            assert s.torque_Nmm == pytest.approx(torque, abs=ContactParams().tangential_tolerance * limit), (shape, torque)


def test_a_soft_object_flattens_in_the_numerical_solver_too(model: ContactModel) -> None:
    """Only the closed forms used the object's modulus: a 0.3 MPa sphere near the skin's edge, where the
    solver takes over from Hertz, had its contact drop from 51 to 24 mm^2 between two frames 0.2 mm apart;
    a key's contact was 13.5 mm^2 whatever its modulus."""
    soft = Sphere(youngs_modulus_mpa=0.3)
    areas = []
    for x in np.arange(6.0, 9.01, 0.2):  # across the switch from Hertz to the solver
        model.reset()
        areas.append(_solve(model, obj=soft, centre=(x, 0.0), effects=NORMAL).contact.sum() * model.grid.cell_area_mm2)
    assert max(areas) / min(areas) < 1.1, np.round(areas, 1)
    assert min(areas) == pytest.approx(np.pi * hertz_contact_radius_mm(2.0, 10.0, MATERIAL.contact_modulus_mpa(0.3)) ** 2,
                                       rel=0.1)
    key = [_solve(model, obj=SHAPES["key"](youngs_modulus_mpa=e), effects=NORMAL).contact.sum() for e in (0.3, 3000.0)]
    assert key[0] > 1.5 * key[1]


def test_zero_load_gives_zero_displacement(model: ContactModel) -> None:
    s = _solve(model, normal=0.0, force=(0.0, 0.0))
    assert not np.any(s.displacement_mm) and s.contact.sum() == 0


@pytest.mark.parametrize("force, torque, kind", [((1.0, 0.0), 0.0, "translational"), ((0.0, 0.0), 2.0, "rotational"),
                                                 ((0.3, 0.4), 2.0, "translational")])
def test_a_tangential_load_with_no_normal_load_is_gross_slip(model: ContactModel, force: tuple, torque: float, kind: str) -> None:
    """mu * 0 N carries nothing: the load is past the friction limit (it was 'stick', the load dropped)."""
    s = _solve(model, normal=0.0, force=force, torque=torque)
    assert (s.slip_state, s.slip_type) == ("gross", kind)
    assert not (s.contact.any() or s.traction_mpa.any() or s.displacement_mm.any() or s.force_N.any())
    assert _solve(model, normal=0.0, force=force, torque=torque, effects=NORMAL).slip_state == "stick"  # not asked for
    rolling = model.solve(Sphere(), np.zeros(2), 0.0, 0.0, np.array(force), torque, "roll", np.zeros(2), ALL)
    assert rolling.slip_state == "stick"  # rolling: no traction


def test_mirror_symmetry(model: ContactModel) -> None:
    s = _solve(model, obj=Corner(), force=(0.6, 0.0))
    ux, uy, uz = s.displacement_mm
    # Corner profile is mirror symmetric about y = 0; a load along x keeps that symmetry.
    np.testing.assert_allclose(ux, ux[::-1, :], atol=1e-6 * np.abs(ux).max())
    np.testing.assert_allclose(uy, -uy[::-1, :], atol=1e-6 * np.abs(ux).max())
    np.testing.assert_allclose(uz, uz[::-1, :], atol=1e-6 * np.abs(uz).max())


@pytest.mark.parametrize(
    "kwargs",
    [
        {"obj": Sphere(mu=1e-3), "force": (0.1, 0.0)},
        {"obj": Sphere(mu=1e3), "force": (0.5, 0.0), "torque": 0.3},
        {"normal": 200.0, "force": (10.0, 0.0)},
        {"obj": Coin(radius_mm=40.0), "force": (0.3, 0.0)},
        {"centre": (11.5, 0.0), "force": (0.2, 0.1)},
        {"normal": 1e-9},
    ],
    ids=["mu_tiny", "mu_huge", "huge_load", "bigger_than_skin", "off_edge", "zero_size"],
)
def test_extremes_stay_finite(model: ContactModel, kwargs: dict) -> None:
    s = _solve(model, **kwargs)
    for arr in (s.pressure_mpa, s.traction_mpa, s.displacement_mm):
        assert np.all(np.isfinite(arr))
    assert s.pressure_mpa.sum() * model.grid.cell_area_mm2 == pytest.approx(kwargs.get("normal", 2.0), rel=0.01)


def test_bad_inputs_raise(model: ContactModel) -> None:
    with pytest.raises(ValueError, match="normal_N"):
        _solve(model, normal=-1.0)
    with pytest.raises(ValueError, match="motion"):
        model.solve(Sphere(), np.zeros(2), 0.0, 1.0, np.zeros(2), 0.0, "fly", np.zeros(2), ALL)
    with pytest.raises(ValueError, match="radius_mm"):
        Sphere(radius_mm=0.0)


@pytest.mark.parametrize("load, modulus", [(1e160, MATERIAL.youngs_modulus_mpa), (5e-324, MATERIAL.youngs_modulus_mpa),
                                            (1.0, 1e-300)])
def test_loads_and_moduli_past_the_float_range_are_refused_by_name(load: float, modulus: float) -> None:
    """The solver looped for ever (its approach NaN) on these; now a ValueError names both. The
    half-space itself is built without an overflow."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        halfspace = HalfSpace(SurfaceGrid(16, 0.375), Elastomer(modulus, MATERIAL.poisson_ratio))
    assert np.isfinite(halfspace.tangential_norm_mm_per_mpa)
    x = np.arange(16) * 0.375
    gap = ((x[:, None] - 3.0) ** 2 + (x[None] - 3.0) ** 2) / 20.0
    with pytest.raises(ValueError, match=re.escape(f"load_N {load:g} N against a Young's modulus of {modulus:g} MPa")):
        solve_normal(halfspace, gap, load, ContactParams())


def test_every_shape_presses_and_carries_the_load(model: ContactModel) -> None:
    rng = np.random.default_rng(3)
    assert len(SHAPES) >= 12
    for name, cls in SHAPES.items():
        s = _solve(model, obj=cls.random(rng), normal=2.0, effects=NORMAL)
        assert s.contact.any(), name
        assert s.pressure_mpa.sum() * model.grid.cell_area_mm2 == pytest.approx(2.0, rel=1e-6), name
        assert s.displacement_mm[2].max() > 0, name  # pushed toward the camera


@pytest.mark.parametrize("effects, torque, limits", [
    (NORMAL, 0.0, 0), (frozenset({"normal", "shear"}), 0.0, 0), (ALL, 0.0, 0),
    (NORMAL, 1.0, 0),  # a torque without "torsion" is not modelled
    (ALL, 1.0, 2),  # the twist's gross-slip test, and the partial-slip solve's scale
])
def test_the_torsional_limit_is_computed_only_for_a_torque_the_scene_models(
        model: ContactModel, monkeypatch: pytest.MonkeyPatch, effects: frozenset, torque: float, limits: int) -> None:
    """It was computed on every frame (about a tenth of a normal-only solve)."""
    import fv_algos.sim.contact as contact
    calls = []
    monkeypatch.setattr(contact, "torsion_limit_Nmm", lambda *args: calls.append(args) or torsion_limit_Nmm(*args))
    state = _solve(model, force=(0.3, 0.0), torque=torque, effects=effects)
    assert len(calls) == limits and state.slip_state != "gross"
