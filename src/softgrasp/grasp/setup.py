"""Paper step 1, where the closing starts: the object at rest on the table
(:mod:`softgrasp.grasp.settle`), the best force-closure initial grasp the hand reaches (or a
given one), the hand's placement for it, and each fingertip's closing line towards the centroid of
the contact triangle with the travel at which it first touches the object.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import InfeasibleGrasp
from softgrasp.grasp.config import MAX_PLACEMENTS, PER_SPREAD, START_BACKOFF, PlanConfig
from softgrasp.grasp.initial import InitialGrasp, ranked_grasps
from softgrasp.grasp.kept_rest import settle
from softgrasp.grasp.settle import centre_of_mass
from softgrasp.hand.kinematics import HandModel
from softgrasp.hand.placement import HandPlacement, place_hand
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import PlaneContact
from softgrasp.sim.scene import State

__all__ = ["ClosingSetup", "closing_setup"]


def _first_touch(body: Body, params: ContactParams, tip: Fingertip, x, t_max: float) -> float:
    """Travel at which ``tip`` (moving along its velocity) first touches the surface ``x``."""

    def touches(t: float) -> bool:
        fc = FingertipContact((tip,), params)
        return len(fc.pairs(body, x, t)) > 0

    grid = np.linspace(0.0, t_max, 41)
    hit = next((k for k, t in enumerate(grid) if touches(float(t))), None)
    if hit is None:
        raise InfeasibleGrasp(
            f"the {tip.name} fingertip never touches the object along its closing line "
            f"({t_max * 1e3:.1f} mm of travel); the initial grasp is not reachable"
        )
    if hit == 0:
        return 0.0
    lo, hi = float(grid[hit - 1]), float(grid[hit])
    while hi - lo > 1e-9:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if touches(mid) else (mid, hi)
    return hi


def _start_centres(ig: InitialGrasp, cfg: PlanConfig) -> tuple[NDArray, NDArray, NDArray]:
    """Fingertip centres where the closing starts: tangent to the surface at each contact point,
    backed off ``START_BACKOFF`` steps along the closing line; the unit closing directions
    (towards the contact triangle's centroid) and each contact's distance to that centroid.

    Two fingers (a gripper, whose pads slide on one axis) start on the line through the two
    contacts, each at the distance from its contact that keeps the sphere off the contact's
    tangent plane (R over the cosine between the line and the normal)."""
    u = ig.centroid[None, :] - ig.points
    reach = np.linalg.norm(u, axis=1)
    u = u / reach[:, None]
    if len(ig.points) == 2:
        cos = np.maximum(-np.einsum("ij,ij->i", ig.normals, u), 0.5)  # opposed within 60 deg
        return ig.points - (cfg.fingertip_radius / cos + START_BACKOFF * cfg.step)[:, None] * u, u, reach
    return ig.points + cfg.fingertip_radius * ig.normals - START_BACKOFF * cfg.step * u, u, reach


def _hand_order(hand: HandModel, ig: InitialGrasp) -> InitialGrasp:
    """``ig`` with the first and middle fingers' contacts swapped if the hand needs them the other
    way round. Seen in a grasp from above (palm y from the thumb's contact to the fingers', palm
    normal down), the finger whose knuckle lies farther along the palm's x axis takes the contact
    farther along that axis: the fingers do not cross. (A two-finger grasp is taken as it is.)"""
    if len(ig.points) != 3:
        return ig
    up = np.array([0.0, 0.0, 1.0])
    y = ig.points[1:].mean(axis=0) - ig.points[0]
    y -= (y @ up) * up
    x_axis = np.cross(y, -up)
    knuckle = {f: hand.link_points(f, 0.5 * np.add(*hand.limits(f)))[0][0] for f in ("first", "middle")}
    want = knuckle["first"] > knuckle["middle"]
    have = (ig.points[1] - ig.points[0]) @ x_axis > (ig.points[2] - ig.points[0]) @ x_axis
    if want == have:
        return ig
    k = [0, 2, 1]
    return replace(ig, points=ig.points[k], normals=ig.normals[k], facets=ig.facets[k])


def _reachable_grasp(
    xs: NDArray[np.float64],
    candidates: Iterable[InitialGrasp],
    cfg: PlanConfig,
    failures: dict[float, int] | None = None,
) -> tuple[InitialGrasp, HandPlacement | None]:
    """The best initial grasp the hand reaches, and the hand's placement for it. Candidates come
    best first; a spread angle (the layout's shape parameter) that failed ``PER_SPREAD`` times is
    skipped (on a near-symmetric object its other azimuths fail alike), and at most
    ``MAX_PLACEMENTS`` placements are tried. ``failures`` (failed placements per spread angle) is
    filled in as it goes, so that the ranking can leave out what will be skipped
    (:func:`_spread_failed`)."""
    if cfg.hand is None:
        return next(iter(candidates)), None
    failures = {} if failures is None else failures
    first_error: InfeasibleGrasp | None = None
    tried = 0
    for cand in candidates:
        if _spread_failed(failures, cand.thumb_azimuth, cand.spread):
            continue
        if tried >= MAX_PLACEMENTS:
            break
        tried += 1
        ig = _hand_order(cfg.hand, cand)
        start, _, _ = _start_centres(ig, cfg)
        try:
            placement = place_hand(cfg.hand, dict(zip(cfg.fingers, start, strict=True)), obstacle=xs)
        except InfeasibleGrasp as exc:
            first_error = first_error or exc
            failures[cand.spread] = failures.get(cand.spread, 0) + 1
            continue
        return ig, placement
    if cfg.grasp is not None:
        raise InfeasibleGrasp(f"the hand does not reach the given grasp: {first_error}")
    raise InfeasibleGrasp(
        f"the hand reaches none of the {tried} best force-closure grasps tried; the best one: {first_error}"
    )


def _spread_failed(failures: dict[float, int], theta: float, spread: float) -> bool:
    """Whether :func:`_reachable_grasp` skips grasps of this spread angle now (the ranking then
    need not compute their quality)."""
    return failures.get(spread, 0) >= PER_SPREAD


def _initial_grasp(
    body: Body, xs: NDArray[np.float64], com: NDArray[np.float64], cfg: PlanConfig
) -> tuple[InitialGrasp, HandPlacement | None]:
    """The initial grasp (the best reachable force-closure grasp, or ``cfg.grasp``) and the
    hand's placement for it."""
    if cfg.grasp is None:
        failures: dict[float, int] = {}
        skip = functools.partial(_spread_failed, failures)
        ranked = ranked_grasps(xs, body.mesh.facets, com, cfg.contact.mu, cfg.layout, skip=skip)
        return _reachable_grasp(xs, ranked, cfg, failures)
    ig = cfg.grasp
    R = cfg.fingertip_radius  # a fingertip resting at each contact touches the surface near it
    probe = FingertipContact(
        tuple(Fingertip(R, centre=p + 0.5 * R * n) for p, n in zip(ig.points, ig.normals, strict=True)),
        cfg.contact,
    )
    near = np.bincount(probe.pairs(body, xs, 0.0).finger, minlength=len(ig.points))
    if near.min() == 0:
        j = int(np.argmin(near))
        raise InfeasibleGrasp(
            f"the given grasp's {cfg.fingers[j]} contact {np.round(ig.points[j] * 1e3, 2).tolist()} mm lies "
            f"more than {cfg.fingertip_radius / 2 * 1e3:g} mm off this object's surface: that grasp was "
            "planned for another object, mesh or placement"
        )
    return _reachable_grasp(xs, [ig], cfg)


@dataclass(frozen=True)
class ClosingSetup:
    """Where a closing starts: the object at rest on the table, the initial grasp, the hand's
    placement for it and the fingertips' closing lines.

    Attributes
    ----------
    settled: the object at rest on the table (no fingers).  table: the table.
    body: the object with its rest shape where it was placed on the table: its mesh turned with
        it when the settle turned it onto a stable facet (:meth:`Body.placed_at
        <softgrasp.physics.body.Body.placed_at>`), so that the contact law measures the mesh where
        the fingertips land on it (:mod:`softgrasp.physics.fingertip.landing`).
    grasp: the initial grasp.  placement: the hand's placement (None without a hand model).
    start: fingertip centres where the closing starts [m], (3, 3).
    directions: unit closing directions (towards the contact triangle's centroid), (3, 3).
    reach: each contact's distance to that centroid [m], (3,).
    first_touch: travel along its line at which each fingertip first touches the object [m], (3,).
    max_squeeze: the configuration's ``max_squeeze``.
    """

    settled: State
    table: PlaneContact
    body: Body
    grasp: InitialGrasp
    placement: HandPlacement | None
    start: NDArray[np.float64]
    directions: NDArray[np.float64]
    reach: NDArray[np.float64]
    first_touch: NDArray[np.float64]
    max_squeeze: float

    @property
    def placed(self) -> NDArray[np.float64]:
        """The unloaded object as placed on the table [m], (N, 3)."""
        return self.body.mesh.points

    @property
    def max_travel(self) -> float:
        """Farthest travel of a fingertip along its line before the object counts as crushed [m]
        (``max_squeeze`` of the shortest reach past the last finger's first contact)."""
        return float(self.first_touch.max() + self.max_squeeze * self.reach.min())


def closing_setup(
    body: Body, cfg: PlanConfig, cache: SolverCache | None = None, *, keep_rest: bool = False
) -> ClosingSetup:
    """Settle ``body`` on the table, choose (or take ``cfg.grasp``) the initial grasp the hand
    reaches, and lay the fingertips' closing lines (paper step 1). ``keep_rest``: the rest on the
    table is read from softgrasp's cache folder when it was kept there, else kept there
    (:func:`softgrasp.grasp.kept_rest.settle`)."""
    cache = cache if cache is not None else SolverCache()
    settled, table, placed = settle(body, cfg, cache, keep=keep_rest)
    body = body.placed_at(placed)  # the rest shape where it lies (turned with it, if it was)
    xs = settled.x
    ig, placement = _initial_grasp(body, xs, centre_of_mass(body, xs), cfg)
    start, u, reach = _start_centres(ig, cfg)
    R = cfg.fingertip_radius
    first = np.array(
        [
            _first_touch(
                body,
                cfg.contact,
                Fingertip(R, centre=start[j], velocity=u[j], name=cfg.fingers[j]),
                xs,
                4 * cfg.step + R,
            )
            for j in range(len(cfg.fingers))
        ]
    )
    return ClosingSetup(settled, table, body, ig, placement, start, u, reach, first, cfg.max_squeeze)
