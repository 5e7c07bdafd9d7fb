"""Grasp equilibrium (Eq. 21-22), friction-cone feasibility and force closure: analytic checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.grasp import closure
from softgrasp.grasp.closure import (
    ferrari_canny,
    ferrari_canny_bound,
    ferrari_canny_bounds,
    is_force_closure,
    primitive_wrenches,
    primitive_wrenches_many,
    support_bounds,
    wrench_epsilon,
    wrench_hull,
)
from softgrasp.grasp.equilibrium import (
    friction_cone_edges,
    friction_feasibility,
    minimum_normal_forces,
    wrench_residual,
)

R = 0.064  # sphere radius [m]
MASS = 0.05  # [kg]
G = 9.81
ORIGIN = np.zeros(3)


def equator(degrees: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Contact points on the sphere's equator and their inward unit normals."""
    t = np.radians(degrees)
    n_out = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    return R * n_out, -n_out


TRIPOD = equator([0.0, 120.0, 240.0])


# ---------------------------------------------------------------------- friction cone edges


def test_cone_edges_basis_convention() -> None:
    n = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.0, -0.8], *TRIPOD[1]])
    tangents, edges = friction_cone_edges(n, m=8)
    t1, t2 = tangents[:, 0], tangents[:, 1]
    np.testing.assert_allclose(np.einsum("ij,ij->i", t1, n), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.cross(t1, t2), n, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(edges, axis=2), 1.0, atol=1e-15)
    # horizontal normals: t1 = e_z exactly (ties to the highest index); n = e_z: helper e_y
    np.testing.assert_array_equal(t1[[0, 3, 4, 5]], np.tile([0.0, 0.0, 1.0], (4, 1)))
    np.testing.assert_allclose(t1[1], [0.0, 1.0, 0.0])
    np.testing.assert_allclose(t1[2], [0.0, 1.0, 0.0])  # |n_y| = 0 is the smallest
    np.testing.assert_allclose(edges[:, 2], t2, atol=1e-15)  # d_{m/4} = t2


# ---------------------------------------------------------------------- wrench residual


def test_wrench_residual_by_hand() -> None:
    points = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    forces = [[-2.0, 0.0, 1.0], [2.0, 0.0, 0.5]]
    force, torque = wrench_residual(points, forces, com=[0.0, 0.0, 0.0], mass=0.1, gravity=(0, 0, -10))
    # sum f = (0, 0, 1.5); m g = (0, 0, -1)  ->  (0, 0, 0.5)
    np.testing.assert_allclose(force, [0.0, 0.0, 0.5], atol=1e-15)
    # (0.1,0,0) x (-2,0,1) = (0, -0.1, 0); (-0.1,0,0) x (2,0,0.5) = (0, 0.05, 0)
    np.testing.assert_allclose(torque, [0.0, -0.05, 0.0], atol=1e-15)
    # about another centre of mass: r -> r - c changes the torque by -c x sum f
    _, torque2 = wrench_residual(points, forces, com=[0.0, 0.2, 0.0], mass=0.1, gravity=(0, 0, -10))
    np.testing.assert_allclose(torque2, [-0.2 * 1.5, -0.05, 0.0], atol=1e-15)


# ---------------------------------------------------------------------- force closure


@pytest.mark.parametrize("mu", [0.5, 0.1])
def test_tripod_is_force_closure_with_friction(mu: float) -> None:
    assert is_force_closure(*TRIPOD, mu, ORIGIN)


def test_tripod_without_friction_is_not_force_closure() -> None:
    assert primitive_wrenches(*TRIPOD, 0.0, ORIGIN).shape == (3, 6)
    assert ferrari_canny(*TRIPOD, 0.0, ORIGIN) == 0.0
    assert not is_force_closure(*TRIPOD, 0.0, ORIGIN)


