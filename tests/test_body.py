"""The calibrated mass-spring body: masses, affine elasticity, uniaxial E and nu, errors."""

from __future__ import annotations

import numpy as np
import pytest

from softgrasp.errors import MaterialError
from softgrasp.experiments.compression import compression_test
from softgrasp.model.material import Material
from softgrasp.model.mesh import box, sphere
from softgrasp.physics.body import build_body


def _isotropic_tensor(E: float, nu: float) -> np.ndarray:
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    d = np.eye(3)
    return lam * np.einsum("ij,kl->ijkl", d, d) + mu * (
        np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d)
    )


def test_lumped_masses():
    mesh = box(0.05, 3)
    body = build_body(mesh, Material(1e5, 0.3, 80.0))
    assert body.total_mass == pytest.approx(80.0 * 0.05**3, rel=1e-12)
    body = build_body(mesh, Material(1e5, 0.3, 80.0), mass=0.02)
    assert body.total_mass == pytest.approx(0.02, rel=1e-12)
    # Each tet gives a quarter of its mass to each node: first-moment of mass = centroid.
    com = (body.mass[:, None] * mesh.points).sum(axis=0) / body.total_mass
    np.testing.assert_allclose(com, mesh.centroid, atol=1e-12)


@pytest.mark.parametrize("mesh_kind", ["box", "sphere"])
@pytest.mark.parametrize("nu", [0.1, 0.25, 0.39, 0.45])
def test_affine_energy_matches_isotropic_elasticity(mesh_kind, nu):
    """Under a homogeneous strain eps, the network's energy is V/2 eps:C:eps with C the isotropic
    tensor of (E, nu): the direction re-weighting and the volume term reproduce both constants."""
    mesh = box(0.05, 3) if mesh_kind == "box" else sphere(0.05, 0.02)
    E = 2e5
    body = build_body(mesh, Material(E, nu, 50.0))
    C = _isotropic_tensor(E, nu)
    rng = np.random.default_rng(3)
    X = np.asarray(mesh.points)
    for _ in range(4):
        a = rng.standard_normal((3, 3))
        eps = 1e-6 * (a + a.T)
        x = X + (X - X.mean(axis=0)) @ eps.T
        expected = 0.5 * mesh.volume * np.einsum("ij,ijkl,kl->", eps, C, eps)
        assert body.internal_energy(x) == pytest.approx(expected, rel=1e-4)


def test_van_gelder_alone_is_anisotropic_on_a_structured_box():
    mesh = box(0.05, 6)
    raw = build_body(mesh, Material(1e5, 0.25, 50.0), isotropize=False)
    fixed = build_body(mesh, Material(1e5, 0.25, 50.0))
    assert raw.calibration.anisotropy_before > 0.05
    assert fixed.calibration.anisotropy_after < 1e-10


def test_direction_sums_from_moments_equal_the_direct_sums():
    """The calibration's sums over springs and probe directions, D(m) = sum_e w_e (n_e . m)^4 and
    the re-weighted ones sum_e w_e (n_e . m)^4 n_e^alpha, taken from the directions' fourth and
    eighth moments, equal the sums taken term by term."""
    from softgrasp.model import network
    rng = np.random.default_rng(3)
    n = rng.standard_normal((5000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    w = rng.uniform(0.1, 2.0, len(n))
    probe = network.sphere_directions(50)
    direct = ((n @ probe.T) ** 4).T @ w
    np.testing.assert_allclose(network.affine_tensor_quartic(w, n, probe), direct, rtol=1e-12, atol=0)
    mono = np.stack([n[:, 0] ** a * n[:, 1] ** b * n[:, 2] ** (4 - a - b) for a in range(5) for b in range(5 - a)], 1)
    direct = ((n @ probe.T) ** 4).T @ (w[:, None] * mono)
    np.testing.assert_allclose(network._reweighting_matrix(w, n, probe), direct, rtol=1e-12, atol=1e-14 * np.abs(direct).max())


@pytest.mark.parametrize("nu", [0.25, 0.39, 0.45])
def test_uniaxial_compression_recovers_E_and_nu(nu):
    """Lubricated small-strain compression of a box: apparent E within 10 %, nu within 0.05."""
    E = 1e5
    body = build_body(box(0.05, 6), Material(E, nu, 100.0))
    res = compression_test(body, strain=0.01, steps=2, fit_strain=0.01)
    assert res.apparent_E_Pa == pytest.approx(E, rel=0.10)
    assert res.apparent_nu == pytest.approx(nu, abs=0.05)
    # Equilibrium: bottom plate carries the top plate's force plus the weight.
    assert res.bottom_force_N[-1] == pytest.approx(res.force_N[-1] + body.total_mass * 9.80665, rel=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mass": 0.0}, r"mass = 0.0 kg is invalid"),
        ({"mass": -1.0}, r"must be > 0"),
        ({"damping_ratio": -0.1}, r"damping ratio = -0.1 is invalid"),
        ({"gravity": float("inf")}, r"gravity = inf"),
    ],
)
def test_body_errors(kwargs, match):
    with pytest.raises(MaterialError, match=match):
        build_body(box(0.05, 2), Material(1e5, 0.3, 50.0), **kwargs)


def test_body_needs_mass_or_density():
    with pytest.raises(MaterialError, match="no density"):
        build_body(box(0.05, 2), Material(1e5, 0.3))
