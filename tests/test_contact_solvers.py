"""The static solver and the explicit dynamics agree on the same fingertip increment."""

from __future__ import annotations

import numpy as np
import pytest

from softgrasp.model.material import Material
from softgrasp.model.mesh import box
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.supports import Tether
from softgrasp.sim.explicit import simulate
from softgrasp.sim.scene import Scene
from softgrasp.sim.static import solve_static


@pytest.mark.slow
@pytest.mark.parametrize("mu", [0.0, 0.8])
def test_static_and_dynamic_agree_on_an_indentation_increment(mu):
    """From the rest state at 1.5 mm, the fingertip steps to 1.7 mm. The static solve and a damped
    RK4 run from the same start must reach the same state. The body hangs on weak tethers (no
    table), whose rigid-body oscillation nothing damps, so the dynamic force is averaged over the
    last third of the run."""
    body = build_body(box(0.04, 3), Material(2e4, 0.3, 500.0), damping_ratio=1.0, gravity=0.0)
    R, top = 0.008, 0.04
    params = ContactParams(mu=mu)
    tether = Tether("xyz", ratio=0.005)

    def scene(depth: float) -> tuple[Scene, FingertipContact]:
        fc = FingertipContact((Fingertip(R, centre=[0.002, 0.001, top + R - depth]),), params)
        return Scene(body, (tether, fc)), fc

    s1, _ = scene(0.0015)
    start, _ = solve_static(s1, s1.initial_state())
    s2, fc = scene(0.0017)
    static, _ = solve_static(s2, s2.initial_state(start.x))
    f_static = fc.report(body, static.x, static.v, 0.0, static.contacts[1], static=True).force[0]

    forces, positions = [], []

    def record(s):
        if s.t > 0.2:
            forces.append(fc.report(body, s.x, s.v, s.t, s.contacts[1]).force[0])
            positions.append(s.x)

    simulate(s2, s2.initial_state(start.x), 0.3, method="rk4", callback=record, every=50)
    f_dyn = np.mean(forces, axis=0)
    x_dyn = np.mean(positions, axis=0)
    assert f_static[2] < 0
    assert f_dyn[2] == pytest.approx(f_static[2], rel=0.01)
    moved = np.abs(static.x - np.asarray(body.mesh.points)).max()
    assert np.abs(x_dyn - static.x).max() < 0.02 * moved