def test_contacts_without_opposition_are_not_force_closure() -> None:
    points, normals = equator([0.0, 40.0, 80.0])
    assert primitive_wrenches(points, normals, 0.5, ORIGIN).shape == (24, 6)
    assert ferrari_canny(points, normals, 0.5, ORIGIN) == 0.0
    assert not is_force_closure(points, normals, 0.5, ORIGIN)


def test_epsilon_grows_with_mu() -> None:
    eps = [ferrari_canny(*TRIPOD, mu, ORIGIN) for mu in (0.05, 0.1, 0.2, 0.4, 0.8)]
    assert eps[0] > 0.0
    assert all(b > a for a, b in zip(eps, eps[1:], strict=False))


def test_epsilon_invariant_under_rigid_motion_about_vertical() -> None:
    # rotations about z carry horizontal normals' bases along (t1 = e_z): the wrench set rotates
    rot = Rotation.from_euler("z", 0.7).as_matrix()
    shift = np.array([0.3, -0.2, 0.1])
    for mu in (0.1, 0.5):
        e0 = ferrari_canny(*TRIPOD, mu, ORIGIN)
        e1 = ferrari_canny(TRIPOD[0] @ rot.T + shift, TRIPOD[1] @ rot.T, mu, shift)
        assert e1 == pytest.approx(e0, rel=1e-9)


def test_epsilon_under_general_rotation_within_linearisation_bounds() -> None:
    # any inscribed m-gon lies between the cones of mu cos(pi/m) and mu, so a rotated grasp (whose
    # m-gons may turn about their normals) has eps between those of the unrotated one
    rot = Rotation.from_euler("xyz", [0.4, -1.1, 2.3]).as_matrix()
    m, mu = 8, 0.5
    c = math.cos(math.pi / m)
    e_rot = ferrari_canny(TRIPOD[0] @ rot.T, TRIPOD[1] @ rot.T, mu, ORIGIN, m=m)
    assert ferrari_canny(*TRIPOD, mu * c, ORIGIN, m=m) <= e_rot * (1 + 1e-9)
    assert e_rot <= ferrari_canny(*TRIPOD, mu / c, ORIGIN, m=m) * (1 + 1e-9)


@pytest.mark.parametrize("m_bound", [3, 4, 6])
def test_bound_dominates_epsilon_of_random_grasps(m_bound: int) -> None:
    """The circumscribed-polygon bound is >= the epsilon of every inscribed linearisation, for
    random contact sets (force closure or not); and it is 0 only where epsilon is 0."""
    rng = np.random.default_rng(7)
    closures = 0
    for _ in range(60):
        k = int(rng.integers(2, 5))
        n_out = rng.standard_normal((k, 3))
        n_out /= np.linalg.norm(n_out, axis=1, keepdims=True)
        points = 0.05 * n_out + 0.005 * rng.standard_normal((k, 3))
        mu = float(rng.uniform(0.1, 1.0))
        ub = ferrari_canny_bound(points, -n_out, mu, ORIGIN, m=m_bound)
        for m in (4, 8, 12):
            eps = ferrari_canny(points, -n_out, mu, ORIGIN, m=m)
            assert eps <= ub * (1 + 1e-12)
            closures += eps > 0
    assert closures > 20  # the sample is not all trivial


@pytest.mark.parametrize("mu", [0.0, 0.35, 0.8])
def test_many_grasps_at_once_give_the_one_by_one_numbers(mu: float) -> None:
    """The batched wrenches, bounds and epsilons (the initial-grasp ranking's) are the one-grasp
    functions' to the last bit, grasp by grasp (each with its own torque scale)."""
    rng = np.random.default_rng(11)
    n_out = rng.standard_normal((25, 3, 3))
    n_out /= np.linalg.norm(n_out, axis=2, keepdims=True)
    points = 0.05 * n_out + 0.01 * rng.standard_normal((25, 3, 3))
    centre = np.array([0.001, -0.002, 0.003])
    w = primitive_wrenches_many(points, -n_out, mu, centre)
    bounds = ferrari_canny_bounds(points, -n_out, mu, centre)
    for i in range(25):
        assert np.array_equal(w[i], primitive_wrenches(points[i], -n_out[i], mu, centre))
        assert wrench_epsilon(w[i]) == ferrari_canny(points[i], -n_out[i], mu, centre)
        assert bounds[i] == ferrari_canny_bound(points[i], -n_out[i], mu, centre)
    if mu > 0:
        assert (bounds > 0).sum() > 3  # some are force closure
    else:
        assert not bounds.any()  # three frictionless contacts never are
    with pytest.raises(ConfigError, match="unit"):
        primitive_wrenches_many(points, -2 * n_out, mu, centre)


