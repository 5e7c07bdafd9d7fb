"""Backward Euler steps from rest (:func:`softgrasp.sim.static.proximal_solve`): where Newton on
the static balance finds no rest, they find the scene's own rest: the bar's closed form, and a
soft, heavy ball on the table balanced by it."""

from __future__ import annotations

import numpy as np
import pytest

from softgrasp.errors import NotConverged
from softgrasp.model.material import Material
from softgrasp.model.mesh import box
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.physics.supports import Tether
from softgrasp.sim.scene import Scene
from softgrasp.sim.static import proximal_solve, solve_static

G = 9.80665


def _table(mu: float) -> PlaneContact:
    return PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=mu, name="table")


def test_backward_euler_steps_from_rest_reach_the_bars_self_weight_rest():
    """:func:`proximal_solve` ends at the static rest, not somewhere along its steps: a prism on
    a frictionless table (tethered sideways) shortens by rho g H^2 / (2 E) under its own weight,
    as the bar's closed form says, and as the static solve finds."""
    H, E, rho = 0.06, 1e5, 1000.0
    mesh = box((0.03, 0.03, H), (4, 4, 8))
    body = build_body(mesh, Material(E, 0.45, rho))
    scene = Scene(body, (_table(0.0), Tether("xy")))
    state, _ = proximal_solve(scene, scene.initial_state(), 0.0)
    X = np.asarray(mesh.points)
    u = state.x[:, 2] - X[:, 2]
    sag = u[X[:, 2] > H - 1e-9].mean() - u[X[:, 2] < 1e-9].mean()
    assert sag == pytest.approx(-rho * G * H**2 / (2 * E), rel=0.04)
    direct, _ = solve_static(scene, scene.initial_state())
    assert np.abs(state.x - direct.x).max() < 1e-6 * abs(sag)


def test_a_soft_heavy_ball_on_which_newton_cycles_comes_to_rest_by_backward_euler_steps():
    """A 60 mm ball of E = 5 kPa, nu = 0.45 and water's density sags millimetres onto a rough
    table; Newton on the static balance cycles there (nodes flip in and out of contact) and
    finds no rest. Backward Euler steps from rest (:func:`proximal_solve`) find one: the forces
    balance to the solver's tolerance, the table carries the whole weight and no sideways force,
    its centre of pressure under the centre of mass (the ball's balance of forces and moments
    with gravity)."""
    mesh, _, _ = make_object("ball:0.03")
    body = build_body(mesh, Material(5e3, 0.45, 1000.0))
    scene = Scene(body, (_table(0.8),))
    with pytest.raises(NotConverged):
        solve_static(scene, scene.initial_state(), rtol=1e-6)
    state, _ = proximal_solve(scene, scene.initial_state(), 0.0, rtol=1e-6)
    f_int = body.internal_forces(state.x)
    f = scene.static_forces(state.x, 0.0, state.contacts, internal=f_int)
    assert np.abs(f).max() <= 1e-6 * max(np.abs(f_int).max(), np.abs(f - f_int).max())
    table = scene.interactions[0].static_forces(body, state.x, 0.0, state.contacts[0])
    R = table.sum(axis=0)
    assert R[2] == pytest.approx(body.total_mass * G, rel=1e-5)
    assert np.abs(R[:2]).max() < 1e-5 * R[2]
    # the table's centre of pressure lies under the centre of mass (no moment left)
    pressure = (table[:, 2] @ state.x[:, :2]) / R[2]
    com = body.mass @ state.x / body.total_mass
    assert np.hypot(*(pressure - com[:2])) < 1e-5 * 0.06
    X = np.asarray(mesh.points)
    sag = X[:, 2].max() - state.x[:, 2].max()
    assert 1e-3 < sag < 0.03  # millimetres, not through the table
