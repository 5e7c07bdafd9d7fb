"""Materials: presets from the paper's Table 1, laws, and every validation error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from softgrasp.errors import MaterialError
from softgrasp.model.material import Linear, Material, Polynomial, Tabulated, parse_material, preset


def test_presets_match_table_1():
    foam, rubber = preset("foam"), preset("rubber")
    assert (foam.E, foam.nu) == (4.9284e6, 0.39)
    assert (rubber.E, rubber.nu) == (0.0793e6, 0.45)
    # The sphere of Sec. 4.2: radius 0.064 m, mass 0.05 kg.
    assert rubber.density * 4 / 3 * math.pi * 0.064**3 == pytest.approx(0.05, rel=1e-12)


def test_lame_constants_are_consistent():
    m = Material(1e5, 0.3, 50.0)
    # E = mu (3 lambda + 2 mu) / (lambda + mu) and nu = lambda / (2 (lambda + mu)).
    lam, mu = m.lame_lambda, m.shear_modulus
    assert mu * (3 * lam + 2 * mu) / (lam + mu) == pytest.approx(1e5, rel=1e-12)
    assert lam / (2 * (lam + mu)) == pytest.approx(0.3, rel=1e-12)
    assert m.bulk_modulus == pytest.approx(lam + 2 * mu / 3, rel=1e-12)


@pytest.mark.parametrize(
    "law",
    [
        Linear(),
        Polynomial(a2=-0.5, a3=2.0),
        Polynomial(a3=-0.3),
        Tabulated(np.array([0.1, 0.2, 0.4]), np.array([1.0e4, 2.5e4, 8.0e4])),
    ],
)
def test_law_normalised_and_consistent(law):
    e = np.linspace(-0.5, 0.5, 201)
    s, ds, w = law.stress(e), law.tangent(e), law.energy(e)
    assert law.stress(np.array([0.0]))[0] == pytest.approx(0.0, abs=1e-15)
    assert law.tangent(np.array([0.0]))[0] == pytest.approx(1.0, rel=1e-9)
    # tangent is the derivative of stress, stress the derivative of energy (central differences)
    h = 1e-6
    np.testing.assert_allclose((law.stress(e + h) - law.stress(e - h)) / (2 * h), ds, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose((law.energy(e + h) - law.energy(e - h)) / (2 * h), s, rtol=1e-6, atol=1e-9)
    assert w.min() >= 0.0
    assert (np.diff(s) > 0).all()


def test_polynomial_stiffening_and_softening():
    e = np.array([-0.3, 0.3])
    assert (np.abs(Polynomial(a3=1.0).stress(e)) > 0.3).all()
    assert (np.abs(Polynomial(a3=-0.5).stress(e)) < 0.3).all()


def test_tabulated_mirrors_compression_data():
    t = Tabulated(np.array([0.1, 0.2]), np.array([1e4, 3e4]))
    np.testing.assert_allclose(t.stress(np.array([-0.2, 0.2])) * t.E0, [-3e4, 3e4], rtol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"E": 0.0, "nu": 0.3}, r"E = 0.0 Pa is invalid: it must be > 0"),
        ({"E": -5.0, "nu": 0.3}, r"must be > 0"),
        ({"E": float("nan"), "nu": 0.3}, r"must be > 0"),
        ({"E": 1e5, "nu": 0.5}, r"nu = 0.5 is invalid: it must lie in \(-1, 0.5\)"),
        ({"E": 1e5, "nu": -1.0}, r"must lie in \(-1, 0.5\)"),
        ({"E": 1e5, "nu": 0.3, "density": -1.0}, r"density = -1.0 kg/m\^3 is invalid"),
        ({"E": 1e5, "nu": 0.3, "density": 0.0}, r"density"),
    ],
)
def test_material_errors(kwargs, match):
    with pytest.raises(MaterialError, match=match):
        Material(**kwargs)


def test_law_errors():
    with pytest.raises(MaterialError, match="not increasing at strain"):
        Polynomial(a3=-3.0)
    with pytest.raises(MaterialError, match="not monotonic"):
        Tabulated(np.array([0.1, 0.2, 0.3]), np.array([1e4, 3e4, 2e4]))
    with pytest.raises(MaterialError, match="repeats strain"):
        Tabulated(np.array([0.1, 0.1, 0.3]), np.array([1e4, 2e4, 3e4]))
    with pytest.raises(MaterialError, match="at least 2 points"):
        Tabulated(np.array([0.1]), np.array([1e4]))
    with pytest.raises(MaterialError, match="2 strains but 3 stresses"):
        Tabulated(np.array([0.1, 0.2]), np.array([1e4, 2e4, 3e4]))


def test_parse_material():
    m, mass = parse_material("rubber")
    assert m.E == 0.0793e6 and mass is None
    m, mass = parse_material("E=80e3,nu=0.4,mass=0.05")
    assert (m.E, m.nu, m.density, mass) == (80e3, 0.4, None, 0.05)
    m, _ = parse_material("foam,nu=0.3,a3=0.5")
    assert m.nu == 0.3 and isinstance(m.law, Polynomial)
    for bad, match in [
        ("", "empty"),
        ("steel", "unknown material 'steel'"),
        ("E=1e5", "lacks nu"),
        ("E=1e5,nu=0.3", "needs density"),
        ("E=abc,nu=0.3,density=1", "not a number"),
        ("E=1e5,nu=0.3,density=1,colour=3", "unknown material key 'colour'"),
        ("E=1e5,nu=0.3,mass=-2", "mass = -2.0 kg is invalid"),
        ("E=1e5,nu=0.7,density=5", "nu = 0.7"),
    ]:
        with pytest.raises(MaterialError, match=match):
            parse_material(bad)
