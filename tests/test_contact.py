"""Fingertip-object contact (paper Sec. 3): hand computations of Eq. 1-20, balance laws, rigid-surface
exactness, impact restitution, Algorithm 1 friction, mesh refinement, errors, broad phase.

Hand computations use a single facet in a local frame where every number is simple (written out in
the comments), then rotate and translate the whole configuration by a generic rigid motion, so that
no result can come from an axis-aligned special case.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from oracles.contact import relative_velocity
from softgrasp.errors import ContactError
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import Material, preset
from softgrasp.model.mesh import TetMesh, box
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.geometry import FacetIndex, detect
from softgrasp.physics.fingertip.laws import (
    HERTZ_PREFACTOR,
    contact_damping,
    contact_stiffness,
    effective_modulus,
    mindlin_ratio,
    normal_force,
    restitution_hunt_crossley,
    slip_force,
)
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.explicit import simulate
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import solve_static

# --------------------------------------------------------------------------- helpers


def _rotation(axis, angle: float) -> np.ndarray:
    """Proper rotation matrix (Rodrigues)."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


Q = _rotation([1.0, 2.0, 3.0], 0.7)
T = np.array([0.1, -0.2, 0.3])

# One tet in the local frame: facet A B C in the plane z = 0 (outward normal +z), apex D below.
A_L, B_L, C_L, D_L = (0.0, 0.0, 0.0), (0.03, 0.0, 0.0), (0.0, 0.02, 0.0), (0.01, 0.005, -0.015)
E_FINGER, NU_FINGER = 1.0e6, 0.0  # (1 - 0^2) / 1e6 = 1.0e-6 Pa^-1
E_OBJECT, NU_OBJECT = 1.875e6, 0.25  # (1 - 0.0625) / 1.875e6 = 0.5e-6 Pa^-1
PSI = 1.0 / 1.5e-6  # Eq. 12: 666 666.67 Pa
R_HAND = 0.0049  # sqrt(R) = 0.07
K_HAND = 2.0 * PSI * 0.07  # Eq. 11: 93 333.33 N/m^1.5
C_HAND = 4.0 * math.pi * R_HAND * 10.0  # Eq. 13 with gamma = 10: 0.615752 N s/m
D_HAND = 0.0039  # centre-to-plane distance
DELTA_HAND = R_HAND - D_HAND  # Eq. 14: 0.001 m
P_LOCAL = np.array([0.006, 0.005, 0.0])  # contact point
CENTRE_LOCAL = P_LOCAL + [0.0, 0.0, D_HAND]


def _local_to_world(p) -> np.ndarray:
    return np.asarray(p, dtype=float) @ Q.T + T


def _vec(v) -> np.ndarray:
    return np.asarray(v, dtype=float) @ Q.T


def _one_tet_body() -> tuple:
    """Body of one tet (nodes A, B, C, D) in world coordinates and the index of facet A B C."""
    pts = _local_to_world([A_L, B_L, C_L, D_L])
    mesh = TetMesh(pts, np.array([[0, 2, 1, 3]]))  # det[C-A, B-A, D-A] > 0
    body = build_body(mesh, Material(E_OBJECT, NU_OBJECT, 1000.0), gravity=0.0, isotropize=False)
    j = [i for i, f in enumerate(mesh.facets) if set(f.tolist()) == {0, 1, 2}][0]
    return body, j


def _area2d(p, q, r) -> float:
    """Unsigned area of a triangle of the local z = 0 plane (shoelace)."""
    return 0.5 * abs((q[0] - p[0]) * (r[1] - p[1]) - (r[0] - p[0]) * (q[1] - p[1]))


def _fingertip_on_tet(**kw) -> Fingertip:
    return Fingertip(R_HAND, centre=_local_to_world(CENTRE_LOCAL), E=E_FINGER, nu=NU_FINGER, **kw)


# Hand-chosen velocities in the local frame (Eq. 1-7).
V_NODES_LOCAL = np.array([[0.1, 0.0, -0.2], [0.0, 0.3, 0.1], [-0.2, 0.1, 0.0], [0.5, 0.5, 0.5]])
V_FINGER_LOCAL = np.array([0.02, -0.01, -0.15])
OMEGA_LOCAL = np.array([1.0, 2.0, -3.0])
# Facet velocity at P (Eq. 4): 0.55 vA + 0.2 vB + 0.25 vC = (0.005, 0.085, -0.09).
# Omega x (P - c) with P - c = (0, 0, -0.0039): (2(-0.0039) - 0, 0 - 1(-0.0039), 0) = (-0.0078, 0.0039, 0).
# Finger velocity at P (Eq. 1): (0.0122, -0.0061, -0.15).
VR_LOCAL = np.array([0.0072, -0.0911, -0.06])  # Eq. 5
VN_LOCAL = np.array([0.0, 0.0, -0.06])  # Eq. 6
VT_LOCAL = np.array([0.0072, -0.0911, 0.0])  # Eq. 7
RATE_HAND = 0.06  # d delta / dt = -V_r . n: the finger approaches the facet at 6 cm/s


#: The paper's normal law K delta^n (Eq. 9-11), which the by-hand checks below follow.
PAPER = ContactParams(law="paper")

# --------------------------------------------------------------------------- 1. equations by hand


def test_effective_modulus_stiffness_and_damping_by_hand():
    """Eq. 11-13 with two finite moduli, a rigid fingertip, and both stiffness prefactors."""
    assert effective_modulus(E_FINGER, NU_FINGER, E_OBJECT, NU_OBJECT) == pytest.approx(666666.6667, rel=1e-9)
    # A rigid fingertip leaves only the object's term: E / (1 - nu^2) = 1.875e6 / 0.9375 = 2e6 Pa.
    assert effective_modulus(math.inf, 0.3, E_OBJECT, NU_OBJECT) == pytest.approx(2.0e6, rel=1e-12)
    assert contact_stiffness(PSI, R_HAND) == pytest.approx(93333.3333, rel=1e-9)
    assert contact_stiffness(PSI, R_HAND, HERTZ_PREFACTOR) == pytest.approx(62222.2222, rel=1e-9)
    assert contact_damping(R_HAND, 10.0) == pytest.approx(0.6157521601, rel=1e-9)
    # The interaction uses the same constants for its fingertip and body.
    body, _ = _one_tet_body()
    fc = FingertipContact((_fingertip_on_tet(),), PAPER)
    assert fc.stiffness(body)[0] == pytest.approx(K_HAND, rel=1e-12)
    assert fc.damping()[0] == pytest.approx(C_HAND, rel=1e-12)
    hertz = FingertipContact((_fingertip_on_tet(),), ContactParams(law="paper", prefactor=4.0 / 3.0))
    assert hertz.stiffness(body)[0] == pytest.approx(62222.2222, rel=1e-9)


def test_normal_force_both_forms_by_hand():
    """Eq. 9: K delta^n + C delta' (paper) and delta^n (K + C delta') (Hunt-Crossley), clipped."""
    # delta^1.5 = 0.001^1.5 = 3.16227766e-5; K delta^1.5 = 2.951459 N; C delta' = 0.0369451 N.
    lin = normal_force(DELTA_HAND, RATE_HAND, K_HAND, C_HAND)
    hc = normal_force(DELTA_HAND, RATE_HAND, K_HAND, C_HAND, damping="hunt-crossley")
    assert float(lin) == pytest.approx(2.951459 + 0.0369451, rel=1e-6)
    assert float(hc) == pytest.approx(3.16227766e-5 * (93333.3333 + 0.0369451), rel=1e-8)
    # Fast separation: the linear form would pull (2.95 - 6.16 < 0) and is clipped to zero.
    assert float(normal_force(DELTA_HAND, -10.0, K_HAND, C_HAND)) == 0.0
    # Hunt-Crossley pulls only when K + C delta' < 0.
    assert float(normal_force(DELTA_HAND, -2.0e5, K_HAND, C_HAND, damping="hunt-crossley")) == 0.0
    assert float(normal_force(DELTA_HAND, -1.0e5, K_HAND, C_HAND, damping="hunt-crossley")) > 0.0
    # No penetration: no force, even when approaching (the linear form's C delta' would be > 0).
    for damping in ("linear", "hunt-crossley"):
        f = normal_force([0.0, -1e-4], [5.0, 5.0], K_HAND, C_HAND, damping=damping)
        assert f.tolist() == [0.0, 0.0]


