"""The compiled plane law (:mod:`softgrasp.physics.planes_compiled`), which PlaneContact.forces and
update run and the fused stepper runs on its arrays, against the NumPy oracle (tests/oracles/
planes.py): forces and friction state updates on nodes sticking, slipping, leaving and entering
contact, on a moving tilted plane, with and without friction."""

from __future__ import annotations

import numpy as np
import pytest

from oracles import planes as oracle
from softgrasp.model.material import Material
from softgrasp.model.mesh import box
from softgrasp.physics.body import build_body
from softgrasp.physics.planes import Plane, PlaneContact, PlaneState

pytest.importorskip("numba")
from softgrasp.physics import planes_compiled  # noqa: E402 - needs numba


@pytest.fixture(scope="module")
def body():
    return build_body(box(0.03, 3), Material(0.0793e6, 0.45, 45.5), mass=0.02)


def _case(body, seed: int):
    """Positions around a tilted plane (about half the nodes beyond it), velocities, and anchors
    some near the nodes (sticking) and some far (slipping)."""
    rng = np.random.default_rng(seed)
    n = np.array([0.2, -0.1, 1.0])
    plane = Plane([0.0, 0.0, 0.015], n, velocity=[0.01, 0.0, -0.02])
    x = np.asarray(body.mesh.points) + 1e-3 * rng.standard_normal((body.n_nodes, 3))
    v = 0.05 * rng.standard_normal(x.shape)
    t = 0.01
    rel = x - plane.point_at(t)
    tangential = rel - (rel @ plane.normal)[:, None] * plane.normal
    anchor = tangential + np.where(rng.random((len(x), 1)) < 0.5, 1e-6, 1e-3) * rng.standard_normal(x.shape)
    active = rng.random(len(x)) < 0.5
    return plane, x, v, t, PlaneState(active=active, anchor=anchor)


@pytest.mark.parametrize("mu", [0.0, 0.5])
@pytest.mark.parametrize("seed", [0, 1])
def test_forces_and_update_match_the_reference(body, mu, seed):
    plane, x, v, t, state = _case(body, seed)
    contact = PlaneContact(plane, mu=mu)
    f, s = contact.forces(body, x, v, t, state), contact.update(body, x, v, t, state)
    f_ref = oracle.plane_forces(contact, body, x, v, t, state)
    s_ref = oracle.plane_update(contact, body, x, v, t, state)
    touching = -(x - plane.point_at(t)) @ plane.normal > 0
    assert 0 < touching.sum() < len(x)
    scale = np.abs(f_ref).max()
    assert scale > 0 and np.abs(f - f_ref).max() <= 1e-12 * scale
    assert not f[~touching].any()
    np.testing.assert_array_equal(s.active, s_ref.active)
    assert np.abs(s.anchor - s_ref.anchor).max() <= 1e-15 + 1e-12 * np.abs(s_ref.anchor).max()
    if mu > 0:  # some touching nodes slip (anchor dragged), some stick (anchor kept)
        moved = np.linalg.norm(s.anchor - state.anchor, axis=1) > 0
        assert moved[touching].any() and not moved[touching].all()


def test_the_kernels_return_the_power_and_take_node_ranges(body):
    plane, x, v, t, state = _case(body, 3)
    contact = PlaneContact(plane, mu=0.5)
    k, c, kt, ct = contact._coeffs(body)
    args = (x, v, plane.point_at(t), plane.normal, plane.velocity, 0.5, k, c, kt, ct, state.anchor)
    whole = np.zeros_like(x)
    power = planes_compiled.plane_forces(*args, 0, len(x), whole)
    assert power == pytest.approx(float(np.sum(whole * v)), rel=1e-12)
    halves = np.zeros_like(x)
    cut = len(x) // 3
    p1 = planes_compiled.plane_forces(*args, 0, cut, halves)
    p2 = planes_compiled.plane_forces(*args, cut, len(x), halves)
    assert np.array_equal(halves, whole) and p1 + p2 == pytest.approx(power, rel=1e-12)
