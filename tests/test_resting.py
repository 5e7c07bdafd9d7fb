"""The approach of a body resting on the table, estimated before the settle solves for it
(:mod:`softgrasp.physics.resting`): against Hertz on a sphere, a flat punch on a flat face, and
the settle it starts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from softgrasp.physics.resting import lowered_onto_table, resting_approach

R = 0.04  # sphere radius [m]
E_STAR = 1.0e6 / (1.0 - 0.45**2)  # contact modulus against a rigid table [Pa]


def _spherical_cap(radius: float, rings: int = 400, segments: int = 256, theta_max: float = 0.5):
    """A triangulated spherical cap around the south pole (lowest point at z = 0), the polar angle
    up to ``theta_max``, rings denser towards the pole; facets ordered for outward (downward)
    normals."""
    theta = theta_max * (np.arange(1, rings + 1) / rings) ** 2
    phi = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack(
        [
            radius * np.sin(theta)[:, None] * np.cos(phi)[None, :],
            radius * np.sin(theta)[:, None] * np.sin(phi)[None, :],
            radius * (1.0 - np.cos(theta))[:, None] * np.ones(segments)[None, :],
        ],
        axis=-1,
    ).reshape(-1, 3)
    points = np.vstack([[0.0, 0.0, 0.0], ring])
    idx = 1 + np.arange(rings * segments).reshape(rings, segments)
    nxt = np.roll(idx, -1, axis=1)
    facets = [np.stack([np.zeros(segments, dtype=int), nxt[0], idx[0]], axis=1)]
    for k in range(rings - 1):
        facets.append(np.stack([idx[k], nxt[k], nxt[k + 1]], axis=1))
        facets.append(np.stack([idx[k], nxt[k + 1], idx[k + 1]], axis=1))
    return points, np.vstack(facets)


def _hertz_approach(weight: float) -> float:
    """Hertz's approach of a sphere of radius R on a rigid plane: (9 W^2 / (16 R E*^2))^(1/3)."""
    return (9.0 * weight**2 / (16.0 * R * E_STAR**2)) ** (1.0 / 3.0)


def test_the_cap_faces_down():
    points, facets = _spherical_cap(R, rings=4, segments=8)
    p = points[facets]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (n[:, 2] < 0).all()


@pytest.mark.parametrize("weight", [0.05, 0.5, 5.0])
def test_on_a_sphere_the_approach_is_the_flat_punch_foundations_closed_form_near_hertz(weight):
    """On a paraboloid the foundation gives W = sqrt(2 R) E* delta^(3/2) (the integral of
    2 E* / (pi a) (delta - r^2 / 2R) over the disc a^2 = 2 R delta), Hertz (4/3) sqrt(R) E*
    delta^(3/2): the approach (4 / (3 sqrt 2))^(2/3) = 0.9615 of Hertz's, whatever the load."""
    points, facets = _spherical_cap(R)
    delta = resting_approach(points, facets, weight, E_STAR)
    closed_form = (weight / (E_STAR * math.sqrt(2.0 * R))) ** (2.0 / 3.0)
    assert delta == pytest.approx(closed_form, rel=0.01)
    # The same statement against Hertz (algebra from the closed form: the 4 % the docs quote).
    assert delta / _hertz_approach(weight) == pytest.approx(
        (4.0 / (3.0 * math.sqrt(2.0))) ** (2.0 / 3.0), rel=0.01
    )


def test_lowered_by_half_the_approach_the_sphere_touches_over_hertzs_contact_disc():
    """Lowered by half its approach, the sphere's nodes below the table are exactly those inside
    the circle where the plane cuts it, of radius a^2 = R delta - delta^2 / 4: Hertz's contact
    radius sqrt(R delta) to 2 % (the approach is 4 % short of Hertz's). Nothing moves sideways."""
    points, facets = _spherical_cap(R)
    weight = 0.5
    delta = resting_approach(points, facets, weight, E_STAR)
    lowered = lowered_onto_table(points, facets, weight, E_STAR)
    np.testing.assert_allclose(lowered[:, :2], points[:, :2], rtol=0, atol=0)
    np.testing.assert_allclose(points[:, 2] - lowered[:, 2], delta / 2, rtol=1e-9)
    r = np.hypot(points[:, 0], points[:, 1])
    touching = lowered[:, 2] < 0.0
    cut = math.sqrt(R * delta - delta**2 / 4)
    assert r[touching].max() < cut < r[~touching].min()
    assert cut / math.sqrt(R * _hertz_approach(weight)) == pytest.approx(0.9806, abs=0.005)


