"""The smooth surface's normal at a contact (softgrasp.model.mesh.normals): checked against the
shapes' own normals (a sphere's radius, a cube's faces), an independent per-node computation, and
the grasp's rigid-body minimum across mesh sizes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from softgrasp.model.material import preset
from softgrasp.model.mesh.generate import box, sphere
from softgrasp.model.mesh.normals import CREASE_DEG
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip

R_SPHERE = 0.064


def _world(mesh) -> np.ndarray:
    """The corner normals in world axes, (F, 3, 3) [facet, corner, axis]."""
    tri = mesh.points[mesh.facets]
    n = mesh.facet_normals
    e1 = tri[:, 1] - tri[:, 0]
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(n, e1)
    c = mesh.facet_corner_normals
    return c[..., 0, None] * e1[:, None] + c[..., 1, None] * e2[:, None] + c[..., 2, None] * n[:, None]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.einsum("...i,...i->...", a, b) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def test_corner_normals_match_a_per_node_loop():
    """Each corner normal is the angle-weighted mean of the normals of the facets around its node
    within the crease angle of its own facet's, written here node by node."""
    mesh = sphere(R_SPHERE, 0.03, on_table=False)
    pts, facets, n = mesh.points, mesh.facets, mesh.facet_normals
    world = _world(mesh)
    for f in range(0, len(facets), 7):
        for i in range(3):
            v = facets[f, i]
            acc = np.zeros(3)
            for g in np.flatnonzero((facets == v).any(axis=1)):
                if np.dot(n[g], n[f]) < math.cos(math.radians(CREASE_DEG)):
                    continue
                k = int(np.flatnonzero(facets[g] == v)[0])
                a = pts[facets[g, (k + 1) % 3]] - pts[v]
                b = pts[facets[g, (k + 2) % 3]] - pts[v]
                acc += math.acos(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b)) * n[g]
            np.testing.assert_allclose(world[f, i], acc / np.linalg.norm(acc), atol=1e-12)


@pytest.mark.parametrize("h", [0.03, 0.016, 0.008])
def test_sphere_corner_normals_are_the_radius(h):
    """On a meshed sphere the corner normals lie within about a tenth of the facets' own tilt of
    the sphere's radius, and the tilt they remove shrinks with the mesh."""
    mesh = sphere(R_SPHERE, h, on_table=False)
    tri = mesh.points[mesh.facets]
    radial = tri / np.linalg.norm(tri, axis=2)[:, :, None]  # the mesh is centred on the origin
    smooth = _angle_deg(_world(mesh), radial).max()
    facet = _angle_deg(mesh.facet_normals[:, None, :], radial).max()
    assert smooth < 0.25 * facet
    assert smooth < math.degrees(h / R_SPHERE) / 4


def test_flat_faces_keep_their_normals():
    """A cube's faces meet at 90°: every corner normal is its facet's own, exactly."""
    mesh = box(0.03, 3)
    c = mesh.facet_corner_normals
    np.testing.assert_allclose(c[..., 2], 1.0, atol=1e-15)
    np.testing.assert_allclose(c[..., :2], 0.0, atol=1e-15)


def _push_directions(normals: str, points: np.ndarray, depth: float) -> np.ndarray:
    """The direction of the force a rigid 8 mm fingertip, centred on the radius through each of
    ``points`` (unit directions) and pressed ``depth`` [m] into the faceted 16 mm sphere mesh,
    puts on it, at rest."""
    mesh = sphere(R_SPHERE, 0.016, on_table=False)
    body = build_body(mesh, preset("rubber"), mass=0.05)
    x = np.asarray(mesh.points, dtype=np.float64)
    out = []
    for u in points:
        r = R_SPHERE + 0.008 - depth  # the sphere's surface, then the facets' (which lie inside it)
        for _ in range(3):
            tips = (Fingertip(0.008, centre=u * r),)
            contact = FingertipContact(tips, ContactParams(normals=normals))
            pairs = contact.pairs(body, x, 0.0)
            r -= depth - (pairs.depth.max() if len(pairs) else 0.0)
        tips = (Fingertip(0.008, centre=u * r),)
        contact = FingertipContact(tips, ContactParams(normals=normals))
        state = contact.init_state(body, x, 0.0)
        rep = contact.report(body, x, None, 0.0, state, static=True)
        out.append(rep.force[0] / np.linalg.norm(rep.force[0]))
    return np.array(out)


def test_fingertip_pushes_along_the_spheres_normal():
    """A fingertip pressed 0.8 mm into the faceted sphere (the default plan's penetration) pushes
    it along the sphere's own normal (into the centre, along the fingertip's radius) to within
    about half the deviation that the facets' normals give, wherever it lands on them."""
    rng = np.random.default_rng(3)
    u = rng.normal(size=(40, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    smooth = _angle_deg(_push_directions("smooth", u, 0.0008), -u)
    facet = _angle_deg(_push_directions("facet", u, 0.0008), -u)
    assert np.median(smooth) < 0.6 * np.median(facet)
    assert smooth.max() < facet.max()
    assert smooth.max() < 2.5


def test_paper_law_uses_facet_normals():
    """The paper's law keeps the paper's facet normals; the default law the smooth surface's."""
    assert ContactParams().normals == "smooth"
    assert ContactParams(law="paper").normals == "facet"
    assert ContactParams().describe()["normals"] == "smooth"


#: Mesh sizes around the default sphere's (0.016 m), +-10 %.
MESH_SIZES = (0.0145, 0.015, 0.0155, 0.016, 0.0165, 0.017, 0.0175)


@pytest.fixture(scope="module")
def plans_by_mesh_size():
    import softgrasp as sg

    return {h: sg.plan(sg.load_object("sphere", mesh_size_m=h)) for h in MESH_SIZES}


def _spread(values) -> float:
    """Largest relative deviation from the median."""
    v = np.asarray(list(values))
    return float(np.abs(v / np.median(v) - 1.0).max())


def test_grasp_geometry_does_not_depend_on_the_mesh(plans_by_mesh_size):
    """The least total normal force a rigid object would need at each plan's held contacts, along
    its fingertips' pushes, is the same within 2 % for every mesh size near the default (the
    contacts lie on one sphere; 0.8 % here). With the facets' normals it deviated by up to 3.8 %
    from the median: each mesh tilts them differently."""
    rigid = [float(np.sum(p.grasp.rigid_normal_forces)) for p in plans_by_mesh_size.values()]
    assert _spread(rigid) < 0.02


def test_setpoints_do_not_depend_on_the_mesh(plans_by_mesh_size):
    """The set-points' total changes by less than 3 % from its median with the mesh size near the
    default (#39's target; 2.75 % at most here, with the critical scale bisected to 1 % of the
    held state's forces: to 2 % it was 3.03 %, one mesh's set-points 2 % above its bracket's
    lower end). With the facets' normals the totals deviated by up
    to 8.4 %; with the hold check's former slip limit of 1 % of the object's size the default
    mesh's stood 4 % below the others' (its thumb slid 1.3 mm and held at 0.91 of the forces
    that hold a rigid object)."""
    totals = [sum(p.setpoints_N.values()) for p in plans_by_mesh_size.values()]
    assert _spread(totals) < 0.03
