"""Compression test between rigid plates (paper Fig. 8-9)."""

from __future__ import annotations

import numpy as np
import pytest

from softgrasp.errors import ConfigError
from softgrasp.experiments.compression import compression_test
from softgrasp.model.material import Material, Polynomial
from softgrasp.model.mesh import box
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body


def _force_at(res, strain: float) -> float:
    return float(np.interp(strain, res.strain, res.force_N))


@pytest.mark.slow
def test_sphere_force_converges_under_refinement():
    """The rubber sphere's force at 10 % strain changes < 10 % between successive refinements."""
    forces = []
    for h in (0.016, 0.011, 0.008):
        mesh, mat, mass = make_object("sphere", h)
        res = compression_test(build_body(mesh, mat, mass=mass), strain=0.1, steps=4)
        forces.append(_force_at(res, 0.1))
    changes = np.abs(np.diff(forces)) / np.array(forces[1:])
    assert (changes < 0.10).all(), forces


def test_polynomial_law_stiffens_the_response():
    mesh = box(0.05, 3)
    lin = compression_test(build_body(mesh, Material(1e5, 0.3, 100.0)), strain=0.2, steps=4)
    stiff = compression_test(
        build_body(mesh, Material(1e5, 0.3, 100.0, Polynomial(a3=3.0))), strain=0.2, steps=4
    )
    # Same small-strain modulus, much larger force at 20 % strain.
    assert stiff.apparent_E_Pa == pytest.approx(lin.apparent_E_Pa, rel=0.02)
    assert _force_at(stiff, 0.2) > 1.08 * _force_at(lin, 0.2)


def test_linear_box_force_is_linear_at_small_strain():
    res = compression_test(build_body(box(0.05, 3), Material(1e5, 0.3, 100.0)), strain=0.02, steps=4)
    slope = res.force_N[1:] / res.displacement_m[1:]
    assert np.ptp(slope) / slope.mean() < 0.03


def test_plate_friction_stiffens_a_box():
    """Sticking plates stop the faces from spreading (barrelling): a stiffer apparent response."""
    body = build_body(box(0.05, 4), Material(1e5, 0.45, 100.0))
    free = compression_test(body, strain=0.05, steps=2)
    stuck = compression_test(body, strain=0.05, steps=2, plate_friction=2.0)
    assert _force_at(stuck, 0.05) > 1.01 * _force_at(free, 0.05)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"strain": 0.0}, "strain = 0.0 is invalid"),
        ({"strain": 0.95}, "strain = 0.95"),
        ({"steps": 0}, "steps = 0 is invalid"),
    ],
)
def test_compression_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        compression_test(build_body(box(0.05, 2), Material(1e5, 0.3, 100.0)), **kwargs)


def test_the_simulated_curve_is_a_smooth_function_of_the_modulus_near_a_bifurcation():
    """The calibration differences simulated curves: they must change smoothly with the material.
    A cube with a softening law (a2 = -1.5, a3 = 3) compressed 30 % in 12 steps ends on an
    indefinite stiffness (about to buckle), where Newton's last iterate lands within rounding of
    its tolerance. Moduli 1e-9-1e-8 apart must give curves 1e-8-1e-7 apart, not another branch
    (single-precision preconditioners, whose rounding noise picked the buckled branch at 127.7
    instead of 131.9 N for 3 of these 4 moduli, are not used for the material tests)."""
    mesh, _, mass = make_object("cube", 0.0125)
    E, nu, a2, a3 = 120033.25862870374, 0.3000230897386545, -1.5000601571824386, 2.982379468300383
    last = []
    for d in (0.0, 1e-9, 3e-9, 1e-8):
        body = build_body(mesh, Material(E * (1 + d), nu, None, Polynomial(a2, a3)), mass=mass)
        res = compression_test(body, strain=0.3, steps=12, plate_friction=0.5)
        last.append((float(res.force_N[-1]), float(res.lateral_strain[-1])))
    force, lateral = np.array(last).T
    assert np.ptp(force) <= 1e-7 * force.max(), force
    assert np.ptp(lateral) <= 1e-7 * lateral.max(), lateral


@pytest.mark.parametrize("friction", [0.0, 0.5])
def test_a_compression_that_finds_no_rest_names_the_last_strain_at_rest(monkeypatch, friction):
    """When an increment finds no rest (a stand-in solver that finds none past 10 % strain), the
    compression stops with NotConverged naming the strain it failed at and the last strain at
    rest, and advises a final strain no larger than that (and lubricated platens when they are
    rough), instead of smaller load steps."""
    from softgrasp.errors import NotConverged
    from softgrasp.experiments import compression

    real = compression.solve_increment
    H = 0.05

    def solve(scene, state, t, **kwargs):
        if t > 0.1 * H + 1e-12:
            raise NotConverged("static solve cycles", "use smaller load steps")
        return real(scene, state, t, **kwargs)

    monkeypatch.setattr(compression, "solve_increment", solve)
    body = build_body(box(H, 3), Material(1e5, 0.3, 100.0))
    with pytest.raises(NotConverged) as info:
        compression_test(body, strain=0.3, steps=10, plate_friction=friction)
    message = str(info.value)
    assert "found no rest at 12.0% strain, past 9.0%" in message, message
    assert "(static solve cycles)" in message and "load steps" not in message
    assert message.endswith(
        "compress to --strain 0.09 or less"
        + (friction > 0) * ", or with lubricated platens (--plate-friction 0)"
    )