def test_a_flat_face_sinks_as_a_rigid_flat_punch_of_its_area():
    """A square face of side L flat on the table: every node touches at once, and the approach
    is the circular flat punch's of the same area, W / (2 E* a) with pi a^2 = L^2. Facets that
    face up (the block's top) carry nothing."""
    L, n = 0.03, 12
    u = np.linspace(0.0, L, n + 1)
    X, Y = np.meshgrid(u, u, indexing="ij")
    bottom = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    top = bottom + [0.0, 0.0, 0.02]
    points = np.vstack([bottom, top])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a_, b_, c_, d_ = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    down = np.vstack([np.stack([a_, c_, b_], 1), np.stack([a_, d_, c_], 1)])  # normals -z
    up = down[:, ::-1] + (n + 1) ** 2  # normals +z
    weight = 2.0
    delta = resting_approach(points, np.vstack([down, up]), weight, E_STAR)
    assert delta == pytest.approx(weight / (2.0 * E_STAR * L / math.sqrt(math.pi)), rel=1e-12)
    assert resting_approach(points, up, weight, E_STAR) == 0.0  # nothing faces the table


def test_where_a_joining_node_drops_the_load_the_first_approach_that_fits_is_taken():
    """The foundation's load grows with the approach between nodes but drops where a node joins
    (the stiffness per area falls as the touching area grows): a small first facet and a large
    second one 0.1 mm above give two approaches that carry the weight; the body lowered onto the
    table reaches the smaller first, on the first node alone."""
    area = (1e-6, 1e-4)  # the nodes' downward areas [m^2]
    h = (0.0, 1e-4)

    def load(d):  # the foundation's load at approach d [N], evaluated directly
        on = [k for k in range(2) if h[k] < d]
        S = sum(area[k] for k in on)
        return 2.0 * E_STAR / (math.pi * math.sqrt(S / math.pi)) * sum(area[k] * (d - h[k]) for k in on)

    # Two single-node "facets": a downward triangle of the given area on each node, its other
    # corners far up (carrying nothing: facets are split by thirds, so each node gets a third).
    points, facets = [], []
    for k in range(2):
        side = math.sqrt(2.0 * 3.0 * area[k])  # a right triangle of area 3 A_k, a third to node k
        base = len(points)
        points += [[10.0 * k, 0.0, h[k]], [10.0 * k + side, 0.0, 1.0], [10.0 * k, side, 1.0]]
        facets.append([base, base + 2, base + 1])
    points, facets = np.array(points), np.array(facets)
    weight = 0.5 * load(1e-4)  # below the load as the second node joins, above it just after
    assert load(1e-4 + 1e-9) < weight
    delta = resting_approach(points, facets, weight, E_STAR)
    assert delta < 1e-4 and load(delta) == pytest.approx(weight, rel=1e-9)


@pytest.mark.parametrize(
    ("weight", "modulus", "what"),
    [(0.0, E_STAR, "weight"), (-1.0, E_STAR, "weight"), (math.inf, E_STAR, "weight"),
     (1.0, 0.0, "modulus"), (1.0, math.nan, "modulus")],
)  # fmt: skip
def test_a_weight_or_modulus_that_is_not_positive_is_refused(weight, modulus, what):
    points, facets = _spherical_cap(R, rings=4, segments=8)
    with pytest.raises(ValueError, match=what):
        resting_approach(points, facets, weight, modulus)


def test_positions_that_are_not_finite_are_refused():
    points, facets = _spherical_cap(R, rings=4, segments=8)
    points[3, 2] = np.nan
    with pytest.raises(ValueError, match="finite"):
        resting_approach(points, facets, 1.0, E_STAR)