def test_slip_force_and_mindlin_ratio_by_hand():
    """Eq. 15: -mu f_n V_t / |V_t|, zero without sliding; Mindlin's k_t / k_n."""
    vt = np.array([[3.0, -4.0, 0.0], [0.0, 0.0, 0.0]])
    f = slip_force([2.0, 2.0], vt, 0.5)
    assert f[0] == pytest.approx([-0.6, 0.8, 0.0], abs=1e-15)  # |f| = 0.5 * 2, opposite V_t
    assert f[1].tolist() == [0.0, 0.0, 0.0]
    assert mindlin_ratio(0.0) == pytest.approx(1.0)
    assert mindlin_ratio(0.25) == pytest.approx(1.5 / 1.75)
    assert mindlin_ratio(0.5) == pytest.approx(2.0 / 3.0)


def test_detection_and_contact_kinematics_on_one_facet_by_hand():
    """Eq. 1-8 and 14 on one facet: distance, depth, area coordinates, relative velocity."""
    body, j = _one_tet_body()
    x = np.asarray(body.mesh.points)
    centre = _local_to_world(CENTRE_LOCAL)[None]
    pairs = detect(x, body.mesh.facets, centre, np.array([R_HAND]), index=FacetIndex.of(body.mesh))
    assert pairs.facet.tolist() == [j]  # the other three facets face away from the fingertip
    assert pairs.distance[0] == pytest.approx(D_HAND, rel=1e-12)
    # Eq. 14 up to its sign convention: the penetration is R - d (the printed formula gives d - R
    # with the outward normal; R - d is the one that is positive when the sphere overlaps).
    assert pairs.depth[0] == pytest.approx(DELTA_HAND, rel=1e-9)
    assert pairs.normal[0] == pytest.approx(_vec([0, 0, 1]), abs=1e-15)
    assert pairs.point[0] == pytest.approx(_local_to_world(P_LOCAL), abs=1e-15)
    # Eq. 4, 8: A_i / A_G from the sub-triangles opposite each node (A_G = 3e-4 m^2; A_A = 1.65e-4,
    # A_B = 6e-5, A_C = 7.5e-5), i.e. (0.55, 0.2, 0.25).
    a, b, c = A_L, B_L, C_L
    AG = _area2d(a, b, c)
    hand = [_area2d(P_LOCAL, b, c) / AG, _area2d(a, P_LOCAL, c) / AG, _area2d(a, b, P_LOCAL) / AG]
    assert AG == pytest.approx(3e-4) and hand == pytest.approx([0.55, 0.2, 0.25])
    facet = body.mesh.facets[j].tolist()
    bary = dict(zip(facet, pairs.bary[0], strict=True))
    assert [bary[0], bary[1], bary[2]] == pytest.approx(hand, abs=1e-12)
    assert pairs.area[0] == pytest.approx(AG, rel=1e-12)

    vr, vn, vt = relative_velocity(
        pairs,
        body.mesh.facets,
        _vec(V_NODES_LOCAL),
        _local_to_world(CENTRE_LOCAL)[None],
        _vec(V_FINGER_LOCAL)[None],
        _vec(OMEGA_LOCAL)[None],
    )
    assert vr[0] == pytest.approx(_vec(VR_LOCAL), abs=1e-14)
    assert vn[0] == pytest.approx(_vec(VN_LOCAL), abs=1e-14)
    assert vt[0] == pytest.approx(_vec(VT_LOCAL), abs=1e-14)
    # The compiled kernel the contact forces run: tangential velocity and penetration rate.
    from softgrasp.physics.fingertip.forces import _relative_velocity

    val = np.column_stack(
        [pairs.bary, pairs.point, pairs.normal, pairs.distance, pairs.depth, pairs.area, pairs.facing]
    )
    *vt_kernel, rate = _relative_velocity(
        0, 0, j, val, _vec(V_NODES_LOCAL), body.mesh.facets, centre, _vec(V_FINGER_LOCAL)[None],
        _vec(OMEGA_LOCAL)[None],
    )  # fmt: skip
    assert vt_kernel == pytest.approx(_vec(VT_LOCAL), abs=1e-14)
    assert rate == pytest.approx(-float(_vec(VN_LOCAL) @ pairs.normal[0]), abs=1e-14)


@pytest.mark.parametrize(("mu", "slips"), [(0.01, True), (0.8, False)])
def test_nodal_forces_on_one_facet_by_hand(mu, slips):
    """Eq. 9-10, 15-16 (Algorithm 1) and 17-20 through the interaction's dynamic forces.

    A fresh pair has no stick displacement, so its trial friction is the tangential damper alone,
    -c_t V_t with c_t = r C (r = Mindlin's 2(1 - nu)/(2 - nu) = 0.857 for nu = 0.25): |trial| =
    0.857 * 0.61575 * 0.091384 = 0.0482 N. With mu = 0.01 the Coulomb limit is 0.0299 N: it slips,
    f_t = -mu f_n V_t / |V_t|; with mu = 0.8 (limit 2.39 N) it sticks, f_t = -c_t V_t.
    """
    body, j = _one_tet_body()
    x = np.asarray(body.mesh.points)
    finger = _fingertip_on_tet(velocity=_vec(V_FINGER_LOCAL), omega=_vec(OMEGA_LOCAL))
    fc = FingertipContact((finger,), ContactParams(law="paper", mu=mu, gamma=10.0, damping="linear"))
    state = fc.init_state(body, x, 0.0)
    f = fc.forces(body, x, _vec(V_NODES_LOCAL), 0.0, state)

    fn = K_HAND * DELTA_HAND**1.5 + C_HAND * RATE_HAND  # Eq. 9, linear form: 2.988404 N
    n = _vec([0, 0, 1])
    vt = _vec(VT_LOCAL)
    speed = math.hypot(0.0072, 0.0911)
    ct = (1.5 / 1.75) * C_HAND
    assert ct * speed == pytest.approx(0.04822, rel=1e-3)
    friction_on_finger = -mu * fn * vt / speed if slips else -ct * vt
    f_p = -fn * n - friction_on_finger  # Eq. 10, 17: the pair's force on the object
    for node, b_l in zip((0, 1, 2), (0.55, 0.2, 0.25), strict=True):
        assert f[node] == pytest.approx(b_l * f_p, rel=1e-9, abs=1e-15)  # Eq. 19: H^T f_p
    assert f[3].tolist() == [0.0, 0.0, 0.0]  # the apex is not on the facet
    assert f.sum(axis=0) == pytest.approx(f_p, rel=1e-9)  # Eq. 18
    rep = fc.report(body, x, _vec(V_NODES_LOCAL), 0.0, state)
    assert rep.normal[0] == pytest.approx(2.988404, rel=1e-6)
    assert rep.tangential[0] == pytest.approx(mu * fn if slips else ct * speed, rel=1e-9)
    assert rep.contacts.tolist() == [1] and rep.depth[0] == pytest.approx(DELTA_HAND, rel=1e-9)


