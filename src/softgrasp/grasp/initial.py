"""The initial grasp (paper step 1, Sec. 2 and 4.3.2): three fingertip contact points on the
undeformed surface, chosen by a force-closure criterion within reach of the hand.

Palm layout (until a kinematic hand model constrains it): the hand approaches the object from the
side with its palm vertical, so the three contacts lie on the horizontal *grasp plane* through the
object's centre of mass (on a sphere: a great circle, as in the paper's Fig. 12). The thumb
opposes the first and middle fingers, which sit side by side: seen from the centre of mass, the
fingers lie at azimuths ``theta + pi -+ phi`` opposite the thumb at ``theta``. The hand limits

* the spread between the first and middle fingertips' contacts, ``min_spread``..``max_spread``
  (a Shadow-like hand: fingers 22 mm apart at the knuckles, abducting to about 90 mm at the tips);
* the aperture, the distance between the thumb's contact and the midpoint of the fingers',
  ``max_aperture`` (150 mm).

Every (theta, phi) on a grid is cast from the centre of mass onto the surface; the candidate
triples within the limits are scored by the Ferrari-Canny epsilon of their frictional point
contacts (:mod:`softgrasp.grasp.closure`), and the best force-closure triple wins.

A two-finger gripper (``fingers = 2``) closes on a pair of opposed contacts at azimuths ``theta``
and ``theta + pi``, at most ``max_aperture`` apart, their normals within ``pi - min_opposition``
of opposite. Two point contacts cannot resist a torque about the line through them, so the pair
is scored as *soft-finger* contacts: each resists, besides the friction cone's forces, a moment
about its normal up to ``(3 pi / 16) mu a`` times its normal force (Hertz's patch of radius
``a`` sliding as a whole), with ``a = patch_radius`` (:data:`PATCH_FRACTION` of the fingertip
radius); the hold check then tests the actual patch of the closing's contact.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.grasp.closure import ferrari_canny_bounds, primitive_wrenches_many, support_bounds, wrench_hull
from softgrasp.hand.kinematics import HandModel

__all__ = [
    "HandLayout",
    "InitialGrasp",
    "FINGER_NAMES",
    "raycast_surface",
    "initial_grasp",
    "initial_grasps",
    "ranked_grasps",
]

#: Finger names of a three-finger grasp, in the order softgrasp uses everywhere.
FINGER_NAMES = ("thumb", "first", "middle")
#: Contact patch radius of the two-finger criterion, as a fraction of the fingertip radius: a
#: sphere pressed a sixteenth of its radius into a soft object (0.5 mm for an 8 mm fingertip,
#: a holding squeeze) has a patch of radius sqrt(R d) = R / 4.
PATCH_FRACTION = 0.25
#: Hull facets nearest the origin kept from each exact quality, as directions that bound the
#: others' (:func:`_best_first`).
NEAREST_FACETS = 8


@dataclass(frozen=True)
class HandLayout:
    """Reach of the hand's thumb, first and middle fingers, in the grasp plane.

    Attributes
    ----------
    min_spread, max_spread: distance between the first and middle fingers' contacts [m].
    max_aperture: largest distance from the thumb's contact to the fingers' midpoint [m].
    max_finger_angle: largest angle between the first and middle fingers' surface normals [rad]
        (side by side, they push the same way, not against each other).
    min_opposition: smallest angle between the thumb's normal and the mean of the fingers' [rad].
    azimuths: number of thumb directions tried around the object.
    spreads: half-angles phi tried [rad] (first and middle fingers at theta + pi -+ phi).
    fingers: 3 (thumb, first, middle) or 2 (an opposed pair: spreads unused).
    patch_radius: the contacts' patch radius [m] of the two-finger criterion (soft-finger
        torsional friction); 0 for three fingers.
    """

    min_spread: float = 0.02
    max_spread: float = 0.09
    max_aperture: float = 0.15
    max_finger_angle: float = math.radians(90.0)
    min_opposition: float = math.radians(135.0)
    azimuths: int = 36
    spreads: tuple[float, ...] = tuple(math.radians(a) for a in range(5, 66, 5))
    fingers: int = 3
    patch_radius: float = 0.0

    @classmethod
    def for_hand(cls, hand: HandModel | None) -> HandLayout:
        """The layout of ``hand``'s reach limits and fingers (the defaults without a hand)."""
        if hand is None:
            return cls()
        r, names = hand.reach, hand.grasp_fingers
        patch = PATCH_FRACTION * hand.fingertip_radius(names[0]) if len(names) == 2 else 0.0
        return cls(r.min_spread, r.max_spread, r.max_aperture, fingers=len(names), patch_radius=patch)

    def __post_init__(self) -> None:
        if not (0 < self.min_spread < self.max_spread and self.max_aperture > 0):
            raise ConfigError(
                f"hand layout needs 0 < min_spread < max_spread and max_aperture > 0, got "
                f"{self.min_spread}, {self.max_spread}, {self.max_aperture} m"
            )
        if self.azimuths < 1 or not self.spreads:
            raise ConfigError("hand layout needs at least one azimuth and one spread angle")
        if self.fingers not in (2, 3) or not (math.isfinite(self.patch_radius) and self.patch_radius >= 0):
            raise ConfigError(
                f"hand layout needs 2 or 3 fingers and a patch radius >= 0, got {self.fingers}, "
                f"{self.patch_radius} m"
            )

    def describe(self) -> dict[str, object]:
        if self.fingers == 2:
            return {
                "grasp_plane": "horizontal, through the centre of mass",
                "fingers": 2,
                "max_aperture_m": self.max_aperture,
                "min_opposition_deg": round(math.degrees(self.min_opposition), 6),
                "azimuths": self.azimuths,
                "patch_radius_m": self.patch_radius,
            }
        return {
            "grasp_plane": "horizontal, through the centre of mass",
            "min_spread_m": self.min_spread,
            "max_spread_m": self.max_spread,
            "max_aperture_m": self.max_aperture,
            "max_finger_normal_angle_deg": round(math.degrees(self.max_finger_angle), 6),
            "min_thumb_opposition_deg": round(math.degrees(self.min_opposition), 6),
            "azimuths": self.azimuths,
            "spread_half_angles_deg": [round(math.degrees(a), 6) for a in self.spreads],
        }


