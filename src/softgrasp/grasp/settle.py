"""The object at rest on the table, before the fingers close (paper Sec. 4.3.2): the mesh as it
stands, or turned onto its most stable hull facet where it would tip over, brought to static
equilibrium under its weight on the table, with friction.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from softgrasp.errors import NotConverged, diagnosis
from softgrasp.grasp.config import LOWERED_MAX_ITER, LOWERED_MIN_NODES, PATH_RTOL, PlanConfig
from softgrasp.linalg.solve import SolverCache, by_multigrid
from softgrasp.model.mesh.placement import stable_facet_pose
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.laws import effective_modulus
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.physics.resting import lowered_onto_table
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import proximal_solve, solve_static

__all__ = [
    "settle_on_table",
    "centre_of_mass",
    "table_under",
    "stable_pose",
    "standing",
    "lowered_start",
    "no_rest_advice",
]


def centre_of_mass(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """The centre of mass of ``body`` at node positions ``x`` [m]."""
    return (body.mass @ x) / body.total_mass


def table_under(x: NDArray[np.float64], mu: float) -> PlaneContact:
    """The table: the horizontal plane under the lowest node of ``x``."""
    zmin = float(x[:, 2].min())
    return PlaneContact(Plane(np.array([0.0, 0.0, zmin]), np.array([0.0, 0.0, 1.0])), mu=mu, name="table")


def stable_pose(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``x`` turned onto its most stable hull facet about its centre of mass
    (:func:`softgrasp.model.mesh.placement.stable_facet_pose`)."""
    return stable_facet_pose(x, centre_of_mass(body, x))


def standing(body: Body) -> Body:
    """``body`` as it stands on a table: as meshed where its centre of mass lies above its lowest
    nodes' hull, otherwise turned onto its most stable hull facet (:func:`stable_pose`), as
    :func:`settle_on_table` places it. A mesh balanced on an edge or a vertex is otherwise held
    up only by the table's friction, a rest no real object has."""
    x = np.asarray(body.mesh.points, dtype=np.float64)
    return body if _stands(x, centre_of_mass(body, x)) else body.placed_at(stable_pose(body, x))


def _lowest(x: NDArray[np.float64]) -> NDArray[np.bool_]:
    """The nodes of ``x`` at its lowest height (to 1e-9 of its size): those touching a table
    under it."""
    return x[:, 2] <= x[:, 2].min() + 1e-9 * float(np.ptp(x, axis=0).max())


def _stands(x: NDArray[np.float64], com: NDArray[np.float64]) -> bool:
    """Whether ``x`` stands on the table as it is: the centre of mass lies above the convex hull
    of its lowest nodes (not balanced on a vertex or an edge, which only tips over)."""
    L = float(np.ptp(x, axis=0).max())
    low = x[_lowest(x), :2]
    if len(low) < 3:
        return False
    try:
        hull = ConvexHull(low)
    except QhullError:
        return False  # collinear: an edge
    return bool((hull.equations[:, :2] @ com[:2] + hull.equations[:, 2] <= 1e-12 * L).all())