def test_stick_spring_by_hand():
    """Eq. 16 at rest: a pair anchored at t = 0, with the fingertip then moved 20 um along the
    facet, pulls the facet with k_t s, k_t = r n K delta^(n-1) = 0.857 * 1.5 * 93333.3 * 0.0316 =
    3794.7 N/m; the contact point, and so the area coordinates, move with the fingertip."""
    body, _ = _one_tet_body()
    x = np.asarray(body.mesh.points)
    step = 2e-5
    finger = _fingertip_on_tet(velocity=_vec([1.0, 0.0, 0.0]))
    fc = FingertipContact((finger,), ContactParams(law="paper", mu=0.8))
    state = fc.init_state(body, x, 0.0)
    f = fc.static_forces(body, x, step, state)
    kt = (1.5 / 1.75) * 1.5 * K_HAND * math.sqrt(DELTA_HAND)
    assert kt == pytest.approx(3794.733, rel=1e-6)
    f_p = -K_HAND * DELTA_HAND**1.5 * _vec([0, 0, 1]) + kt * _vec([step, 0.0, 0.0])
    b = (1.0 - (0.006 + step) / 0.03 - 0.25, (0.006 + step) / 0.03, 0.25)
    for node in range(3):
        assert f[node] == pytest.approx(b[node] * f_p, rel=1e-9, abs=1e-15)


# --------------------------------------------------------------------------- 2. balance laws


def _random_contact_setup(seed: int, rule: str, damping: str, mu: float):
    """A perturbed box with three fingertips, each placed over a random point inside a random
    boundary facet, random node velocities and fingertip motions; the contact state is anchored at
    t = 0 and the forces are evaluated at t1, when the fingertips have moved on."""
    rng = np.random.default_rng(seed)
    mesh = box(0.03, 3)
    body = build_body(mesh, preset("foam"), mass=0.02)
    X = np.asarray(mesh.points)
    x = X + 2e-4 * rng.standard_normal(X.shape)
    facets = mesh.facets
    fingers = []
    for _ in range(3):
        j = rng.integers(len(facets))
        tri = x[facets[j]]
        w = rng.uniform(0.15, 1.0, 3)
        w /= w.sum()
        P = w @ tri
        nrm = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        nrm /= np.linalg.norm(nrm)
        R = rng.uniform(0.004, 0.008)
        c = P + rng.uniform(0.5, 0.9) * R * nrm
        fingers.append(
            Fingertip(R, centre=c, velocity=0.3 * rng.standard_normal(3), omega=5 * rng.standard_normal(3))
        )
    fc = FingertipContact(tuple(fingers), ContactParams(mu=mu, rule=rule, damping=damping))
    state = fc.init_state(body, x, 0.0)
    v = 0.05 * rng.standard_normal(X.shape)
    return body, fc, x, v, state, 2e-3


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("mu", [0.0, 0.05, 5.0])
@pytest.mark.parametrize(("rule", "damping"), [("patch", "linear"), ("facet", "hunt-crossley")])
def test_nodal_forces_balance_the_fingertip_forces_and_moments(seed, mu, rule, damping):
    """Newton's third law, Eq. 18-22: the nodal forces add up to each fingertip's force on the
    object, and their moment about the origin equals that of the contact forces applied at the
    contact points (Sum x_l x b_l F = P x F because Sum b_l x_l = P)."""
    body, fc, x, v, state, t1 = _random_contact_setup(seed, rule, damping, mu)
    rep = fc.report(body, x, v, t1, state)
    assert (rep.contacts > 0).all()
    f = fc.forces(body, x, v, t1, state)
    scale = float(np.abs(rep.force).max())
    assert scale > 0.1
    assert f.sum(axis=0) == pytest.approx(rep.force.sum(axis=0), abs=1e-12 * scale)
    centres = fc.centres(t1)
    moment_nodes = np.cross(x, f).sum(axis=0)
    moment_fingers = (rep.moment + np.cross(centres, rep.force)).sum(axis=0)
    assert moment_nodes == pytest.approx(moment_fingers, abs=1e-13 * scale)
    # Each fingertip alone: its nodal forces sum to its own reported force.
    for i, finger in enumerate(fc.fingertips):
        alone = FingertipContact((finger,), fc.params)
        st = alone.init_state(body, x, 0.0)
        fi = alone.forces(body, x, v, t1, st)
        assert fi.sum(axis=0) == pytest.approx(rep.force[i], abs=1e-12 * scale)
    if mu == 0.0:
        assert rep.tangential.tolist() == [0.0, 0.0, 0.0]
    if mu == 0.0 and rule == "facet":
        # Normal forces act along the facet normal at the centre's projection, through the centre:
        # no moment about it. (The patch rule's pairs on an edge push along their facet's normal
        # at the closest point, off the centre line.)
        assert np.abs(rep.moment).max() < 1e-14 * scale
    else:
        assert np.abs(rep.moment).max() > 1e-6 * scale


# --------------------------------------------------------------------------- 3. rigid flat surface


# Points of the top face of box(0.02, 2) (top at z = 0.02) and the number of facets sharing them.
TOP_POINTS = {
    "inside a facet": ((0.005, 0.005 / 3), 1),
    "on an edge": ((0.0025, 0.0025), 2),
    "on a face-centre node": ((0.005, 0.005), 4),
    "on a grid node": ((0.0, 0.0), 8),
}


@pytest.mark.parametrize("where", list(TOP_POINTS))
def test_rigid_flat_surface_force_is_exactly_K_delta_n(where):
    """On the undeformed mesh (a numerically rigid object), the patch rule gives K delta^n wherever
    the fingertip presses, even on a node shared by k facets; the paper's literal rule gives
    k K delta^n there: the documented mesh dependence of the rule taken literally."""
    (px, py), k = TOP_POINTS[where]
    mesh = box(0.02, 2)
    body = build_body(mesh, preset("foam"), mass=0.01)
    x = np.asarray(mesh.points)
    R = 0.008
    mat = preset("foam")
    K = 2.0 * mat.E / (1.0 - mat.nu**2) * math.sqrt(R)  # Eq. 11-12 with a rigid fingertip
    for delta in (1e-4, 5e-4, 2e-3):
        finger = Fingertip(R, centre=[px, py, 0.02 + R - delta])
        for rule, factor in (("patch", 1), ("facet", k)):
            fc = FingertipContact((finger,), ContactParams(law="paper", rule=rule))
            state = fc.init_state(body, x)
            rep = fc.report(body, x, np.zeros_like(x), 0.0, state, static=True)
            # the literal rule touches the k facets around the point; the patch rule also the
            # neighbours the sphere overlaps
            assert rep.contacts[0] == k if rule == "facet" else rep.contacts[0] >= k
            for f in (
                fc.static_forces(body, x, 0.0, state),
                fc.forces(body, x, np.zeros_like(x), 0.0, state),
            ):
                total = f.sum(axis=0)
                assert total[2] == pytest.approx(-factor * K * delta**1.5, rel=1e-12)
                assert np.abs(total[:2]).max() < 1e-12 * abs(total[2])
            assert rep.normal[0] == pytest.approx(factor * K * delta**1.5, rel=1e-12)


def test_patch_weights_on_a_dented_surface_by_hand():
    """The patch rule on a bowl: the top centre node of a one-cell box lowered by 2 mm, a fingertip
    over it slightly off centre touches all four tilted facets at different depths, computed here
    from the planes. Patch rule: total elastic force K delta_max^n (the sphere's overlap with the
    surface), shared as w_j = A_j delta_j / Sum A delta, each part along its facet's normal.
    Literal rule: K delta_j^n on every facet."""
    mesh = box(0.02, 1)
    body = build_body(mesh, preset("foam"), mass=0.01)
    x = np.array(mesh.points)
    top = int(np.flatnonzero((np.abs(x[:, 0]) < 1e-12) & (np.abs(x[:, 1]) < 1e-12) & (x[:, 2] > 0.019))[0])
    x[top, 2] -= 0.002
    R = 0.008
    c = np.array([0.0003, 0.0002, 0.02 + R - 0.0025])
    facets = [f for f in mesh.facets if top in f]
    assert len(facets) == 4
    mat = preset("foam")
    K = 2.0 * mat.E / (1.0 - mat.nu**2) * math.sqrt(R)
    area, depth, normal = [], [], []
    for f in facets:
        a, b, e = x[f]
        cr = np.cross(b - a, e - a)
        n = cr / np.linalg.norm(cr)
        assert n[2] > 0.9  # outward, tilted towards the bowl's axis
        area.append(0.5 * np.linalg.norm(cr))
        depth.append(R - (c - a) @ n)
        normal.append(n)
    area, depth, normal = np.array(area), np.array(depth), np.array(normal)
    assert np.ptp(depth) > 0.05 * depth.mean()  # different depths: the weights matter
    w = area * depth / (area * depth).sum()
    for rule, f_facet in (("patch", w * K * depth.max() ** 1.5), ("facet", K * depth**1.5)):
        fc = FingertipContact((Fingertip(R, centre=c),), ContactParams(law="paper", rule=rule))
        state = fc.init_state(body, x)
        rep = fc.report(body, x, np.zeros_like(x), 0.0, state, static=True)
        assert rep.contacts.tolist() == [4]
        assert rep.normal[0] == pytest.approx(f_facet.sum(), rel=1e-12)
        assert rep.depth[0] == pytest.approx(depth.max(), rel=1e-12)
        expected = -f_facet @ normal  # on the object
        assert fc.static_forces(body, x, 0.0, state).sum(axis=0) == pytest.approx(expected, rel=1e-12)