@dataclass(frozen=True)
class InitialGrasp:
    """The contact points on the surface, one per finger (thumb, first, middle; or left, right).

    Attributes
    ----------
    points: contact points [m], (k, 3).
    normals: outward unit surface normals there, (k, 3).
    facets: boundary facet of each contact, (k,).
    centroid: centroid of the contact triangle [m], (3,) (the fingers close towards it).
    epsilon: Ferrari-Canny quality (force units per unit normal force; 0 = not force closure).
    thumb_azimuth: theta [rad]; spread: phi [rad].
    """

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    facets: NDArray[np.int64]
    centroid: NDArray[np.float64]
    epsilon: float
    thumb_azimuth: float
    spread: float


def raycast_surface(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    origin: NDArray[np.float64],
    directions: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Outermost crossing of rays from ``origin`` along unit ``directions`` (r, 3) with the
    boundary facets (Moller-Trumbore). Returns (distance along each ray [m] (r,), facet (r,)); a ray
    that crosses nothing gets distance nan and facet -1."""
    tri = x[facets]
    a = tri[:, 0]
    e1 = tri[:, 1] - a
    e2 = tri[:, 2] - a
    s = origin[None, :] - a  # (F, 3)
    dist = np.full(len(directions), np.nan)
    which = np.full(len(directions), -1, dtype=np.int64)
    for k, d in enumerate(directions):
        p = np.cross(d[None, :], e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        if hit.any():
            j = np.flatnonzero(hit)[np.argmax(t[hit])]
            dist[k] = t[j]
            which[k] = j
    return dist, which


def _outward_normals(x: NDArray[np.float64], facets: NDArray[np.int64]) -> NDArray[np.float64]:
    tri = x[facets]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def initial_grasp(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    com: NDArray[np.float64],
    mu: float,
    layout: HandLayout = HandLayout(),  # noqa: B008 - frozen dataclass
) -> InitialGrasp:
    """Best force-closure triple (thumb, first, middle) in the grasp plane within the hand's reach:
    the first of :func:`ranked_grasps`."""
    return next(ranked_grasps(x, facets, com, mu, layout))


def initial_grasps(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    com: NDArray[np.float64],
    mu: float,
    layout: HandLayout = HandLayout(),  # noqa: B008 - frozen dataclass
) -> list[InitialGrasp]:
    """Every force-closure triple (thumb, first, middle) in the grasp plane within the layout's
    reach, best (largest Ferrari-Canny epsilon) first; ties keep the search order. The whole list
    of :func:`ranked_grasps` (which computes only as many qualities as its caller takes)."""
    return list(ranked_grasps(x, facets, com, mu, layout))


def ranked_grasps(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    com: NDArray[np.float64],
    mu: float,
    layout: HandLayout = HandLayout(),  # noqa: B008 - frozen dataclass
    skip: Callable[[float, float], bool] | None = None,
) -> Iterator[InitialGrasp]:
    """The force-closure triples (thumb, first, middle) in the grasp plane within the layout's
    reach, best (largest Ferrari-Canny epsilon) first, ties in the search order, computed lazily.

    Every candidate first gets the cheap upper bound :func:`~softgrasp.grasp.closure.ferrari_canny_bound` of
    its quality (all candidates at once);
    the exact epsilon is computed only when a candidate's bound is the best left, and a candidate
    is yielded once its exact quality beats every other's bound (best-first search). Taking the
    first few grasps costs a fraction of ranking them all; the order is the same.

    Parameters
    ----------
    x: node positions [m] (the object at rest on the table).  facets: boundary facets, outward.
    com: centre of mass [m].  mu: friction coefficient used for the closure test.
    layout: the hand's reach.
    skip: ``skip(thumb_azimuth, spread)`` true for candidates the caller will not take (asked
        when a candidate comes to the top, before its exact quality is computed; the answer may
        change from false to true as the caller goes on, never back). Such candidates are left
        out; the others come in the same order as without ``skip``.

    Raises
    ------
    InfeasibleGrasp: no triple is within the hand's reach (at the call), or none of them is force
        closure (when the first grasp is asked for: the object is too large or too small for the
        hand, or mu = 0).
    """
    com = np.asarray(com, dtype=np.float64)
    thetas = 2.0 * np.pi * np.arange(layout.azimuths) / layout.azimuths
    # One ray per needed azimuth: thumb directions and every finger direction.
    angles = [thetas]
    spreads = (0.0,) if layout.fingers == 2 else layout.spreads
    for phi in spreads:
        angles += [thetas + np.pi - phi, thetas + np.pi + phi]
    allang = np.mod(np.concatenate(angles), 2 * np.pi)
    uniq, inv = np.unique(np.round(allang, 12), return_inverse=True)
    dirs = np.stack([np.cos(uniq), np.sin(uniq), np.zeros_like(uniq)], axis=1)
    dist, fac = raycast_surface(x, facets, com, dirs)
    if np.isnan(dist).all():
        raise InfeasibleGrasp(
            "the horizontal plane through the centre of mass does not cross the object's surface; "
            "check the mesh is closed and the object rests on the table"
        )
    pts = com[None, :] + dist[:, None] * dirs
    nrm = _outward_normals(x, facets)
    ray = {float(a): i for i, a in enumerate(uniq)}
    found: list[tuple[NDArray, NDArray, NDArray, float, float]] = []
    widest = 0.0
    for theta in thetas:
        it = ray[float(np.round(np.mod(theta, 2 * np.pi), 12))]
        for phi in spreads:
            i1 = ray[float(np.round(np.mod(theta + np.pi - phi, 2 * np.pi), 12))]
            i2 = ray[float(np.round(np.mod(theta + np.pi + phi, 2 * np.pi), 12))]
            idx = [it, i1, i2]
            if np.isnan(dist[idx]).any():
                continue
            if layout.fingers == 2:
                pair = _opposed_pair(pts[[it, i1]], nrm[fac[[it, i1]]], layout)
                widest = max(widest, float(np.linalg.norm(pts[it] - pts[i1])))
                if pair is not None:
                    found.append((pts[[it, i1]], pair, fac[[it, i1]].astype(np.int64), float(theta), 0.0))
                continue
            p = pts[idx]
            spread = float(np.linalg.norm(p[1] - p[2]))
            aperture = float(np.linalg.norm(p[0] - 0.5 * (p[1] + p[2])))
            widest = max(widest, aperture)
            if not (layout.min_spread <= spread <= layout.max_spread and aperture <= layout.max_aperture):
                continue
            n_out = nrm[fac[idx]]
            fingers = n_out[1] + n_out[2]
            side_by_side = n_out[1] @ n_out[2] >= math.cos(layout.max_finger_angle)
            opposed = n_out[0] @ fingers <= math.cos(layout.min_opposition) * np.linalg.norm(fingers)
            if not (side_by_side and opposed):
                continue
            found.append((p, n_out, fac[idx].astype(np.int64), float(theta), float(phi)))
    if not found and layout.fingers == 2:
        raise InfeasibleGrasp(
            f"the gripper cannot reach this object: no opposed pair of contacts in the grasp plane is within "
            f"its {layout.max_aperture * 1e3:.0f} mm opening (the object is {widest * 1e3:.0f} mm across); "
            "use a smaller object or a gripper with a wider opening (max_aperture)"
        )
    if not found:
        raise InfeasibleGrasp(
            f"the hand cannot reach this object: no thumb/finger triple in the grasp plane has the "
            f"fingers {layout.min_spread * 1e3:.0f}-{layout.max_spread * 1e3:.0f} mm apart and the "
            f"thumb within {layout.max_aperture * 1e3:.0f} mm of them (the object is "
            f"{widest * 1e3:.0f} mm across); use a smaller object or a hand layout with a wider reach"
        )
    return _best_first(found, com, mu, skip, _torsion(mu, layout))


def _torsion(mu: float, layout: HandLayout) -> float:
    """Largest moment about a contact's normal per unit normal force [m] of the two-finger
    criterion: Hertz's patch of radius ``patch_radius`` sliding as a whole, (3 pi / 16) mu a."""
    return 3.0 * math.pi / 16.0 * mu * layout.patch_radius if layout.fingers == 2 else 0.0


def _opposed_pair(
    p: NDArray[np.float64], n_out: NDArray[np.float64], layout: HandLayout
) -> NDArray[np.float64] | None:
    """The outward normals of two contacts ``p`` (2, 3) when the gripper reaches them (within its
    opening, normals opposed within ``pi - min_opposition``), else None."""
    if np.linalg.norm(p[0] - p[1]) > layout.max_aperture:
        return None
    if n_out[0] @ n_out[1] > math.cos(layout.min_opposition):
        return None
    return n_out


def _best_first(
    found: list[tuple[NDArray, NDArray, NDArray, float, float]],
    com: NDArray[np.float64],
    mu: float,
    skip: Callable[[float, float], bool] | None = None,
    torsion: float = 0.0,
) -> Iterator[InitialGrasp]:
    """Yield the force-closure candidates by decreasing epsilon (rounded to 12 digits; ties in
    list order): a heap keyed by each candidate's best-known upper bound, refined to the exact
    value when it comes to the top. A candidate ``skip`` rejects when it comes to the top is
    dropped there (the caller would pass over it when it came: ``skip`` only ever turns true).

    The bounds: the circumscribed cones' quality (:func:`~softgrasp.grasp.closure.ferrari_canny_bounds`)
    at first; then, after each exact quality, the hull's nearest facet normals turned about the
    vertical by the difference of the thumb azimuths (a grasp a little further round the object
    has its wrenches, and its nearest facets, turned about as much) bound every candidate still
    inexact by its support function (:func:`~softgrasp.grasp.closure.support_bounds`)."""
    P = np.array([c[0] for c in found])
    N = -np.array([c[1] for c in found])  # inward normals
    theta = np.array([c[3] for c in found])
    ub = ferrari_canny_bounds(P, N, mu, com, torsion=torsion)
    wrenches = primitive_wrenches_many(P, N, mu, com, torsion=torsion)
    exact = np.full(len(found), np.nan)  # the exact qualities computed so far
    alive = ub > 0.0  # not yet yielded, dropped or found not force closure

    # Entries (-round(value, 12), index, exact?, value). The bounds only ever decrease, so an entry
    # made before a bound fell sorts before its candidate's current one: when one comes to the top
    # it is replaced by the current one (and ones of dropped or yielded candidates are passed
    # over). The candidates come off in the order a heap rebuilt after every change would give.
    heap = [(-round(float(ub[i]), 12), int(i), False, float(ub[i])) for i in np.flatnonzero(alive)]
    heapq.heapify(heap)
    yielded = 0
    while heap:
        entry = heapq.heappop(heap)
        _, i, is_exact, eps = entry
        if not alive[i] or (not is_exact and not np.isnan(exact[i])):
            continue
        if not is_exact and eps != ub[i]:
            heapq.heappush(heap, (-round(float(ub[i]), 12), i, False, float(ub[i])))
            continue
        p, n_out, fac, th, phi = found[i]
        if skip is not None and skip(th, phi):
            alive[i] = False
            continue
        if not is_exact:
            eps, normals = wrench_hull(wrenches[i], NEAREST_FACETS)
            exact[i] = eps
            if eps <= 0.0:
                alive[i] = False
                continue
            rest = alive & np.isnan(exact)
            if rest.any() and len(normals):
                ub[rest] = np.minimum(ub[rest], _support_bound(wrenches[rest], normals, theta[rest] - th))
                alive &= ub > 0.0
            heapq.heappush(heap, (-round(eps, 12), i, True, eps))
            continue
        alive[i] = False
        yielded += 1
        yield InitialGrasp(
            points=p,
            normals=n_out,
            facets=fac,
            centroid=p.mean(axis=0),
            epsilon=float(eps),
            thumb_azimuth=th,
            spread=phi,
        )
    if not yielded:
        raise InfeasibleGrasp(
            f"no reachable {'pair' if len(found[0][0]) == 2 else 'triple'} is force closure with mu = "
            f"{mu:g}: the friction cones are too narrow for the fingertips to resist every load on this "
            "surface (with mu = 0 none can); raise the friction coefficient"
        )


def _support_bound(
    w: NDArray[np.float64], normals: NDArray[np.float64], turn: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Upper bounds of the qualities of the wrench sets ``w`` ``(K, n, 6)`` from the facet
    normals ``(d, 6)`` of another grasp's hull, turned about the vertical by ``turn`` ``(K,)``
    [rad] (force and torque parts alike), ``(K,)``. Each turned normal is a unit direction, so
    the bound holds whatever the turn; a margin of 1e-9 relative (and 2e-12) keeps it above the
    exact quality through rounding."""
    c, s = np.cos(turn), np.sin(turn)
    a = normals.reshape(-1, 2, 3)  # (d, force/torque, xyz)
    d = np.empty((len(turn), len(normals), 2, 3))
    d[..., 0] = c[:, None, None] * a[None, ..., 0] - s[:, None, None] * a[None, ..., 1]
    d[..., 1] = s[:, None, None] * a[None, ..., 0] + c[:, None, None] * a[None, ..., 1]
    d[..., 2] = a[None, ..., 2]
    h = support_bounds(w, d.reshape(len(turn), len(normals), 6))
    return h + 1e-9 * np.abs(h) + 2e-12
