"""Where a fingertip's load lands on the mesh, and how well the mesh resolves it there.

The default normal law (:mod:`softgrasp.physics.fingertip.resolved`) supplies the part of the
object's compliance that its mesh does not resolve. How much the mesh resolves depends on where the
load lands: the shape functions b of the point of the rest surface closest to the fingertip centre
put a load there on its facet's nodes (Eq. 17-20), and a linear body deflects under that nodal
load, in the half-space's terms, by ``sum_lm b_l b_m / (pi E* r_lm)``: ``1 / r`` between distinct
nodes, and for a node's own deflection ``r_ll = kappa x`` the facet's size (the edge of the
equilateral triangle of its area; ``kappa`` is
:data:`~softgrasp.physics.fingertip.laws.RESOLUTION`, a property of the discretisation). The
radius of the disc whose Hertz compliance ``1 / (2 E* h)`` is the same,
``h = (pi / 2) / sum_lm b_l b_m / r_lm``, is the mesh's resolution length there: ``h_land``; a
load on one node has ``h_node = (pi / 2) kappa x size``, a load spread on a facet's three nodes a
larger one.

Measured on the rest shape, the resolution does not change as the loaded nodes move; it is
continuous as the centre moves over edges and vertices (the shape functions of the nodes left
behind vanish there).

The object's own curvature there enters Hertz's law as the pair's effective radius,
``1 / R_eff = 1 / R + kappa_surface``: flat facets do not carry it, so the law must.
``kappa_surface`` is the landing facet's mean curvature, the mean over its three edges of the
angle between its normal and its neighbour's over the distance between their centroids
(positive where the surface is convex, negative in a dent): ``1 / R_s`` on a sphere of radius R_s.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from softgrasp.physics.fingertip.geometry import pair_geometry

__all__ = ["landing_resolution", "facet_curvatures"]


def facet_curvatures(points: NDArray[np.float64], facets: NDArray[np.int64]) -> NDArray[np.float64]:
    """Mean curvature [1/m] of each boundary facet (F,) of the rest surface (module docstring);
    0 across an edge without a neighbour."""
    tri = points[facets]
    centroid = tri.mean(axis=1)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal = cross / np.linalg.norm(cross, axis=1)[:, None]
    F = len(facets)
    edges = np.sort(np.stack([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]], axis=1), axis=2)
    key = edges.reshape(-1, 2)
    owner = np.repeat(np.arange(F), 3)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k, o = key[order], owner[order]
    same = (k[1:] == k[:-1]).all(axis=1)
    a, b = o[:-1][same], o[1:][same]  # the facets on either side of each shared edge
    gap = centroid[b] - centroid[a]
    dist = np.linalg.norm(gap, axis=1)
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", normal[a], normal[b]), -1.0, 1.0))
    sign = np.where(np.einsum("ij,ij->i", gap, normal[a] - normal[b]) <= 0, 1.0, -1.0)
    kappa = sign * angle / np.maximum(dist, 1e-300)
    total = np.zeros(F)
    np.add.at(total, a, kappa)
    np.add.at(total, b, kappa)
    return total / 3.0


def landing_resolution(
    points: NDArray[np.float64],
    facets: NDArray[np.int64],
    curvature: NDArray[np.float64],
    centres: NDArray[np.float64],
    kappa: float,
) -> NDArray[np.float64]:
    """Per fingertip centre (n_f, 3) over the rest surface (``points`` (N, 3) [m], boundary
    ``facets`` (F, 3), their mean curvatures ``curvature`` (F,) [1/m]): (h_node, h_land, facet
    size [m], surface curvature [1/m]) of the point of the surface closest to the centre (module
    docstring), shape (n_f, 4); zeros with ``kappa = 0``."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    nf, F = len(centres), len(facets)
    out = np.zeros((nf, 4))
    if not kappa > 0 or F == 0:
        return out
    finger = np.repeat(np.arange(nf, dtype=np.int64), F)
    facet = np.tile(np.arange(F, dtype=np.int64), nf)
    pr = pair_geometry(points, facets, centres, np.ones(nf), finger, facet, closest=True)
    dist = pr.distance.reshape(nf, F)
    best = np.argmin(dist, axis=1)
    for i in range(nf):
        k = i * F + best[i]
        b = pr.bary[k]
        tri = points[facets[best[i]]]
        size = math.sqrt(4.0 * float(pr.area[k]) / math.sqrt(3.0))
        r = np.linalg.norm(tri[:, None, :] - tri[None, :, :], axis=-1)
        r[np.arange(3), np.arange(3)] = kappa * size
        h_land = 0.5 * math.pi / float(b @ (1.0 / r) @ b)
        out[i] = (0.5 * math.pi * kappa * size, h_land, size, curvature[best[i]])
    return out
