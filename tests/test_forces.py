"""Forces are minus the gradient of their energy; Jacobians are the derivatives of the forces."""

from __future__ import annotations

import numpy as np
import pytest

from softgrasp.model.material import Linear, Material, Polynomial, Tabulated
from softgrasp.model.mesh import box, signed_volumes
from softgrasp.physics.body import build_body
from softgrasp.physics.springs import edge_damping_forces, spring_forces

LAWS = {
    "linear": Linear(),
    "polynomial": Polynomial(a2=-0.4, a3=1.5),
    "tabulated": Tabulated(np.array([0.05, 0.1, 0.2, 0.3]), np.array([5e3, 1.1e4, 2.6e4, 5e4])),
}


def _fd_gradient(fun, x: np.ndarray, h: float) -> np.ndarray:
    g = np.zeros_like(x)
    for idx in np.ndindex(*x.shape):
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        g[idx] = (fun(xp) - fun(xm)) / (2 * h)
    return g


@pytest.fixture(scope="module")
def perturbed():
    mesh = box(0.04, 2)
    rng = np.random.default_rng(7)
    x = mesh.points + 0.001 * rng.standard_normal(mesh.points.shape)
    assert (signed_volumes(x, mesh.tets) > 0.3 * mesh.volumes).all()
    return mesh, x


@pytest.mark.parametrize("law", LAWS.values(), ids=LAWS.keys())
@pytest.mark.parametrize("nu", [0.2, 0.45])
def test_internal_forces_are_minus_energy_gradient(perturbed, law, nu):
    mesh, x = perturbed
    body = build_body(mesh, Material(1e5, nu, 50.0, law))
    f = body.internal_forces(x)
    g = _fd_gradient(body.internal_energy, x, 1e-7)
    assert np.abs(f + g).max() < 1e-6 * np.abs(f).max()


@pytest.mark.parametrize("law", LAWS.values(), ids=LAWS.keys())
@pytest.mark.parametrize("nu", [0.2, 0.45])
def test_internal_jacobian_matches_finite_differences(perturbed, law, nu):
    mesh, x = perturbed
    body = build_body(mesh, Material(1e5, nu, 50.0, law))
    J = body.internal_jacobian(x).toarray()
    h = 1e-7
    Jfd = np.zeros_like(J)
    flat = x.ravel()
    for i in range(flat.size):
        xp, xm = flat.copy(), flat.copy()
        xp[i] += h
        xm[i] -= h
        Jfd[:, i] = (
            body.internal_forces(xp.reshape(-1, 3)) - body.internal_forces(xm.reshape(-1, 3))
        ).ravel() / (2 * h)
    assert np.abs(J - Jfd).max() < 1e-5 * np.abs(J).max()
    # A conservative force field has a symmetric Jacobian.
    assert np.abs(J - J.T).max() < 1e-10 * np.abs(J).max()


def test_single_linear_spring_hooke():
    """One spring of stiffness k stretched by d pulls its ends together with force k d."""
    x = np.array([[0.0, 0.0, 0.0], [0.013, 0.0, 0.0]])
    f, e = spring_forces(x, np.array([[0, 1]]), np.array([0.01]), np.array([250.0]), Linear())
    np.testing.assert_allclose(f, [[250 * 0.003, 0, 0], [-250 * 0.003, 0, 0]], rtol=1e-12)
    assert e == pytest.approx(0.5 * 250 * 0.003**2, rel=1e-12)


def test_internal_forces_have_no_net_force_or_torque(perturbed):
    """Internal forces cancel in force and moment (Newton's third law between nodes)."""
    mesh, x = perturbed
    body = build_body(mesh, Material(1e5, 0.45, 50.0, LAWS["polynomial"]))
    v = np.random.default_rng(1).standard_normal(x.shape)
    f = body.internal_forces(x, v)
    assert np.abs(f.sum(axis=0)).max() < 1e-10 * np.abs(f).max()
    assert np.abs(np.cross(x, f).sum(axis=0)).max() < 1e-10 * np.abs(f).max() * 0.05


def test_edge_damping_ignores_rigid_motion(perturbed):
    mesh, x = perturbed
    body = build_body(mesh, Material(1e5, 0.3, 50.0))
    omega = np.array([0.3, -1.0, 2.0])
    v = np.array([0.1, 0.2, -0.3]) + np.cross(omega, x)
    f = edge_damping_forces(x, v, body.edges, body.damping)
    assert np.abs(f).max() < 1e-12