def test_patch_rule_force_is_continuous_as_facets_leave_a_dent():
    """The same bowl as above; the fingertip slides 4 mm sideways in 10 um steps at a fixed height
    while the facets it touches drop out one by one (they leave where their closest point meets
    the staying facets'). A continuous contact force changes by ~0.15 % per step here (3 N/mm);
    assert < 1 % for the force vector. (With the projection test of Sec. 3.1 the total normal
    force jumped 19.4 -> 20.6 -> 24.0 N and 26.0 -> 31.2 N over 10 um.)"""
    mesh = box(0.02, 1)
    body = build_body(mesh, preset("foam"), mass=0.01)
    x = np.array(mesh.points)
    top = int(np.flatnonzero((np.abs(x[:, 0]) < 1e-12) & (np.abs(x[:, 1]) < 1e-12) & (x[:, 2] > 0.019))[0])
    x[top, 2] -= 0.002
    R = 0.008
    force, counts = [], []
    for xc in np.linspace(0.0, 0.004, 401):
        fc = FingertipContact((Fingertip(R, centre=[xc, 0.0002, 0.02 + R - 0.0025]),))
        state = fc.init_state(body, x)
        rep = fc.report(body, x, np.zeros_like(x), 0.0, state, static=True)
        force.append(rep.force[0])
        counts.append(rep.contacts[0])
    assert counts[0] == 4 and counts[-1] < 4  # facets did leave on the way
    force = np.array(force)
    step = np.linalg.norm(np.diff(force, axis=0), axis=1) / np.linalg.norm(force[1:], axis=1)
    assert step.max() < 0.01


# --------------------------------------------------------------------------- 4. restitution


def _regular_tet(a: float) -> np.ndarray:
    return np.array(
        [
            [0.0, 0.0, 0.0],
            [a, 0.0, 0.0],
            [a / 2, a * math.sqrt(3) / 2, 0.0],
            [a / 2, a * math.sqrt(3) / 6, a * math.sqrt(2.0 / 3.0)],
        ]
    )


def test_hunt_crossley_closed_form_restitution():
    # -y - ln(1 - y) = 0.3 - ln(1.3) = 0.037636 at y = beta v_out = 0.249861: e = 0.83287.
    assert restitution_hunt_crossley(0.3) == pytest.approx(0.83287, abs=5e-6)
    assert restitution_hunt_crossley(1e-4) == pytest.approx(1.0 - 2.0 / 3.0 * 1e-4, rel=1e-6)  # light damping


def test_hunt_crossley_impact_reproduces_the_closed_form_restitution():
    """A stiff free tet (no gravity, no internal damping) hits a fixed soft fingertip at 1 m/s,
    centre-on through its centre of mass, on one facet. With damping="hunt-crossley" and
    C = 0.3 K (beta = 0.3 s/m), the outgoing speed of the centre of mass gives e = 0.83287.

    Residual (measured 7e-6): the body's own elastic compliance in series with the contact stores
    energy that it returns undamped, so e - e_closed scales as 1/E_body (5.6e-5 at 1e8 Pa, 5.6e-6
    at 1e9 Pa, 5.6e-7 at 1e10 Pa). The internal vibration left after the impact is ~1e-24 of the
    kinetic energy (the contact lasts ~100 periods of the tet), and halving the RK4 step changes e
    by < 1e-7.
    """
    P = _regular_tet(0.02)
    mesh = TetMesh(P, np.array([[0, 1, 2, 3]]))
    body = build_body(mesh, Material(1e9, 0.3, 1000.0), gravity=0.0, damping_ratio=0.0, isotropize=False)
    R, gap = 0.005, 1e-4
    bottom = P[:3].mean(axis=0)  # facet (0, 2, 1) faces -z; its centroid lies below the COM
    finger = Fingertip(R, centre=bottom - [0.0, 0.0, R + gap], E=2.5e5, nu=0.3)
    K = FingertipContact((finger,), PAPER).stiffness(body)[0]
    gamma = 0.3 * K / (4.0 * math.pi * R)  # C = 4 pi R gamma = 0.3 K
    # The closed form is the power law's, K delta^n: the paper's law.
    fc = FingertipContact((finger,), ContactParams(law="paper", damping="hunt-crossley", gamma=gamma, mu=0.0))
    assert fc.damping()[0] / K == pytest.approx(0.3, rel=1e-12)
    scene = Scene(body, (fc,))
    state = scene.initial_state(v=np.tile([0.0, 0.0, -1.0], (4, 1)))
    touched = []

    def record(s: State) -> None:
        r = fc.report(body, s.x, s.v, s.t, s.contacts[0])
        touched.append((int(r.contacts[0]), float(r.depth[0])))

    out = simulate(scene, state, 0.012, callback=record)
    counts = {c for c, _ in touched}
    assert counts == {0, 1}  # single-facet contact, and separated at the end
    # Largest penetration from the same energy balance: K x^(n+1) / (n+1) = m (b - ln(1 + b)) / beta^2
    # with b = beta v_in: 0.916 mm, well inside the fingertip's radius.
    m, n = body.total_mass, 1.5
    x_max = ((n + 1) * m * (0.3 - math.log1p(0.3)) / (0.3**2 * K)) ** (1 / (n + 1))
    assert max(d for _, d in touched) == pytest.approx(x_max, rel=1e-3)
    v_com = body.mass @ out.v / body.total_mass
    assert np.abs(v_com[:2]).max() < 1e-12
    assert v_com[2] == pytest.approx(restitution_hunt_crossley(0.3), rel=1e-4)


# --------------------------------------------------------------------------- 5. friction (Algorithm 1)

MU = 0.5
SOFT_TIP = {"E": 1.0e5, "nu": 0.45}  # silicone-like fingertip: Psi ~ 1.25e5 Pa, 800 x softer than the block


def _stiff_block():
    """A block 800 times stiffer than the fingertip and heavy enough (5 kg) that the fingertip can
    neither tip nor drag it: the contact's own stick spring carries the tangential travel."""
    body = build_body(box((0.04, 0.04, 0.02), (4, 4, 2)), Material(1e8, 0.3, 1000.0), mass=5.0)
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=1.0, name="table")
    return body, table


def _press(body, table, centre, depth, params, cache=None):
    """Static press of a fingertip straight down by ``depth`` from ``centre``; (state, centre)."""
    fc = FingertipContact((Fingertip(0.008, centre=centre, velocity=[0, 0, -1.0], **SOFT_TIP),), params)
    scene = Scene(body, (table, fc))
    state, _ = solve_static(scene, scene.initial_state(), t=depth, cache=cache)
    return state, np.asarray(centre, dtype=float) - [0.0, 0.0, depth]


