"""Force closure and the Ferrari-Canny grasp quality of frictional point contacts.

Each contact ``j`` (point ``p_j``, unit inward normal ``n_j``, friction coefficient ``mu``) can
apply any force in its friction cone, linearised by the m-gon of
:func:`softgrasp.grasp.equilibrium.friction_cone_edges` (same tangent basis and edges). With unit
normal force the cone's edges are the forces ``f_jk = n_j + mu d_jk`` and the primitive wrenches
``w_jk = (f_jk, (p_j - c) x f_jk / L)``; the torque scale ``L`` (default ``max_j |p_j - c|``) makes
torques commensurate with forces, so the quality is dimensionless and scale invariant.

Soft-finger contacts (``torsion`` kappa > 0 [m]) also resist a moment about their normal up to
``kappa`` times their normal force: each adds the two primitive wrenches
``(n_j, ((p_j - c) x n_j +- kappa n_j) / L)``; two contacts need it to be in force closure at all
(point contacts cannot resist a torque about the line through them).

The grasp is in force closure iff the origin of wrench space is strictly inside the convex hull
of the primitive wrenches; Ferrari and Canny's epsilon (L1 or "sum" metric: total normal force
at most 1) is the radius of the largest origin-centred ball in that hull. SI units throughout.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull, QhullError

from softgrasp.errors import ConfigError
from softgrasp.grasp.equilibrium import (
    _edges_count,
    _length_scale,
    _mu,
    _point3,
    _unit_normals,
    _vectors,
    friction_cone_edges,
)

__all__ = [
    "primitive_wrenches",
    "primitive_wrenches_many",
    "ferrari_canny",
    "ferrari_canny_bound",
    "ferrari_canny_bounds",
    "wrench_epsilon",
    "wrench_hull",
    "support_bounds",
    "is_force_closure",
]

#: Singular values below this fraction of the largest count as zero in the rank test.
RANK_RTOL = 1e-10
#: A hull computed without merging is kept when no point lies further outside a facet than this
#: fraction of the largest wrench component (Qhull's round-off on these sets: ~1e-15).
HULL_ATOL = 1e-12


def primitive_wrenches(
    points: ArrayLike,
    normals: ArrayLike,
    mu: float,
    centre: ArrayLike,
    m: int = 8,
    torque_scale: float | None = None,
) -> NDArray[np.float64]:
    """Primitive wrenches ``(f, tau / L)`` of unit normal force, shape ``(k*m, 6)``.

    Row ``j*m + k`` is the cone edge ``f = n_j + mu d_jk`` and its torque ``(p_j - centre) x f``
    divided by ``torque_scale`` ``L`` (default ``max_j |p_j - centre|``, or 1 if that is 0).
    With ``mu = 0`` the cones collapse to the normals and the ``k`` normal wrenches ``(k, 6)``
    are returned.
    """
    p = _vectors(points, "points")
    n = _unit_normals(normals, p.shape[0])
    mu = _mu(mu)
    c = _point3(centre, "centre")
    m = _edges_count(m)
    r = p - c
    if torque_scale is None:
        L = _length_scale(r)
    else:
        L = float(torque_scale)
        if not (math.isfinite(L) and L > 0.0):
            raise ConfigError(f"torque_scale = {torque_scale} m is invalid: it must be finite and > 0")
    if mu == 0.0:
        f = n
        rr = r
    else:
        _, d = friction_cone_edges(n, m)
        f = (n[:, None, :] + mu * d).reshape(-1, 3)
        rr = np.repeat(r, m, axis=0)
    return np.hstack([f, np.cross(rr, f) / L])


def ferrari_canny(
    points: ArrayLike,
    normals: ArrayLike,
    mu: float,
    centre: ArrayLike,
    m: int = 8,
    torque_scale: float | None = None,
) -> float:
    """Ferrari-Canny epsilon (L1 metric) of the grasp: dimensionless, ``>= 0``.

    The distance from the origin to the nearest facet of the convex hull of
    :func:`primitive_wrenches`; ``0.0`` when the origin is not strictly inside the hull (no force
    closure), including rank-deficient (< 6) or otherwise degenerate wrench sets.
    """
    eps = _signed_epsilon(primitive_wrenches(points, normals, mu, centre, m, torque_scale))
    return eps if eps is not None and eps > 0.0 else 0.0


def primitive_wrenches_many(
    points: ArrayLike, normals: ArrayLike, mu: float, centre: ArrayLike, m: int = 8, torsion: float = 0.0
) -> NDArray[np.float64]:
    """:func:`primitive_wrenches` of ``K`` grasps of ``k`` contacts at once, shape ``(K, k*m, 6)``
    (``(K, k, 6)`` with ``mu = 0``): ``points`` and ``normals`` are ``(K, k, 3)``, each grasp's
    torque scale its own ``max_j |p_j - centre|``. Row for row the same numbers as the one-grasp
    function (the same operations, vectorised over the grasps). ``torsion`` kappa > 0 [m]: soft-finger
    contacts, ``2 k`` more rows (the normal force with the moment ``+- kappa n_j`` about the normal)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or not np.all(np.isfinite(p)):
        raise ConfigError(f"points must be a finite (K, k, 3) array, got shape {p.shape}")
    K, k, _ = p.shape
    n = _unit_normals(np.asarray(normals, dtype=np.float64).reshape(-1, 3), K * k).reshape(K, k, 3)
    mu = _mu(mu)
    c = _point3(centre, "centre")
    m = _edges_count(m)
    r = p - c
    L = np.max(np.linalg.norm(r, axis=2), axis=1)
    L = np.where(L > 0.0, L, 1.0)
    if mu == 0.0:
        f, rr = n, r
    else:
        _, d = friction_cone_edges(n.reshape(-1, 3), m)
        f = (n.reshape(-1, 3)[:, None, :] + mu * d).reshape(K, k * m, 3)
        rr = np.repeat(r, m, axis=1)
    w = np.concatenate([f, np.cross(rr, f) / L[:, None, None]], axis=2)
    if torsion > 0.0:
        spin = np.cross(r, n)
        twist = [
            np.concatenate([n, (spin + sign * torsion * n) / L[:, None, None]], axis=2) for sign in (1, -1)
        ]
        w = np.concatenate([w, *twist], axis=1)
    return w


