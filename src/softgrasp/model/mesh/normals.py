"""The smooth surface a faceted boundary stands for: its normal at each facet's corners.

A mesh of a curved object tilts each facet's normal from the surface's by up to about half the
angle between neighbouring facets: about h / (2 R) on a sphere of radius R meshed at size h, 7°
on the default sphere. A fingertip's force, and the friction that must hold the object, follow
that tilt: the set-points would change by several per cent from one mesh to the next of the same
object. The contact's normal is therefore the smooth surface's, interpolated over the facet
(Phong's normal) from a normal at each corner.

The normal at a facet's corner is the angle-weighted mean of the normals of the facets around
that node (Thürmer and Wüthrich's pseudo-normal), over those whose normal lies within
:data:`CREASE_DEG` of the facet's own: faces meeting at a sharper edge (a cube's 90°) keep their
own normals on either side of it, and a flat face's corner normals are its normal exactly. Each
facet's three corner normals are stored in its own rest frame (e1 along its first edge
``p1 - p0``, e2 = n x e1, n), so that a contact turns them with the facet as the object deforms
(:func:`softgrasp.physics.fingertip.detect._pair_values`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["CREASE_DEG", "corner_normals"]

#: Facets around a node whose normals differ by more than this from a facet's [deg] meet it at an
#: edge of the object, not on its smooth surface: their normals stay out of its corner normal.
#: Neighbouring facets of the built-in sphere differ by at most 27° at the coarsest mesh size the
#: command line allows; a cube's faces by 90°.
CREASE_DEG = 45.0


def corner_normals(
    points: NDArray[np.float64],
    facets: NDArray[np.int64],
    normals: NDArray[np.float64],
    node_facets: tuple[NDArray[np.int64], NDArray[np.int64]],
) -> NDArray[np.float64]:
    """The smooth surface's unit normal at each corner of each boundary facet, in the facet's rest
    frame (module docstring), (F, 3, 3) indexed [facet, corner, (e1, e2, n) component].

    ``points`` (N, 3) [m] at rest; ``facets`` (F, 3) and their outward unit ``normals`` (F, 3);
    ``node_facets`` the facets around each node, CSR (indptr, indices)."""
    tri = points[facets]
    n = normals
    angle = np.empty(facets.shape)  # each facet's interior angle at each corner [rad]
    for i in range(3):
        a = tri[:, (i + 1) % 3] - tri[:, i]
        b = tri[:, (i + 2) % 3] - tri[:, i]
        angle[:, i] = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
    indptr, indices = node_facets
    node = facets.ravel()  # corner c = 3 f + i is node facets[f, i]
    count = indptr[node + 1] - indptr[node]
    corner = np.repeat(np.arange(node.size), count)
    # the facets around each corner's node, corner by corner
    first = np.repeat(indptr[node] - (np.cumsum(count) - count), count)
    around = indices[np.arange(count.sum()) + first]
    own = corner // 3
    smooth = np.einsum("ij,ij->i", n[around], n[own]) >= math.cos(math.radians(CREASE_DEG))
    at = np.argmax(facets[around] == node[corner][:, None], axis=1)  # the node's corner in each
    weight = np.where(smooth, angle[around, at], 0.0)
    total = np.zeros((node.size, 3))
    np.add.at(total, corner, weight[:, None] * n[around])
    total /= np.linalg.norm(total, axis=1)[:, None]  # the facet itself is always among its own
    total = total.reshape(-1, 3, 3)
    e1 = tri[:, 1] - tri[:, 0]
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(n, e1)
    out = np.stack(
        [np.einsum("fij,fj->fi", total, e) for e in (e1, e2, n)], axis=2
    )  # [facet, corner, component]
    out.flags.writeable = False
    return out
