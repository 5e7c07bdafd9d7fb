"""Grasp without crushing: peak contact pressure, peak strain and the limits on them."""

from __future__ import annotations

import math

import numpy as np
import pytest

import softgrasp as sg
from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.grasp.config import PlanConfig
from softgrasp.grasp.damage import hertz_peak_pressure, peak_strain
from softgrasp.model.material import Material
from softgrasp.model.mesh.generate import box
from softgrasp.physics.body import build_body


def test_hertz_peak_pressure_by_hand():
    """F = 1 N, R = 8 mm, E* = 100 kPa: a = (3 F R / 4 E*)^(1/3) = (6e-8)^(1/3) = 3.9149 mm and
    p0 = 3 F / (2 pi a^2) = 31.154 kPa; the mean pressure F / (pi a^2) is 2/3 of the peak
    (Hertz's elliptical distribution), and p0 grows as F^(1/3)."""
    p0, a = hertz_peak_pressure(np.array([1.0, 8.0, 0.0]), np.full(3, 0.008), np.full(3, 1e5))
    assert a[0] == pytest.approx(6e-8 ** (1 / 3), rel=1e-12)
    assert p0[0] == pytest.approx(31153.5, rel=1e-5)
    assert 1.0 / (math.pi * a[0] ** 2) == pytest.approx(2.0 / 3.0 * p0[0], rel=1e-12)
    assert p0[1] == pytest.approx(2.0 * p0[0], rel=1e-12)  # 8 = 2^3
    assert p0[2] == 0.0 and a[2] == 0.0


def test_peak_strain_of_homogeneous_deformations():
    """A rigid rotation strains nothing; a 10 % stretch along x, 0.1; a 20 % squeeze with a 5 %
    bulge, 0.2 (the largest |stretch - 1|), whatever the rotation on top."""
    mesh = box(0.02, 2)
    body = build_body(mesh, Material(1e5, 0.3, 1000.0))
    X = np.asarray(mesh.points)
    c, s = math.cos(0.7), math.sin(0.7)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert peak_strain(body, X @ Rz.T)[0] == pytest.approx(0.0, abs=1e-12)
    assert peak_strain(body, X @ np.diag([1.1, 1.0, 1.0]))[0] == pytest.approx(0.1, rel=1e-12)
    squeeze = X @ np.diag([1.05, 1.05, 0.8]) @ Rz.T
    assert peak_strain(body, squeeze)[0] == pytest.approx(0.2, rel=1e-12)


@pytest.fixture(scope="module")
def default_plan():
    return sg.plan()


def test_plan_reports_its_load_and_limits_refuse_it(default_plan):
    """The default plan reports each finger's Hertz peak pressure (at its set-point, radius and
    modulus: recomputed here) and the peak strain; a limit below them makes the plan
    InfeasibleGrasp naming the limit (a pressure limit between the least squeeze's and the
    set-points' names the set-points), a limit above leaves the set-points as they were."""
    doc = default_plan.to_dict()
    damage = doc["damage"]
    obj = default_plan.object.material
    E_star = obj.E / (1.0 - obj.nu**2)
    for f in doc["fingers"]:
        p, a = hertz_peak_pressure(np.array([f["setpoint_N"]]), np.array([0.008]), np.array([E_star]))
        # the sphere's curvature (R_s = 64 mm) makes the effective radius smaller and p0 larger
        assert damage["peak_pressure_Pa"][f["name"]] == pytest.approx(p[0] * (8 / 7.11) ** (2 / 3), rel=0.05)
    assert 0 < damage["peak_strain"] < 0.5
    peak = max(damage["peak_pressure_Pa"].values())
    least = "the least squeeze that holds the object presses .* above --max-pressure"
    with pytest.raises(InfeasibleGrasp, match=least):
        sg.plan(max_pressure_Pa=0.5 * peak)
    # Hertz: p0 grows as F^(1/3); the set-points press (their factor over the held forces)^(1/3) more
    held = [f["normal_force_N"] for f in doc["fingers"]]
    factor = max(sp / h for sp, h in zip(doc["setpoints_N"].values(), held, strict=True))
    assert factor > 1.05
    between = peak / factor ** (1 / 6)
    with pytest.raises(InfeasibleGrasp, match="the set-points press .* lower --safety-factor"):
        sg.plan(max_pressure_Pa=between)
    with pytest.raises(InfeasibleGrasp, match="above --max-strain"):
        sg.plan(max_strain=0.5 * damage["peak_strain"])
    within = sg.plan(max_pressure_Pa=2.0 * peak, max_strain=2.0 * damage["peak_strain"])
    assert within.setpoints_N == pytest.approx(default_plan.setpoints_N, rel=1e-12)
    assert within.to_dict()["damage"]["max_pressure_Pa"] == 2.0 * peak


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_bad_limits_are_refused(bad):
    with pytest.raises(ConfigError, match="max_pressure"):
        PlanConfig(max_pressure=bad)
    with pytest.raises(ConfigError, match="max_strain"):
        PlanConfig(max_strain=bad)