def wrench_epsilon(w: NDArray[np.float64]) -> float:
    """Ferrari-Canny epsilon of a set of primitive wrenches ``(n, 6)`` (one grasp's rows of
    :func:`primitive_wrenches_many`): as :func:`ferrari_canny` returns it, ``>= 0``."""
    return wrench_hull(w)[0]


def wrench_hull(w: NDArray[np.float64], nearest: int = 0) -> tuple[float, NDArray[np.float64]]:
    """:func:`wrench_epsilon` of the wrenches ``w`` ``(n, 6)`` and the unit outward normals of
    (up to) the ``nearest`` hull facets closest to the origin, nearest first, ``(<= nearest, 6)``
    (none when the set is degenerate). A grasp much like this one has its own nearest facets in
    about these directions: they make tight :func:`support_bounds` for it."""
    hull = _hull(w)
    if hull is None:
        return 0.0, np.zeros((0, 6))
    offsets = -hull.equations[:, -1]
    eps = float(np.min(offsets))
    order = np.argsort(offsets, kind="stable")[:nearest]
    return (eps if eps > 0.0 else 0.0), hull.equations[order, :-1]


def support_bounds(w: NDArray[np.float64], directions: NDArray[np.float64]) -> NDArray[np.float64]:
    """Upper bounds of the Ferrari-Canny epsilon of ``K`` wrench sets ``w`` ``(K, n, 6)`` from unit
    directions ``(K, d, 6)`` (each set its own): ``min_d max_i w_i . d``, ``(K,)``. The support
    function ``max_i w_i . d`` of the hull is its extent along d, and a ball of radius epsilon
    about the origin inside the hull reaches as far along every unit d; so each direction bounds
    epsilon from above, and a facet normal of the hull attains it. ``inf`` with no directions."""
    if directions.shape[1] == 0:
        return np.full(w.shape[0], math.inf)
    # (K, n, d) support values by batched products (three times faster than the einsum here)
    return np.matmul(w, directions.transpose(0, 2, 1)).max(axis=1).min(axis=1)


