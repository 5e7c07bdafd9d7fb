"""How far an elastic body sinks onto a rigid table under its own weight, estimated before the
static solve that finds it: a start for that solve (:func:`softgrasp.grasp.settle.settle_on_table`).

Placed level with the table, a body touches it at the nodes of one facet (or one node) and
Newton's first steps hang the whole weight there while the contact patch forms. Lowered first by
the right amount, the body starts with the nodes of its contact patch already touching.

The estimate is a Winkler foundation with a flat punch's stiffness: the nodes below the approach
``delta`` press on the table over their downward-facing areas ``A_i`` with a pressure
``k (delta - h_i)``, ``h_i`` their heights above the lowest node, ``k = 2 E* / (pi a)`` the
stiffness per area of a rigid flat punch of the touching area's radius ``a`` (its stiffness
``2 E* a`` over its area ``pi a^2``), ``E* = E / (1 - nu^2)`` against a rigid table. On a sphere of
radius R this gives ``W = sqrt(2 R) E* delta^(3/2)`` where Hertz has ``(4 / 3) sqrt(R) E*
delta^(3/2)``: the approach 4 % short of Hertz's. The body is then lowered by *half* the
approach: a sphere cut by a plane at ``delta / 2`` leaves a circle of radius ``a^2 = R delta -
delta^2 / 4``, Hertz's contact radius for the approach ``delta`` (2 % short of Hertz's for the
weight, as the approach is 4 % short), so on a sphere the nodes of the predicted contact patch
start touching, none outside it (the foundation's own patch, ``a^2 = 2 R delta``, is wider).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["resting_approach", "lowered_onto_table"]


def resting_approach(
    points: NDArray[np.float64],
    facets: NDArray[np.integer],
    weight: float,
    modulus: float,
) -> float:
    """The approach [m] of a body resting under ``weight`` [N] on a rigid horizontal table at its
    lowest node, by the flat-punch Winkler foundation above (Hertz's to 4 % on a sphere).

    Parameters
    ----------
    points: the body's node positions [m], (N, 3), the table's normal +z.
    facets: boundary triangles, (F, 3), ordered for outward normals.
    weight: the load pressing the body onto the table [N] (> 0).
    modulus: the contact modulus ``E* = E / (1 - nu^2)`` against a rigid table [Pa] (> 0).

    Returns 0 where nothing faces the table (no downward-facing boundary area).
    """
    if not (weight > 0 and math.isfinite(weight)):
        raise ValueError(f"the weight must be positive and finite, got {weight} N")
    if not (modulus > 0 and math.isfinite(modulus)):
        raise ValueError(f"the contact modulus must be positive and finite, got {modulus} Pa")
    x = np.asarray(points, dtype=np.float64)
    if not np.isfinite(x).all():
        raise ValueError("the node positions must be finite")
    f = np.asarray(facets, dtype=np.int64)
    p = x[f]
    # Each facet's area projected on the table where its outward normal points down, a third to
    # each of its nodes.
    down = np.maximum(-0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2], 0.0)
    area = np.bincount(f.ravel(), np.repeat(down / 3.0, 3), minlength=x.shape[0])
    nodes = np.flatnonzero(area > 0.0)
    if nodes.size == 0:
        return 0.0
    h = x[nodes, 2] - x[:, 2].min()
    order = np.argsort(h, kind="stable")
    h, area = h[order], area[nodes][order]
    S = np.cumsum(area)  # touching area with the first j + 1 nodes in
    SH = np.cumsum(area * h)
    # With the first j + 1 nodes touching: W = (2 E* / (pi a)) (delta S - SH), a = sqrt(S / pi).
    a = np.sqrt(S / np.pi)
    delta = (weight * np.pi * a / (2.0 * modulus) + SH) / S
    # The approach is one whose touching nodes are those below it: delta_j below the next node.
    # The load grows with delta between nodes but drops where a node joins (the stiffness per
    # area falls as the touching area grows), so several may fit; the first is the smallest, the
    # one a body lowered onto the table reaches first.
    fits = np.flatnonzero(np.append(delta[:-1] <= h[1:], True))
    return float(delta[fits[0]])


def lowered_onto_table(
    points: NDArray[np.float64],
    facets: NDArray[np.integer],
    weight: float,
    modulus: float,
) -> NDArray[np.float64]:
    """``points`` lowered by half their :func:`resting_approach`: the nodes inside the predicted
    contact patch below the table (the plane through the lowest node), the rest above it."""
    x = np.asarray(points, dtype=np.float64)
    return x - np.array([0.0, 0.0, 0.5 * resting_approach(x, facets, weight, modulus)])