def test_support_bounds_lie_above_epsilon_and_the_nearest_facet_attains_it() -> None:
    """The support function along any unit direction is at least the inscribed ball's radius
    (random directions, and other grasps' nearest facet normals; below zero only where the
    origin is outside the hull: epsilon 0), and along the hull's own nearest facet normal it
    equals epsilon; ``wrench_hull`` gives ``wrench_epsilon``."""
    rng = np.random.default_rng(5)
    n_out = rng.standard_normal((40, 3, 3))
    n_out /= np.linalg.norm(n_out, axis=2, keepdims=True)
    points = 0.05 * n_out + 0.01 * rng.standard_normal((40, 3, 3))
    w = primitive_wrenches_many(points, -n_out, 0.7, ORIGIN)
    eps = np.array([wrench_epsilon(wi) for wi in w])
    assert (eps > 0).sum() > 5
    random_dirs = rng.standard_normal((40, 500, 6))
    random_dirs /= np.linalg.norm(random_dirs, axis=2, keepdims=True)
    assert (np.maximum(support_bounds(w, random_dirs), 0.0) >= eps - 1e-15).all()
    for i in np.flatnonzero(eps > 0):
        e, normals = wrench_hull(w[i], nearest=5)
        assert e == eps[i] and normals.shape == (5, 6)
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=0, atol=1e-12)
        own = support_bounds(w[i][None], normals[None, :1])[0]
        assert own == pytest.approx(e, rel=1e-12)
        others = support_bounds(w, np.broadcast_to(normals, (40, 5, 6)))
        assert (np.maximum(others, 0.0) >= eps - 1e-15).all()
    assert np.isinf(support_bounds(w, np.zeros((40, 0, 6)))).all()


def _epsilon_by_enumeration(w: np.ndarray) -> float:
    """The smallest facet offset of the hull of ``w`` (n, 6) from every hyperplane through six
    affinely independent wrenches that has all the others on one side (no Qhull)."""
    import itertools

    best = math.inf
    scale = float(np.abs(w).max())
    for subset in itertools.combinations(range(len(w)), 6):
        M = np.hstack([w[list(subset)], -np.ones((6, 1))])
        _, s, vt = np.linalg.svd(M)
        if s[-1] <= 1e-9 * s[0]:
            continue  # the six are affinely dependent: no unique hyperplane
        a, b = vt[-1, :6], vt[-1, 6]
        norm = np.linalg.norm(a)
        a, b = a / norm, b / norm
        side = w @ a - b
        if side.max() <= 1e-12 * scale:
            best = min(best, b)
        elif side.min() >= -1e-12 * scale:
            best = min(best, -b)
    return best


@pytest.mark.parametrize("m", [3, 4])
def test_hull_epsilon_matches_facet_enumeration(m: int) -> None:
    """The signed epsilon from Qhull's hull (computed without merging where that is exact) equals
    the one found by enumerating every candidate facet, on grasps of a sphere, of a cube's faces
    (many coplanar wrenches) and in a horizontal plane."""
    rng = np.random.default_rng(11)
    sets = []
    for _ in range(6):
        n_out = rng.standard_normal((3, 3))
        n_out /= np.linalg.norm(n_out, axis=1, keepdims=True)
        sets.append((R * n_out, -n_out))
    cube = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0]])
    for _ in range(4):
        p = 0.03 * cube + 0.01 * rng.uniform(-1, 1, (3, 3)) * (1 - np.abs(cube))
        sets.append((p, -cube))
    sets.append(TRIPOD)
    checked = 0
    for points, normals in sets:
        w = primitive_wrenches(points, normals, 0.6, ORIGIN, m)
        hull = closure._hull(w)
        if hull is None:
            continue
        got = float(np.min(-hull.equations[:, -1]))
        assert got == pytest.approx(_epsilon_by_enumeration(w), rel=1e-9, abs=1e-12 * np.abs(w).max())
        checked += 1
    assert checked >= 8