def _drag(body, table, state, centre, direction, path, params, cache=None):
    """Static increments of a fingertip moved from ``centre`` along ``direction`` to the travels
    in ``path``; returns the states and reports after each increment."""
    d = np.asarray(direction, dtype=float)
    fc = FingertipContact(
        (Fingertip(0.008, centre=centre, velocity=d / np.linalg.norm(d), **SOFT_TIP),), params
    )
    scene = Scene(body, (table, fc))
    state = State(state.x, state.v, 0.0, state.contacts)
    out = []
    for s in path:
        state, _ = solve_static(scene, state, t=float(s), cache=cache)
        out.append((state, fc.report(body, state.x, state.v, state.t, state.contacts[1], static=True)))
    return fc, out


def test_stuck_fingertip_holds_until_mu_fn_then_slides_at_mu_and_dissipates():
    """Algorithm 1 on a numerically rigid block: the tangential force grows as k_t s (Mindlin's k_t
    at the pressed depth) until it reaches mu f_n, then the fingertip slides at f_t = mu f_n across
    facet edges; dragged back to its start it traces a hysteresis loop that absorbs work, the
    elastic-perfectly-plastic amount W = mu f_n (2 L - 5/2 s_y) with s_y = mu f_n / k_t."""
    body, table = _stiff_block()
    params = ContactParams(law="paper", mu=MU)
    depth = 1e-3
    start, direction = np.array([-0.0125, -0.0045, 0.02 + 0.008]), np.array([1.0, 0.3, 0.0])
    state, centre = _press(body, table, start, depth, params)
    fc0 = FingertipContact((Fingertip(0.008, centre=centre, **SOFT_TIP),), params)
    rep0 = fc0.report(body, state.x, state.v, 0.0, state.contacts[1], static=True)
    assert rep0.contacts[0] >= 1
    fn, delta = float(rep0.normal[0]), float(rep0.depth[0])
    K = fc0.stiffness(body)[0]
    assert fn == pytest.approx(K * delta**1.5, rel=1e-9) and delta == pytest.approx(depth, rel=0.02)
    kt = mindlin_ratio(0.3) * 1.5 * K * math.sqrt(delta)
    s_y = MU * fn / kt  # 0.4 mm
    L = 0.02
    u = direction / np.linalg.norm(direction)
    rise = np.array([0.05e-3, 0.1e-3, 0.15e-3, 0.2e-3])  # < s_y
    forth = np.concatenate([rise, np.linspace(0.6e-3, L, 12)])
    back = np.concatenate(
        [L - np.array([0.2e-3, 0.4e-3, 0.6e-3, 0.8e-3, 1.0e-3]), np.linspace(L - 2e-3, 0.0, 10)]
    )
    fc, recs = _drag(body, table, state, centre, direction, np.concatenate([forth, back]), params)
    travel = np.concatenate([[0.0], forth, back])
    F = np.array([rep0.force[0]] + [r.force[0] for _, r in recs])  # on the object
    ft = np.array([rep0.tangential[0]] + [r.tangential[0] for _, r in recs])
    fnorm = np.array([rep0.normal[0]] + [r.normal[0] for _, r in recs])
    # Stick: the fingertip pulls the block along with the spring force k_t s.
    assert (F[1:5] - F[0]) @ u == pytest.approx(kt * rise, rel=0.02)
    ratio = ft / fnorm
    assert ratio.max() <= MU * (1 + 1e-6)
    # Slide, forth then back once the load has reversed (2 s_y of travel): f_t = mu f_n along the
    # fingertip's motion.
    n_forth = 1 + len(forth)
    going = np.zeros(len(travel), bool)
    going[5:n_forth] = True
    coming = np.zeros(len(travel), bool)
    coming[n_forth:] = L - travel[n_forth:] > 2.2 * s_y
    assert going.sum() == 12 and coming.sum() == 11
    assert ratio[going | coming] == pytest.approx(MU, rel=0.01)
    assert F[going] @ u == pytest.approx(MU * fnorm[going], rel=0.01)
    assert -F[coming] @ u == pytest.approx(MU * fnorm[coming], rel=0.01)
    # It slid across several facets with no jump of the friction force.
    facets_seen = set()
    for st, _ in recs[: len(forth)]:
        facets_seen |= set(np.flatnonzero(st.contacts[1].active[0]).tolist())
    assert len(facets_seen) >= 4
    # Closed loop: positive work absorbed, as the elastic-perfectly-plastic slider predicts.
    work = float(np.trapezoid(F @ u, travel))
    expected = MU * fn * (2 * L - 2.5 * s_y)
    assert work > 0
    assert work == pytest.approx(expected, rel=0.03)
    # The stick spring is then loaded backwards (energy mu^2 f_n^2 / 2 k_t stored): what remains of
    # the work is dissipated, mu f_n times the slip distance 2 L - 3 s_y.
    stored = (MU * fn) ** 2 / (2 * kt)
    assert work - stored == pytest.approx(MU * fn * (2 * L - 3 * s_y), rel=0.03)


def test_contact_state_resets_when_the_fingertip_leaves():
    """Algorithm 1: u and v are reset on loss of contact. After a slide, lifting the fingertip
    clears every pair; pressing again at the same place starts from a fresh, unloaded stick."""
    body, table = _stiff_block()
    params = ContactParams(law="paper", mu=MU)
    start = np.array([0.0052, 0.0017, 0.028])
    state, centre = _press(body, table, start, 1e-3, params)
    fc, recs = _drag(body, table, state, centre, [1.0, 0.0, 0.0], [1e-3, 2e-3], params)
    slid = recs[-1][0]
    fs = slid.contacts[1]
    assert fs.active.any() and np.abs(fs.slip).max() > 0.5e-3 and np.abs(fs.memory).max() > 0
    away = FingertipContact((Fingertip(0.008, centre=centre + [0.002, 0, 0.01], **SOFT_TIP),), params)
    gone = away.update(body, slid.x, np.zeros_like(slid.x), 0.0, fs)
    assert not gone.active.any()
    assert not gone.anchor.any() and not gone.slip.any() and not gone.memory.any()
    # Back down where it slid to: no friction left over from the slide.
    again = FingertipContact((Fingertip(0.008, centre=centre + [0.002, 0, 0], **SOFT_TIP),), params)
    st = again.update(body, slid.x, np.zeros_like(slid.x), 0.0, gone)
    rep = again.report(body, slid.x, slid.v, 0.0, st, static=True)
    assert rep.contacts[0] >= 1 and rep.normal[0] > 0.5
    assert rep.tangential[0] < 1e-9 * rep.normal[0]
    # ... whereas the state carried over from the slide is still loaded at the Coulomb limit.
    kept = fc.report(body, slid.x, slid.v, 2e-3, fs, static=True)
    assert kept.tangential[0] == pytest.approx(MU * kept.normal[0], rel=0.01)


def test_fingertip_on_compliant_foam_does_not_slip_below_the_coulomb_limit():
    """On the compliant foam cube, a pressed fingertip moved sideways 0.3 mm is held at
    f_t ~ 0.23 f_n: Algorithm 1 says it sticks (slip only when f_stick > mu f_n)."""
    mesh = box(0.05, 4)
    body = build_body(mesh, preset("foam"), mass=0.0125)
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=1.0, name="table")
    params = ContactParams(mu=MU)
    cache = SolverCache()
    fc = FingertipContact((Fingertip(0.008, centre=[0.003, 0.002, 0.058], velocity=[0, 0, -1.0]),), params)
    scene = Scene(body, (table, fc))
    state = scene.initial_state()
    for t in (0.5e-3, 1e-3):
        state, _ = solve_static(scene, state, t=t, cache=cache)
    drag = FingertipContact((Fingertip(0.008, centre=[0.003, 0.002, 0.057], velocity=[1.0, 0, 0]),), params)
    scene = Scene(body, (table, drag))
    state = State(state.x, state.v, 0.0, state.contacts)
    for s in (0.3e-3, 0.6e-3):
        state, _ = solve_static(scene, state, t=s, cache=cache)
        rep = drag.report(body, state.x, state.v, s, state.contacts[1], static=True)
        ratio = rep.tangential[0] / rep.normal[0]
        assert 0.1 < ratio < 0.9 * MU
        assert np.abs(state.contacts[1].slip).max() == 0.0, f"slipped at f_t / f_n = {ratio:.3f} < mu = {MU}"


