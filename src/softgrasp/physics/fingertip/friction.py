"""The compiled elastic-slider friction law of the fingertip contact (paper Eq. 15-16, Algorithm 1).

Each touching (fingertip, facet) pair has a stick anchor X_a (a material point of the facet, in
barycentric coordinates) and the fingertip centre's offset from it; its stick displacement v
(Eq. 16) is the tangential part of ``(c - X_a) - offset`` (:func:`_stick`), its tangential stiffness
``k_t = ratio x dF_n/d delta`` of the normal law (:func:`_tangential_stiffness`). The stick force
``-w (k_t v + c_t V_t)`` is capped by Coulomb's ``mu f_n`` (:mod:`softgrasp.physics.fingertip.forces`);
after an accepted step Algorithm 1 cuts a slipping pair's stick back to the limit
(:func:`softgrasp.physics.fingertip.compiled._update_pairs`).
"""

from __future__ import annotations

from softgrasp import jitcache
from softgrasp.physics.fingertip import resolved

__all__: list[str] = []

_jit = jitcache.jit(fastmath=False, error_model="numpy")
#: The elastic normal law (:func:`softgrasp.physics.fingertip.resolved.elastic_normal_value`).
_elastic_normal = resolved.elastic_normal_value


@_jit
def _elastic(depth, f, radii, law, n_exp):  # pragma: no cover - compiled
    """Finger f's elastic normal law at penetration ``depth``: (F [N], dF/d delta [N/m], energy
    [J]). ``law`` (n_f, 6) per finger: K, the resolved share r, the mesh's resolution under its
    load (h_node, h_land, facet size [m]) and Hertz's radius [m]
    (:meth:`softgrasp.physics.fingertip.contact.FingertipContact.law_table`)."""
    return _elastic_normal(depth, law[f, 5], law[f, 0], n_exp, law[f, 1], law[f, 2], law[f, 3], law[f, 4])


@_jit
def _stick(p, f, j, val, x, facets, centres, active, anchor, offset, memory):  # pragma: no cover
    """Tangential stick displacement (Eq. 16) of pair p: (c - X_a) - o in the facet's plane, with
    X_a the anchor (a material point of the facet) and o the centre's offset from it when it was
    set; a new pair is anchored at its contact point with the finger's memory as its stick.
    Returns (s_x, s_y, s_z, whether the pair continues, X_a's x, y, z)."""
    cont = active[f, j]
    if cont:
        ax = 0.0
        ay = 0.0
        az = 0.0
        for m in range(3):
            node = facets[j, m]
            ax += anchor[f, j, m] * x[node, 0]
            ay += anchor[f, j, m] * x[node, 1]
            az += anchor[f, j, m] * x[node, 2]
        ox = offset[f, j, 0]
        oy = offset[f, j, 1]
        oz = offset[f, j, 2]
    else:
        ax = val[p, 3]
        ay = val[p, 4]
        az = val[p, 5]
        ox = centres[f, 0] - ax - memory[f, 0]
        oy = centres[f, 1] - ay - memory[f, 1]
        oz = centres[f, 2] - az - memory[f, 2]
    sx = centres[f, 0] - ax - ox
    sy = centres[f, 1] - ay - oy
    sz = centres[f, 2] - az - oz
    sn = sx * val[p, 6] + sy * val[p, 7] + sz * val[p, 8]
    return sx - sn * val[p, 6], sy - sn * val[p, 7], sz - sn * val[p, 8], cont, ax, ay, az


@_jit
def _tangential_stiffness(depth, f, radii, law, n_exp, ratio, min_depth_ratio):  # pragma: no cover
    """k_t = ratio x dF_n/d delta (Mindlin's ratio of the normal law's stiffness, :func:`_elastic`)
    at max(delta, min_depth_ratio R)."""
    d = max(max(depth, min_depth_ratio * radii[f]), 0.0)
    return ratio * _elastic(d, f, radii, law, n_exp)[1]