def test_hull_without_merging_is_checked_and_recomputed(monkeypatch: pytest.MonkeyPatch) -> None:
    """A hull from Qhull's unmerged run that leaves a wrench outside one of its facets is not
    used: the hull is computed again with merging, and the epsilon is the right one."""
    w = primitive_wrenches(*TRIPOD, 0.5, ORIGIN, 8)
    want = wrench_epsilon(w)
    real = closure.ConvexHull
    calls = []

    def partial_hull(points, qhull_options=None):  # the unmerged run misses the last wrench
        calls.append(qhull_options)
        return real(points[:-1], qhull_options=qhull_options) if qhull_options == "Q0" else real(points)

    monkeypatch.setattr(closure, "ConvexHull", partial_hull)
    assert wrench_epsilon(w) == pytest.approx(want, rel=1e-12)
    assert calls == ["Q0", None]


def test_bound_of_the_tripod_is_the_epsilon_of_its_circumscribed_cone() -> None:
    mu = 0.5
    want = ferrari_canny(*TRIPOD, mu / math.cos(math.pi / 3), ORIGIN, m=3)
    assert ferrari_canny_bound(*TRIPOD, mu, ORIGIN) == pytest.approx(want, rel=1e-12)
    assert ferrari_canny_bound(*TRIPOD, 0.0, ORIGIN) == 0.0


# ---------------------------------------------------------------------- minimum normal forces


@pytest.mark.parametrize("m", [4, 8, 16])
def test_minimum_normal_force_tripod(m: int) -> None:
    mu = 0.5
    exact = MASS * G / (3 * mu)  # exact circular cone
    fn = minimum_normal_forces(*TRIPOD, mu, ORIGIN, MASS, m=m)
    # angle between the vertical and the nearest generator, from the documented basis
    _, edges = friction_cone_edges(TRIPOD[1], m)
    alpha = np.arccos(np.clip(np.max(edges @ np.array([0.0, 0.0, 1.0]), axis=1), -1.0, 1.0))
    expected = exact / np.cos(alpha)
    assert np.all(expected >= exact) and np.all(expected <= exact / math.cos(math.pi / m) * (1 + 1e-12))
    assert np.all(fn >= exact * (1 - 1e-9)) and np.all(fn <= exact / math.cos(math.pi / m) * (1 + 1e-9))
    np.testing.assert_allclose(fn, expected, rtol=1e-6)


@pytest.mark.parametrize("m", [4, 8])
def test_minimum_normal_force_rotated_grasp_within_bounds(m: int) -> None:
    # grasp and gravity rotated together: the m-gons turn, the total lies between the cone bounds
    mu = 0.5
    rot = Rotation.from_euler("xyz", [0.4, -1.1, 2.3]).as_matrix()
    g = rot @ np.array([0.0, 0.0, -G])
    fn = minimum_normal_forces(TRIPOD[0] @ rot.T, TRIPOD[1] @ rot.T, mu, ORIGIN, MASS, g, m=m)
    lo = MASS * G / mu
    assert lo * (1 - 1e-9) <= fn.sum() <= lo / math.cos(math.pi / m) * (1 + 1e-9)


def test_frictionless_equator_grasp_cannot_hold_weight() -> None:
    with pytest.raises(InfeasibleGrasp, match="mu = 0.0"):
        minimum_normal_forces(*TRIPOD, 0.0, ORIGIN, MASS)


# ---------------------------------------------------------------------- friction feasibility