# --------------------------------------------------------------------------- 6. mesh refinement


@functools.cache
def _indentation(n: int, rule: str, where: str, travel: float, law: str = "paper") -> tuple[float, int]:
    """Vertical force [N] on a frictionless rigid fingertip (R = 8 mm) pushed ``travel`` into the
    top of the foam cube box(0.05, n) standing on a rough table, in three static increments, and
    the number of facets it touches. ``where``: over the grid node at the top centre (n even; 8
    facets share it) or inside a facet, at the same place relative to the cell for every n.

    The fingertip is frictionless so that the result does not depend on the loading path. ``law``:
    the paper's normal law (whose recorded behaviour the tests below describe) or the resolved one."""
    h = 0.05 / n
    xy = {"node": (0.0, 0.0), "facet": (h / 2, h / 6)}[where]
    body = build_body(box(0.05, n), preset("foam"), mass=0.0125)
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.8, name="table")
    finger = Fingertip(0.008, centre=[xy[0], xy[1], 0.058], velocity=[0, 0, -1.0])
    fc = FingertipContact((finger,), ContactParams(law=law, mu=0.0, rule=rule))
    scene = Scene(body, (table, fc))
    state = scene.initial_state()
    cache = SolverCache()
    steps = 3 if law == "paper" else max(2, round(travel / 5e-4))  # the resolved law: 0.5 mm or less
    before = None
    for t in np.linspace(0, travel, steps + 1)[1:]:
        # Newton starts from the last two rests extrapolated (the same rest, found in fewer
        # iterations: the fingertip is frictionless, so no anchor depends on the path).
        guess = None if before is None else 2.0 * state.x - before
        before = state.x.copy()
        state, _ = solve_static(scene, state, t=float(t), cache=cache, guess=guess)
    rep = fc.report(body, state.x, state.v, state.t, state.contacts[1], static=True)
    return float(-rep.force[0, 2]), int(rep.contacts[0])


def _changes(forces) -> np.ndarray:
    f = np.asarray(forces)
    return np.abs(np.diff(f)) / f[1:]


def test_patch_rule_indentation_force_converges_under_refinement():
    """Default rule, 3 mm into the foam cube, n = 6, 8, 10. Over the top-centre node the force
    changes by < 3 % between successive refinements while the patch grows from 8 to 32 facets
    (measured 57.2, 56.7, 58.0 N: 0.9 %, 2.2 %); over a facet it converges from above, each change
    less than half the previous (74.9, 65.2, 60.9 N: 14.9 %, 7.1 %), and the two landing points
    draw together (31 % apart at n = 6, 5 % at n = 10). (At 1.5 mm over a facet it does not yet
    converge in this range: `test_paper_law_counts_the_object_compliance_twice`.)"""
    node = [_indentation(n, "patch", "node", 3e-3) for n in (6, 8, 10)]
    facet = [_indentation(n, "patch", "facet", 3e-3) for n in (6, 8, 10)]
    f_node = np.array([f for f, _ in node])
    f_facet = np.array([f for f, _ in facet])
    assert [k for _, k in node] == [8, 16, 32]  # the patch spreads over more, smaller facets
    assert (_changes(f_node) < 0.03).all(), f_node
    ch = _changes(f_facet)
    assert ch[1] < 0.5 * ch[0], f_facet
    assert (np.diff(f_facet) < 0).all(), f_facet
    apart = f_facet / f_node - 1
    assert (np.diff(apart) < 0).all() and apart[-1] < 0.1, apart


@pytest.mark.slow
def test_literal_facet_rule_under_the_same_refinement():
    """Recorded behaviour of the paper's literal rule in the same refinement: it converges (104.3,
    98.8, 95.9 N: 5.5 %, 3.1 %) to 1.65-1.85 times the patch rule's force, because all 8 facets
    around the node under the fingertip each carry a full K delta^n. Its mesh dependence is on the
    number of facets meeting under the fingertip, which this refinement keeps at 8 (see the next
    test for where the fingertip lands)."""
    facet = [_indentation(n, "facet", "node", 3e-3) for n in (6, 8, 10)]
    patch = [_indentation(n, "patch", "node", 3e-3) for n in (6, 8, 10)]
    assert [k for _, k in facet] == [8, 8, 8]
    ff = np.array([f for f, _ in facet])
    fp = np.array([f for f, _ in patch])
    assert (_changes(ff) < 0.10).all(), ff
    assert ((ff / fp > 1.6) & (ff / fp < 1.9)).all(), ff / fp


def test_force_depends_on_where_the_fingertip_lands_on_a_coarse_mesh():
    """Recorded behaviour on the default cube mesh (n = 6, h = 8.3 mm), 1.5 mm of travel: over a
    facet interior both rules nearly coincide (the literal rule touches one facet, 31.1 N; the
    patch rule also the neighbours the sphere overlaps, 7 facets, 31.0 N). Over the node shared by 8
    facets the literal rule gives 1.42 times that (44.1 N): its total contact stiffness is 8 K.
    The patch rule removes that factor (exact on a rigid surface, see above), yet still gives
    0.77 times the facet-interior force there (23.9 N): the contact patch (radius ~4 mm) is
    smaller than the elements, so the load sits on one node instead of three, and the discrete
    body is softer under the more concentrated load."""
    f_facet = {rule: _indentation(6, rule, "facet", 1.5e-3) for rule in ("patch", "facet")}
    f_node = {rule: _indentation(6, rule, "node", 1.5e-3) for rule in ("patch", "facet")}
    assert f_facet["patch"][0] == pytest.approx(f_facet["facet"][0], rel=0.02)
    assert f_facet["facet"][1] == 1
    assert f_node["patch"][1] == f_node["facet"][1] == 8
    base = f_facet["patch"][0]
    assert f_node["facet"][0] / base == pytest.approx(1.42, abs=0.05)
    assert f_node["patch"][0] / base == pytest.approx(0.77, abs=0.05)


def test_paper_law_counts_the_object_compliance_twice():
    """Recorded behaviour of the paper's law (Hertz's K delta^n with the object's own E, in series
    with the meshed body, which deforms too): at 1.5 mm over a facet the force falls by more than
    10 % per refinement (n = 6, 8, 10), away from Hertz's sphere on a half-space, as the mesh
    resolves more of the compliance the law already contains."""
    forces = np.array([_indentation(n, "patch", "facet", 1.5e-3)[0] for n in (6, 8, 10)])
    assert (np.diff(forces) < 0).all() and (_changes(forces) > 0.10).all(), forces
    assert forces[-1] < 0.8 * _hertz_force(1.5e-3)


def _hertz_force(depth: float, R: float = 0.008) -> float:
    """Hertz's rigid sphere on the foam's half-space: 4/3 E* sqrt(R) delta^1.5 [N]."""
    mat = preset("foam")
    return 4.0 / 3.0 * mat.E / (1.0 - mat.nu**2) * math.sqrt(R) * depth**1.5


@pytest.mark.parametrize("where", ["facet", "node"])
def test_resolved_law_follows_hertz_under_refinement(where):
    """The default law counts the object's compliance once (Hertz's law less what the mesh
    resolves): 0.5 mm into the foam cube the force is within 10 % of Hertz's (a closed form the
    code does not use: the cube is 6 fingertip radii wide and deep, nearly a half-space) on the
    default mesh (n = 6) and three refinements, over a facet and over a node (the paper's law:
    0.77 to 0.54 of Hertz's over the same range). Over a facet it changes by less than 5 % per
    refinement. Measured: facet 1.06, 1.07, 1.06, 1.05; node 1.08, 1.03, 0.99, 0.96 (5.1, 4.4 and
    2.8 % per refinement)."""
    forces = np.array([_indentation(n, "patch", where, 5e-4, "resolved")[0] for n in (6, 8, 10, 12)])
    ratio = forces / _hertz_force(5e-4)
    assert (np.abs(ratio - 1.0) < 0.10).all(), ratio
    if where == "facet":
        assert (_changes(forces) < 0.05).all(), ratio


