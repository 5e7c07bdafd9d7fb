"""The node-averaged volume term (softgrasp.physics.nodal_volume): its forces are the gradient of
its energy and its Jacobian their derivative, it obeys Newton's third law inside the body, it is
the per-tet term under any uniform deformation (so the calibration to E and nu holds), and it
removes the volumetric locking that makes the per-tet term's rubber sphere (nu = 0.45) stiffer
than Hertz's contact on every mesh."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from softgrasp.errors import ConfigError
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.explicit import fused_unsupported, simulate, stable_time_step
from softgrasp.sim.integrators import RK4
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import solve_static


@pytest.fixture(scope="module")
def sphere():
    mesh, material, mass = make_object("sphere")
    return build_body(mesh, material, mass=mass, volume="nodal"), build_body(mesh, material, mass=mass)


def _deformed(body, scale=2e-3, seed=0):
    rng = np.random.default_rng(seed)
    return np.asarray(body.mesh.points) + scale * rng.standard_normal((body.n_nodes, 3))


@pytest.mark.parametrize("nu", [0.45, 0.2])
def test_forces_are_the_energy_gradient_and_the_jacobian_their_derivative(sphere, nu):
    """Central differences of the energy along a random direction give -f . d, and of the forces
    the Jacobian's product; the Jacobian is symmetric (a potential's Hessian). At nu = 0.45 the
    volume term has the inversion barrier; at nu = 0.2 its modulus is negative (nu < 1/4: the
    springs alone are too stiff in bulk) and psi the quadratic."""
    body, _ = sphere
    if nu != body.material.nu:
        material = dataclasses.replace(body.material, nu=nu)
        body = build_body(body.mesh, material, mass=body.total_mass, volume="nodal")
        assert body.kappa < 0 and not body.barrier
    x = _deformed(body)
    d = np.random.default_rng(1).standard_normal(x.shape)
    h = 1e-7
    f = body.internal_forces(x)
    slope = (body.internal_energy(x + h * d) - body.internal_energy(x - h * d)) / (2 * h)
    assert slope == pytest.approx(-float(np.sum(f * d)), rel=1e-6)
    J = body.internal_jacobian(x)
    df = (body.internal_forces(x + h * d) - body.internal_forces(x - h * d)).ravel() / (2 * h)
    assert np.abs(J @ d.ravel() - df).max() < 1e-6 * np.abs(df).max()
    assert abs(J - J.T).max() < 1e-9 * abs(J).max()


def test_internal_forces_balance_and_vanish_under_rigid_motion(sphere):
    """Inside the body every force has its reaction: the nodal forces sum to zero with zero
    moment; a rigid rotation and translation of the rest shape carries no force."""
    body, _ = sphere
    x = _deformed(body)
    f = body.internal_forces(x)
    scale = np.abs(f).max()
    assert np.abs(f.sum(axis=0)).max() < 1e-12 * scale * body.n_nodes
    size = float(np.ptp(x, axis=0).max())
    assert np.abs(np.cross(x, f).sum(axis=0)).max() < 1e-12 * scale * size * body.n_nodes
    c, s = math.cos(0.7), math.sin(0.7)
    about_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = about_z @ np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    rigid = np.asarray(body.mesh.points) @ R.T + np.array([0.01, -0.02, 0.03])
    assert np.abs(body.internal_forces(rigid)).max() < 1e-9 * scale


@pytest.mark.parametrize("seed", [0, 1])
def test_under_uniform_deformation_it_is_the_per_tet_term(sphere, seed):
    """x = F X with F near the identity (a uniform stretch, shear and volume change): every node's
    J is every tet's, so forces, energy and stiffness are the per-tet term's to round-off."""
    nodal, element = sphere
    F = np.eye(3) + 0.05 * np.random.default_rng(seed).standard_normal((3, 3))
    x = np.asarray(nodal.mesh.points) @ F.T
    f_n, f_e = nodal.internal_forces(x), element.internal_forces(x)
    assert np.abs(f_n - f_e).max() < 1e-9 * np.abs(f_e).max()
    assert nodal.internal_energy(x) == pytest.approx(element.internal_energy(x), rel=1e-9)
    d = np.random.default_rng(7).standard_normal(3 * nodal.n_nodes)
    # the stiffness differs off the uniform modes; along an affine direction it is the same
    G = np.random.default_rng(8).standard_normal((3, 3))
    affine = (np.asarray(nodal.mesh.points) @ G.T).ravel()
    assert affine @ (nodal.internal_jacobian(x) @ affine) == pytest.approx(
        affine @ (element.internal_jacobian(x) @ affine), rel=1e-9
    )
    assert np.isfinite(nodal.internal_jacobian(x) @ d).all()


R_TIP = 0.008


def _squeeze(mesh_size: float, volume: str, travel: float = 2e-3, exact_body: bool = False) -> np.ndarray:
    """Force over Hertz's of two rigid 8 mm fingertips squeezing the rubber sphere (R = 64 mm,
    nu = 0.45) on the table across its equator, each ``travel`` past first touch, (2,). Hertz:
    each contact's approach delta gives F = 4/3 E* sqrt(R_eff) delta^1.5, 1 / R_eff = 1 / R_tip +
    1 / R_sphere (the sphere's far field is part of Hertz's approach). The fingertips have
    friction (mu = 0.5) only to hold the sphere's spin about the vertical; by symmetry they load
    it along the squeeze."""
    mesh, material, mass = make_object("sphere", mesh_size)
    body = build_body(mesh, material, mass=mass, volume=volume)
    x0 = np.asarray(mesh.points)
    Rs = 0.5 * float(np.ptp(x0[:, 2]))
    c = x0.mean(axis=0)
    c[2] = x0[:, 2].min() + Rs
    params = ContactParams(mu=0.5)

    def tips(gap):
        return FingertipContact(
            (
                Fingertip(R_TIP, centre=c + [gap, 0.0, 0.0], velocity=[-1.0, 0.0, 0.0]),
                Fingertip(R_TIP, centre=c - [gap, 0.0, 0.0], velocity=[1.0, 0.0, 0.0]),
            ),
            params,
        )

    lo, hi = Rs + R_TIP - 0.01, Rs + R_TIP + 0.01  # first touch of both, on the rest mesh
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if tips(mid).init_state(body, x0).active.any(axis=1).all() else (lo, mid)
    fc = tips(hi)
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.8)
    scene = Scene(body, (table, fc))
    state, cache, before = scene.initial_state(), SolverCache(exact_body=exact_body), None
    for k, t in enumerate(np.linspace(0.0, travel, 9)[1:]):
        # Newton starts from the last two rests extrapolated (the start, unsettled, is not one:
        # extrapolated, its drop onto the table would start the solve deep in it).
        guess = None if k < 2 else 2.0 * state.x - before
        before = state.x.copy()
        state, _ = solve_static(scene, state, t=float(t), cache=cache, guess=guess)
    rep = fc.report(body, state.x, state.v, state.t, state.contacts[1], static=True)
    Es = material.E / (1 - material.nu**2)
    r_eff = 1.0 / (1.0 / R_TIP + 1.0 / Rs)
    return np.linalg.norm(rep.force, axis=1) / (4.0 / 3.0 * Es * math.sqrt(r_eff) * travel**1.5)


def test_the_nodal_term_squeezes_the_rubber_sphere_as_hertz_where_the_per_tet_term_locks():
    """Squeezed 2 mm between two fingertips (contact radius ~3.8 mm), the sphere of 388, 745 and
    2 196 nodes gives 0.94-1.07 times Hertz's force with the nodal term at each fingertip;
    the per-tet term 1.19-1.31 times, on every mesh: volumetric locking, not the contact law
    (at nu = 0.3 the per-tet term comes within 3 % on the finer meshes)."""
    for h in (0.016, 0.012, 0.008):
        nodal = _squeeze(h, "nodal")
        element = _squeeze(h, "element")
        assert (np.abs(nodal - 1.0) < 0.10).all(), (h, nodal)
        assert (element > 1.15).all(), (h, element)


def test_the_fused_stepper_leaves_a_nodal_body_to_the_per_step_path_which_conserves_energy(sphere):
    """Without damping, gravity or contact, a nodal body set vibrating keeps its energy under RK4
    (the per-step path: the fused kernels sum the per-tet term); its momentum stays zero. Steps
    of a quarter of the stable bound: at the bound itself RK4 damps the highest modes the random
    velocities excite (5e-5 of the energy lost at a quarter, 3.5 % at the bound)."""
    nodal, _ = sphere
    mesh = nodal.mesh
    mass = nodal.total_mass
    body = build_body(mesh, nodal.material, mass=mass, damping_ratio=0.0, gravity=0.0, volume="nodal")
    scene = Scene(body, ())
    assert "nodal volume term" in fused_unsupported(scene, RK4())
    rng = np.random.default_rng(3)
    v = 0.05 * rng.standard_normal((body.n_nodes, 3))
    v -= (body.mass @ v) / body.total_mass  # no net momentum
    state = State(np.asarray(mesh.points).copy(), v, 0.0, ())
    e0 = scene.kinetic_energy(v) + body.internal_energy(state.x)
    end = simulate(scene, state, 0.01, dt=stable_time_step(scene) / 4)
    e1 = scene.kinetic_energy(end.v) + body.internal_energy(end.x)
    assert e1 == pytest.approx(e0, rel=2e-4)
    assert np.abs(body.mass @ end.v).max() < 1e-12 * float(np.abs(body.mass @ np.abs(v)).max())


def test_an_unknown_volume_term_is_refused(sphere):
    body, _ = sphere
    with pytest.raises(ConfigError, match="volume term 'per-edge' is unknown; choose one of element, nodal"):
        build_body(body.mesh, body.material, mass=body.total_mass, volume="per-edge")


def test_a_plan_with_the_nodal_term_holds_at_the_same_forces_and_squeezes_deeper():
    """``sg.plan`` of the sphere loaded with ``volume_term="nodal"`` records the term in plan.json;
    its set-points (the least forces that hold, times the safety factor: friction and weight set
    them) are within 3 % of the per-tet body's, while the unlocked body lets the fingertips in
    further and strains more under them."""
    import softgrasp as sg

    element = sg.plan(sg.load_object("sphere"))
    nodal = sg.plan(sg.load_object("sphere", volume_term="nodal"))
    assert nodal.document["object"]["volume_term"] == "nodal"
    assert element.document["object"]["volume_term"] == "element"
    for name, force in element.setpoints_N.items():
        assert nodal.setpoints_N[name] == pytest.approx(force, rel=0.03), name
    pen = {g: np.array([f.penetration for f in r.grasp.fingers]) for g, r in (("e", element), ("n", nodal))}
    assert (pen["n"] > pen["e"]).all()
    assert nodal.grasp.damage.strain > element.grasp.damage.strain


def test_an_unknown_volume_term_in_a_config_file_names_the_choices(tmp_path):
    from softgrasp.api.planning import plan_options

    conf = tmp_path / "plan.toml"
    conf.write_text('volume_term = "per-tet"\n')
    with pytest.raises(ConfigError, match="volume_term must be element or nodal, got 'per-tet'"):
        plan_options({}, str(conf))


@pytest.mark.slow
def test_calibration_fits_with_the_volume_term_it_will_be_used_with(tmp_path):
    """A compression curve (sticking platens, 20 %) simulated with a nodal body of E = 100 kPa,
    nu = 0.45: fitted with the nodal term it gives E back (0.99998 of it); fitted with the per-tet
    term, whose locked body is stiffer, 0.983 of it: the fit simulates the term it is told."""
    from softgrasp.experiments.calibration import fit_compression, read_compression_data, specimen_geometry
    from softgrasp.experiments.compression import compression_test
    from softgrasp.model.material import Material

    mesh, _, mass = make_object("cube")
    true = Material(1.0e5, 0.45, 100.0)
    body = build_body(mesh, true, mass=mass, volume="nodal")
    res = compression_test(body, strain=0.2, steps=10, plate_friction=0.5)
    csv = tmp_path / "c.csv"
    rows = zip(res.displacement_m[1:], res.force_N[1:], strict=True)
    csv.write_text("displacement_m,force_N\n" + "\n".join(f"{d:.9g},{f:.9g}" for d, f in rows) + "\n")
    data = read_compression_data(csv, *specimen_geometry(mesh))
    fitted = {
        vol: fit_compression(mesh, data, nu=0.45, mass=mass, law="linear", E_start=6e4, volume=vol)[0].E
        for vol in ("nodal", "element")
    }
    assert fitted["nodal"] == pytest.approx(true.E, rel=1e-3)
    assert fitted["element"] < 0.99 * true.E


def test_newton_factorises_the_per_tet_matrix_of_a_large_nodal_body_and_corrects_its_products(monkeypatch):
    """Above NODAL_DIRECT_MAX_NODES the Newton matrix of a nodal body is the per-tet term's (its
    sparsity: a quarter of the blocks) and the correction turns its products into the exact
    Jacobian's, unless the solver cache asks for the exact matrix (``exact_body``); the three
    paths reach the same rest of the sphere squeezed 2 mm (to the solves' tolerance; asked for, the
    exact matrix gives the small body's own path exactly)."""
    import softgrasp.physics.body as body_module

    mesh, material, mass = make_object("sphere")
    body = build_body(mesh, material, mass=mass, volume="nodal")
    x = _deformed(body)
    assert body.newton_correction(x) is None  # 388 nodes: the exact matrix
    monkeypatch.setattr(body_module, "NODAL_DIRECT_MAX_NODES", 0)
    A = -body.newton_jacobian(x)
    assert A.nnz == build_body(mesh, material, mass=mass).internal_jacobian(x).nnz
    v = np.random.default_rng(2).standard_normal(3 * body.n_nodes)
    product = A @ v
    body.newton_correction(x)(v, product)
    exact = -(body.internal_jacobian(x) @ v)
    assert np.abs(product - exact).max() < 1e-12 * np.abs(exact).max()
    assert body.newton_correction(x, exact=True) is None
    assert (body.newton_jacobian(x, exact=True) != body.internal_jacobian(x)).nnz == 0
    approximated = _squeeze(0.016, "nodal")
    asked_exact = _squeeze(0.016, "nodal", exact_body=True)
    monkeypatch.setattr(body_module, "NODAL_DIRECT_MAX_NODES", 10**9)
    direct = _squeeze(0.016, "nodal")
    assert approximated == pytest.approx(direct, rel=1e-6)
    assert np.array_equal(asked_exact, direct)  # the same matrices, bit for bit (the GMRES path: ~1e-11)