def lowered_start(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Where the settle's Newton starts: ``x`` lowered by half the approach its weight presses it
    into the table (:func:`softgrasp.physics.resting.lowered_onto_table`), the nodes of the
    predicted contact patch touching from the start; ``None`` (start as placed) where gravity
    does not press the body onto the table, or where the patch is no more than the nodes that
    touch as placed (a flat face down, where lowering gains nothing)."""
    weight = -float(body.mass.sum() * body.gravity[2])
    if not weight > 0.0:
        return None
    modulus = effective_modulus(math.inf, 0.0, body.material.E, body.material.nu)  # a rigid table
    lowered = lowered_onto_table(x, body.mesh.facets, weight, modulus)
    pressed_in = int((lowered[:, 2] < x[:, 2].min()).sum())
    return lowered if pressed_in > int(_lowest(x).sum()) else None


def settle_on_table(
    body: Body, cfg: PlanConfig, cache: SolverCache
) -> tuple[State, PlaneContact, NDArray[np.float64]]:
    """The object at rest on the table, and the table. As the mesh stands if its centre of mass is
    above its lowest nodes' hull and a rest is found there; otherwise (a convex mesh balanced on
    one node tips over: Newton creeps along the nearly free tipping mode), standing on its most
    stable hull facet, as a real object comes to rest.

    For bodies of :data:`~softgrasp.grasp.config.LOWERED_MIN_NODES` nodes or more whose Newton
    systems go to multigrid (:func:`~softgrasp.linalg.solve.by_multigrid`, the default there),
    Newton first starts each placement lowered by half the approach its weight presses it into the
    table (:func:`lowered_start`): the nodes of the predicted contact patch touch from the first
    iterate, anchored for friction where they stand, as when the object is set straight down;
    then, if that finds no rest within :data:`~softgrasp.grasp.config.LOWERED_MAX_ITER`
    iterations (a friction pass), level with the table; the linear solver's state is dropped
    between starts. Smaller bodies and PARDISO's exact solves start level: there the iterates of a
    lowered sphere may zig-zag along its nearly neutral rolling mode.
    Where no start of a placement finds a rest by Newton directly (a soft, heavy object sagging
    far onto the table, whose Newton iterates cycle as nodes flip in and out of contact; a ball
    meshed finely at its bottom, whose iterates wander along its nearly neutral rolling mode),
    that placement is brought to rest by backward Euler steps from rest
    (:func:`~softgrasp.sim.static.proximal_solve`) before the object is turned onto its most
    stable facet: one that stands stays where it is put.
    Returns (the rest state, the table, the unloaded placement the rest was found from)."""
    lowers = body.n_nodes >= LOWERED_MIN_NODES and by_multigrid(3 * body.n_nodes, cache)

    def placements() -> Iterable[tuple[str, NDArray[np.float64]]]:
        x = np.asarray(body.mesh.points, dtype=np.float64)
        if _stands(x, centre_of_mass(body, x)):
            yield "as meshed", x
        yield "on its most stable facet", stable_pose(body, x)

    failures = []
    for where, x in placements():
        table = table_under(x, cfg.table_mu)
        rest = Scene(body, (table,))
        guess = lowered_start(body, x) if lowers else None
        starts = ([(f"{where}, lowered", guess)] if guess is not None else []) + [(where, None)]
        for label, start in starts:
            if failures:
                cache.scene_changed()  # the failed start's factor or hierarchy is no guide here
            limit = {} if start is None else {"guess": start, "max_iter": LOWERED_MAX_ITER}
            try:
                state = solve_static(rest, rest.initial_state(x), cache=cache, rtol=PATH_RTOL, **limit)[0]
                return state, table, x
            except NotConverged as exc:
                failures.append((label, exc))
        # Set down where it stands before it is turned: an object that stands stays where it is put
        # (a ball meshed finely at its bottom, whose nearly neutral rolling mode Newton wanders
        # along, would otherwise be turned onto a coarse facet across its hull).
        cache.scene_changed()
        try:
            return proximal_solve(rest, rest.initial_state(x), 0.0, cache=cache, rtol=PATH_RTOL)[0], table, x
        except NotConverged as exc:
            failures.append((f"{where}, by backward Euler steps", exc))
    raise NotConverged(
        "the object found no rest on the table: "
        + "; ".join(f"{where}: {diagnosis(exc)}" for where, exc in failures),
        no_rest_advice(body),
    ) from failures[-1][1]


def no_rest_advice(body: Body) -> str:
    """What to change where ``body`` finds no rest on the table, with how far its weight strains it."""
    sag = weight_strain(body, float(np.ptp(body.mesh.points[:, 2])))
    return (
        f"its weight strains it by about {100 * sag:.2g} % (rho g H / E), and the table's contact with its "
        "nodes flips as they touch and leave: a finer mesh (--mesh-size) spreads that over more, "
        "smaller nodes and may let it rest"
    )


def weight_strain(body: Body, height_m: float) -> float:
    """The strain the object's own weight causes at its base, rho g H / E (``height_m`` [m] the
    object's height): how far it sags onto the table."""
    return float(body.density * np.linalg.norm(body.gravity) * height_m / body.material.E)