def test_friction_feasibility_around_minimum() -> None:
    mu = 0.5
    fmin = minimum_normal_forces(*TRIPOD, mu, ORIGIN, MASS)
    assert friction_feasibility(*TRIPOD, 1.05 * fmin, mu, ORIGIN, MASS).feasible
    low = friction_feasibility(*TRIPOD, 0.95 * fmin, mu, ORIGIN, MASS)
    assert not low.feasible and low.margin < 0 and math.isfinite(low.utilisation)
    res = friction_feasibility(*TRIPOD, 2.0 * fmin, mu, ORIGIN, MASS)
    assert res.feasible
    assert res.utilisation == pytest.approx(0.5, rel=1e-6)
    assert res.margin == pytest.approx(0.5, rel=1e-6)
    # the friction forces are tangential, inside the (scaled) cones, and balance the load
    ft = res.tangential
    np.testing.assert_allclose(np.einsum("ij,ij->i", ft, TRIPOD[1]), 0.0, atol=1e-12)
    assert np.all(np.linalg.norm(ft, axis=1) <= res.utilisation * mu * 2.0 * fmin * (1 + 1e-9))
    forces = 2.0 * fmin[:, None] * TRIPOD[1] + ft
    fres, tres = wrench_residual(TRIPOD[0], forces, ORIGIN, MASS)
    assert np.linalg.norm(fres) < 1e-9 * MASS * G
    assert np.linalg.norm(tres) < 1e-9 * MASS * G * R
    assert res.force_residual_N < 1e-9 * MASS * G and res.torque_residual_Nm < 1e-9 * MASS * G * R


def test_friction_feasibility_unbalanced_normal_forces() -> None:
    # one finger pushes alone: its normal force cannot be cancelled by friction at any rho
    fn = np.array([1.0, 0.0, 0.0])
    res = friction_feasibility(*TRIPOD, fn, 0.5, ORIGIN, MASS)
    assert not res.feasible and res.utilisation == math.inf and res.margin == -math.inf
    np.testing.assert_array_equal(res.tangential, 0.0)
    expected = np.linalg.norm(fn[0] * TRIPOD[1][0] + MASS * np.array([0.0, 0.0, -G]))
    assert res.force_residual_N == pytest.approx(expected, rel=1e-12)
    assert res.torque_residual_Nm == pytest.approx(0.0, abs=1e-15)


# ---------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: friction_cone_edges([[0.0, 0.0, 2.0]]), r"normals\[0\] has length 2"),
        (lambda: friction_cone_edges(TRIPOD[1], m=2), "m = 2"),
        (lambda: minimum_normal_forces(*TRIPOD, -0.1, ORIGIN, MASS), r"mu = -0.1"),
        (lambda: minimum_normal_forces(*TRIPOD, math.nan, ORIGIN, MASS), r"mu = nan"),
        (lambda: minimum_normal_forces(*TRIPOD, 0.5, ORIGIN, 0.0), r"mass = 0.0"),
        (
            lambda: minimum_normal_forces(TRIPOD[0][:2], TRIPOD[1], 0.5, ORIGIN, MASS),
            "normals has 3 rows but there are 2",
        ),
        (lambda: minimum_normal_forces(TRIPOD[0][:, :2], TRIPOD[1], 0.5, ORIGIN, MASS), r"points"),
        (lambda: friction_feasibility(*TRIPOD, [1.0, -1.0, 1.0], 0.5, ORIGIN, MASS), "normal_forces"),
        (lambda: friction_feasibility(*TRIPOD, [1.0, 1.0], 0.5, ORIGIN, MASS), "normal_forces"),
        (lambda: wrench_residual(TRIPOD[0], np.zeros((3, 3)), [0.0, 0.0], MASS), "com"),
        (lambda: ferrari_canny(*TRIPOD, 0.5, ORIGIN, torque_scale=0.0), "torque_scale = 0.0"),
    ],
)
def test_bad_inputs_raise_config_error(call, match: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError, match=match):
        call()