def test_the_penetration_at_a_force_inverts_the_normal_law():
    """``penetration_value`` (where the force-controlled closing starts each finger) returns the
    penetration at which the elastic normal law gives a force: the paper's law in closed form,
    (F / K)^(1/n); under the resolved law it lies between Hertz's (F / K)^(2/3), a fully
    unresolved contact, and that less the share r of it, a fully resolved one, and the law gives
    the force back there, on a coarse and a fine mesh."""
    from softgrasp.physics.fingertip.resolved import elastic_normal_value, penetration_value

    R, K = 0.008, 2.0e4
    for F in (1e-3, 0.3, 20.0):
        assert penetration_value(F, R, K, 2.0, 0.0, 0.0, 0.0, 0.0) == pytest.approx((F / K) ** 0.5, rel=1e-12)
        hertz = (F / K) ** (2 / 3)
        for h in (5e-3, 2e-4):  # the mesh's resolution length: coarse, fine
            d = penetration_value(F, R, K, 1.5, 0.9, h, 1.5 * h, 2 * h)
            assert (1 - 0.9) * hertz < d < hertz
            assert elastic_normal_value(d, R, K, 1.5, 0.9, h, 1.5 * h, 2 * h)[0] == pytest.approx(F, rel=1e-9)
    assert penetration_value(0.0, R, K, 1.5, 0.9, 1e-3, 1e-3, 1e-3) == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("where", ["facet", "node"])
def test_resolved_law_follows_hertz_deeper_on_finer_meshes(where):
    """2 mm into the cube (contact radius ~4 mm, larger than the facets of the finer meshes)
    over a facet and over a node of n = 8, 10 and 12 cells a side: within 10 % of Hertz's.
    Measured: facet 0.99, 0.94, 0.91; node 0.92, 0.98, 0.99."""
    forces = np.array([_indentation(n, "patch", where, 2e-3, "resolved")[0] for n in (8, 10, 12)])
    ratio = forces / _hertz_force(2e-3)
    assert (np.abs(ratio - 1.0) < 0.10).all(), (where, ratio)


# --------------------------------------------------------------------------- 7. misses and errors


def test_fingertip_that_misses_gives_zero_force():
    mesh = box(0.02, 2)
    body = build_body(mesh, preset("foam"), mass=0.01)
    x = np.asarray(mesh.points)
    v = np.ones_like(x)
    R = 0.008
    for centre in ([0.0, 0.0, 0.02 + R + 1e-9], [0.05, 0.0, 0.01], [0.0, -0.0105 - R, 0.01]):
        fc = FingertipContact((Fingertip(R, centre=centre, velocity=[0, 0, -1.0]),))
        state = fc.init_state(body, x)
        assert not state.active.any()
        assert not fc.forces(body, x, v, 0.0, state).any()
        assert not fc.static_forces(body, x, 0.0, state).any()
        rep = fc.report(body, x, v, 0.0, state)
        for field in (rep.force, rep.moment, rep.normal, rep.tangential, rep.contacts, rep.depth):
            assert not np.any(field)


def test_overlap_near_a_convex_edge():
    """A fingertip pressed 1 mm into the top of a box 0.5 mm beyond its edge (centre outside the
    side face's plane too): the paper's detection rule (Sec. 3.1: the centre's projection must fall
    inside a facet) finds no facet and no force; the patch rule finds the facets the sphere
    overlaps, the deepest by R - |c - Q| to the edge point Q (0.98 mm, not the plane's 1 mm), and
    the normal forces add up to K overlap^n. 3 mm beyond the edge the sphere still overlaps the
    edge (by 0.38 mm): one top and one side facet share the closest point, and their forces,
    weighted by the area each shows the centre, add up to a push along c - Q, as a sphere on a
    sharp edge pushes."""
    mesh = box(0.02, 2)
    body = build_body(mesh, preset("foam"), mass=0.01)
    x = np.asarray(mesh.points)
    R = 0.008
    mat = preset("foam")
    K = 2.0 * mat.E / (1.0 - mat.nu**2) * math.sqrt(R)
    centre = np.array([0.01 + 0.0005, 0.0025, 0.02 + R - 0.001])
    overlap = R - math.hypot(0.0005, R - 0.001)
    fc = FingertipContact((Fingertip(R, centre=centre),), PAPER)
    state = fc.init_state(body, x)
    rep = fc.report(body, x, np.zeros_like(x), 0.0, state, static=True)
    assert rep.contacts[0] >= 1
    assert rep.depth[0] == pytest.approx(overlap, rel=1e-12)
    assert rep.normal[0] == pytest.approx(K * overlap**1.5, rel=1e-12)
    assert rep.force[0, 2] < 0 and rep.force[0, 0] < 0  # down, and off the edge
    assert (fc.pairs(body, x, 0.0).facing < 1).all()
    literal = FingertipContact((Fingertip(R, centre=centre),), ContactParams(law="paper", rule="facet"))
    st = literal.init_state(body, x)
    assert literal.report(body, x, np.zeros_like(x), 0.0, st).contacts.tolist() == [0]
    assert not literal.static_forces(body, x, 0.0, st).any()
    c_far = centre + [0.0025, 0, 0]
    far = FingertipContact((Fingertip(R, centre=c_far),), PAPER)
    rep = far.report(body, x, np.zeros_like(x), 0.0, far.init_state(body, x), static=True)
    edge_point = np.array([0.01, 0.0025, 0.02])
    overlap = R - np.linalg.norm(c_far - edge_point)
    assert rep.contacts.tolist() == [2]
    assert rep.depth[0] == pytest.approx(overlap, rel=1e-12)
    assert rep.normal[0] == pytest.approx(K * overlap**1.5, rel=1e-12)
    push = (edge_point - c_far) / np.linalg.norm(edge_point - c_far)
    assert rep.force[0] / np.linalg.norm(rep.force[0]) == pytest.approx(push, abs=1e-12)


def test_a_tangent_fingertip_on_a_convex_mesh_has_no_phantom_contact():
    """On the faceted sphere, a fingertip tangent to a facet at its centroid overlaps the planes of
    the neighbouring facets extended past their edges (a convex surface bends away beneath them),
    but not the facets themselves: no force; pressed 0.1 mm it feels exactly K (0.1 mm)^n."""
    mesh, material, mass = make_object("sphere", 0.016)
    body = build_body(mesh, material, mass=mass)
    x = np.asarray(mesh.points)
    R = 0.008
    K = 2.0 * material.E / (1.0 - material.nu**2) * math.sqrt(R)
    tri = x[mesh.facets]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    for j in range(0, len(mesh.facets), 37):
        p = tri[j].mean(axis=0)
        for delta in (-1e-9, 1e-4):
            fc = FingertipContact((Fingertip(R, centre=p + (R - delta) * nrm[j]),), PAPER)
            rep = fc.report(body, x, np.zeros_like(x), 0.0, fc.init_state(body, x), static=True)
            if delta < 0:
                assert rep.contacts[0] == 0
            else:
                assert rep.normal[0] == pytest.approx(K * delta**1.5, rel=1e-9)