def ferrari_canny_bounds(
    points: ArrayLike, normals: ArrayLike, mu: float, centre: ArrayLike, m: int = 3, torsion: float = 0.0
) -> NDArray[np.float64]:
    """:func:`ferrari_canny_bound` of ``K`` grasps at once (points and normals ``(K, k, 3)``):
    ``(K,)`` upper bounds of their epsilon for any number of cone edges (0: no linearisation is
    force closure; ``inf``: degenerate, no bound known)."""
    mu = _mu(mu)
    if mu == 0.0:
        w = primitive_wrenches_many(points, normals, 0.0, centre, m)
        return np.array([wrench_epsilon(wi) for wi in w])
    m = _edges_count(m)
    out = np.empty(np.shape(points)[0])
    circumscribed = primitive_wrenches_many(points, normals, mu / math.cos(math.pi / m), centre, m, torsion)
    for i, wi in enumerate(circumscribed):
        eps = _signed_epsilon(wi)
        out[i] = math.inf if eps is None else max(eps, 0.0)
    return out


def _hull(w: NDArray[np.float64]) -> ConvexHull | None:
    """Qhull's convex hull of the wrenches ``w``; None when the set is degenerate (fewer than 7
    wrenches, rank below 6, or Qhull fails). Its facet equations are unit outward normals a and
    offsets b with a.x + b <= 0 inside."""
    if w.shape[0] < 7:
        return None
    s = np.linalg.svd(w, compute_uv=False)
    if s[0] == 0.0 or np.count_nonzero(s > RANK_RTOL * s[0]) < 6:
        return None
    try:
        # Without Qhull's default pre-merging ('Q0': three times faster on the grasps' 24-wrench
        # sets, whose eight edges per cone lie in one plane); kept only when every wrench is
        # inside every facet it reports, otherwise (or when Qhull reports a precision error)
        # computed again with merging.
        hull = ConvexHull(w, qhull_options="Q0")
        if float((w @ hull.equations[:, :-1].T + hull.equations[:, -1]).max()) <= HULL_ATOL * float(
            np.abs(w).max()
        ):
            return hull
    except (QhullError, ValueError):
        pass
    try:
        return ConvexHull(w)
    except (QhullError, ValueError):
        return None


def _signed_epsilon(w: NDArray[np.float64]) -> float | None:
    """Smallest offset of the hull facets of the wrenches ``w``: positive inside (the epsilon),
    <= 0 when the origin is outside; None when the set is degenerate."""
    hull = _hull(w)
    return None if hull is None else float(np.min(-hull.equations[:, -1]))


def ferrari_canny_bound(
    points: ArrayLike,
    normals: ArrayLike,
    mu: float,
    centre: ArrayLike,
    m: int = 3,
    torque_scale: float | None = None,
) -> float:
    """An upper bound of :func:`ferrari_canny` for any number of cone edges, cheaper to compute.

    The friction disc of radius ``mu`` (per unit normal force) lies inside the regular ``m``-gon of
    circumradius ``mu / cos(pi / m)``, in any rotation, and so does every inscribed polygon that
    linearises the cone. Each primitive wrench is linear in the force, so the hull of the inscribed
    polygons' wrenches lies inside the hull of the circumscribed ones', and its inscribed ball is no
    larger: ``ferrari_canny(..., mu, m=k) <= ferrari_canny_bound(..., mu, m)`` for every ``k``.
    With ``m = 3`` the hull has 9 points instead of 24 and costs about a tenth. Returns 0 when the
    origin is outside the circumscribed hull (then no linearisation is force closure), ``inf``
    when the circumscribed wrenches are degenerate (no bound known).
    """
    mu = _mu(mu)
    if mu == 0.0:
        return ferrari_canny(points, normals, 0.0, centre, m, torque_scale)
    m = _edges_count(m)
    if torque_scale is None:
        torque_scale = _length_scale(_vectors(points, "points") - _point3(centre, "centre"))
    w = primitive_wrenches(points, normals, mu / math.cos(math.pi / m), centre, m, torque_scale)
    eps = _signed_epsilon(w)
    if eps is None:
        return math.inf
    return eps if eps > 0.0 else 0.0


def is_force_closure(
    points: ArrayLike,
    normals: ArrayLike,
    mu: float,
    centre: ArrayLike,
    m: int = 8,
    tol: float = 1e-9,
) -> bool:
    """True iff the grasp is in force closure: ``ferrari_canny(...) > tol``."""
    return ferrari_canny(points, normals, mu, centre, m) > tol