def test_fingertip_starting_inside_the_object_is_refused():
    mesh = box(0.02, 2)
    body = build_body(mesh, preset("foam"), mass=0.01)
    fc = FingertipContact(
        (Fingertip(0.008, centre=[0, 0, 0.05], name="thumb"), Fingertip(0.008, centre=[0.001, 0.002, 0.015]))
    )
    with pytest.raises(ContactError, match=r"fingertip 'finger' starts with its centre inside the object"):
        fc.init_state(body, np.asarray(mesh.points))
    with pytest.raises(ContactError, match="start it outside the surface"):
        Scene(body, (fc,)).initial_state()
    # The check uses the time given: a fingertip that has moved in by then is refused too.
    moving = FingertipContact((Fingertip(0.008, centre=[0, 0, 0.03], velocity=[0, 0, -1.0], name="thumb"),))
    moving.init_state(body, np.asarray(mesh.points), 0.0)
    with pytest.raises(ContactError, match="'thumb' starts with its centre inside"):
        moving.init_state(body, np.asarray(mesh.points), 0.015)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: Fingertip(0.0), r"radius = 0.0 m is invalid; it must be > 0"),
        (lambda: Fingertip(-0.01), r"radius = -0.01 m is invalid"),
        (lambda: Fingertip(math.nan), r"radius = nan m is invalid"),
        (lambda: Fingertip(0.01, centre=[math.nan, 0, 0]), r"centre must be 3 finite numbers"),
        (lambda: Fingertip(0.01, centre=[0, 0]), r"centre must be 3 finite numbers"),
        (lambda: Fingertip(0.01, velocity=[0, math.inf, 0]), r"velocity must be 3 finite numbers"),
        (lambda: Fingertip(0.01, E=-1.0), r"E = -1.0 Pa, nu = 0.3 out of range"),
        (lambda: Fingertip(0.01, nu=0.5), r"nu = 0.5 out of range"),
        (lambda: ContactParams(gamma=-1.0), r"contact parameter gamma = -1.0 is invalid"),
        (lambda: ContactParams(mu=-0.1), r"contact parameter mu = -0.1 is invalid"),
        (lambda: ContactParams(mu=math.nan), r"contact parameter mu = nan is invalid"),
        (lambda: ContactParams(exponent=0.5), r"contact parameter exponent = 0.5 is invalid"),
        (lambda: ContactParams(rule="nodes"), r"rule must be 'patch' or 'facet', got 'nodes'"),
        (
            lambda: ContactParams(damping="viscous"),
            r"damping must be 'linear' or 'hunt-crossley', got 'viscous'",
        ),
        (lambda: FingertipContact(()), r"needs at least one fingertip"),
        (lambda: contact_damping(0.01, -1.0), r"gamma = -1.0 must be >= 0"),
        (lambda: contact_stiffness(1e6, 0.0), r"radius = 0.0 m is invalid"),
        (lambda: normal_force(1e-3, 0.0, 1.0, 1.0, damping="kelvin"), r"unknown damping form 'kelvin'"),
        (lambda: effective_modulus(math.inf, 0.3, math.inf, 0.3), r"both bodies are rigid"),
        (lambda: effective_modulus(1e6, 0.3, 1e6, 0.5), r"object: E = 1000000.0 Pa and nu = 0.5"),
        (lambda: restitution_hunt_crossley(0.0), r"beta v_in = 0.0 must be > 0"),
    ],
)
def test_invalid_contact_inputs_raise_clear_errors(make, match):
    with pytest.raises(ContactError, match=match):
        make()


# --------------------------------------------------------------------------- 8. broad phase


def _brute_force_pairs(x, facets, centres, radii, closest=False, tol=1e-12):
    """Every (finger, facet) pair, checking all facets, with area coordinates from signed
    sub-triangle areas: by Sec. 3.1 (projection inside the facet), or with ``closest`` by the
    sphere's overlap with the facet measured to its closest point. Returns
    {(finger, facet): (distance to the contact point, its barycentric coordinates)}."""
    tri = x[facets]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    twice_area = np.linalg.norm(nrm, axis=1)
    n = nrm / twice_area[:, None]
    out = {}
    for i, (c, R) in enumerate(zip(centres, radii, strict=True)):
        d = np.einsum("ij,ij->i", c - tri[:, 0], n)
        P = c - d[:, None] * n
        lam = np.stack(
            [
                np.einsum("ij,ij->i", np.cross(tri[:, (k + 1) % 3] - P, tri[:, (k + 2) % 3] - P), n)
                / twice_area
                for k in range(3)
            ],
            axis=1,
        )
        if closest:
            # Closest point of each triangle: the projection inside, else the nearest edge point.
            inside = lam.min(axis=1) >= 0
            gap = np.where(inside, d, np.inf)
            bary = np.where(inside[:, None], lam, 0.0)
            for k in range(3):
                e0, e1 = tri[:, k], tri[:, (k + 1) % 3]
                s_ = np.clip(
                    np.einsum("ij,ij->i", c - e0, e1 - e0) / np.einsum("ij,ij->i", e1 - e0, e1 - e0), 0, 1
                )
                g = np.linalg.norm(c - (e0 + s_[:, None] * (e1 - e0)), axis=1)
                better = ~inside & (g < gap)
                gap = np.where(better, g, gap)
                be = np.zeros_like(lam)
                be[:, k], be[:, (k + 1) % 3] = 1 - s_, s_
                bary = np.where(better[:, None], be, bary)
            hit = (d > 0) & (gap < R)
        else:
            gap, bary = d, lam
            hit = (d > 0) & (d < R) & (lam >= -tol).all(axis=1)
        for j in np.flatnonzero(hit):
            out[(i, int(j))] = (gap[j], bary[j])
    return out


@pytest.mark.parametrize("broad", ["tree", "nodes"])
@pytest.mark.parametrize("closest", [False, True], ids=["paper", "closest"])
def test_broad_phase_finds_exactly_the_brute_force_pairs(closest, broad):
    """The broad phases of ``detect`` miss no pair and invent none: same pairs, distances and area
    coordinates of the contact points as a check of every facet, for fingertips near the surface
    of the sphere mesh, undeformed (convex: at most one facet per fingertip with the paper's test)
    and dented (concave: several)."""
    mesh, _, _ = make_object("sphere", 0.016)
    rng = np.random.default_rng(7)
    X = np.asarray(mesh.points)
    mid = X.mean(axis=0)
    facets = mesh.facets
    total, multi = 0, 0
    for trial in range(60):
        x = X + 2e-4 * rng.standard_normal(X.shape)
        if trial % 2:  # a dent 10 mm deep and 50 mm wide somewhere on the surface
            p = X[rng.choice(np.unique(facets))]
            r = np.linalg.norm(X - p, axis=1)
            radial = (X - mid) / np.linalg.norm(X - mid, axis=1)[:, None]
            x -= (0.01 * np.clip(1 - (r / 0.025) ** 2, 0, None))[:, None] * radial
            near = np.flatnonzero(np.linalg.norm(x[facets].mean(axis=1) - p, axis=1) < 0.025)
        else:
            near = np.arange(len(facets))
        k = 10
        j = rng.choice(near, size=k)
        # Contact points spread over the facets and crowded near their corners, at distances up to
        # and just past R: where a pair is farthest from its facet's centroid (the broad phase's
        # search radius R + reach is tight there).
        w = rng.dirichlet(np.full(3, 0.3 if trial % 4 < 2 else 1.0), size=k)
        tri = x[facets[j]]
        P = np.einsum("kb,kbj->kj", w, tri)
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
        radii = rng.uniform(0.0015, 0.02, size=k)
        centres = P + rng.uniform(-0.1, 1.02, size=(k, 1)) * radii[:, None] * nrm
        centres += 0.001 * rng.standard_normal((k, 3))
        index = FacetIndex.of(mesh) if broad == "nodes" else None
        pairs = detect(x, facets, centres, radii, closest=closest, index=index)
        brute = _brute_force_pairs(x, facets, centres, radii, closest)
        found = set(zip(pairs.finger.tolist(), pairs.facet.tolist(), strict=True))
        assert found == set(brute)
        assert len(found) == len(pairs)  # no duplicates
        for i, jj, d, b in zip(pairs.finger, pairs.facet, pairs.distance, pairs.bary, strict=True):
            d_ref, lam = brute[(int(i), int(jj))]
            assert d == pytest.approx(d_ref, rel=1e-9)
            assert b == pytest.approx(lam, abs=1e-9)
        total += len(found)
        multi += int((np.bincount(pairs.finger, minlength=k) >= 2).sum())
    assert total > 350 and multi > 25  # the sample exercises many pairs and multi-facet contacts
