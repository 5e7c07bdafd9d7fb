"""Static equilibrium of a scene: friction advanced by passes around Newton's method, and load
increments split in halves where they do not converge, and, where even halves do not, a rest
reached by backward Euler steps from rest (:func:`proximal_solve`).

The equilibrium is the minimum of the total potential (elastic + gravity + contact penalty + the
tangential springs of sticking contacts). Friction is advanced incrementally: Newton
(:func:`softgrasp.sim.newton.newton`) solves with the contact anchors held fixed (stick
predictor); then anchors whose spring exceeds the Coulomb limit are dragged back onto it (slip
return, :meth:`Scene.update_contacts`) and Newton runs again, until the anchors no longer move.

Linear constraints ``C (x - x_ref) = 0`` (e.g. fixing the rigid motions a frictionless set-up leaves
free) are enforced with Lagrange multipliers in a saddle-point system.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import backend
from softgrasp.errors import NotConverged, SimulationUnstable, diagnosis
from softgrasp.linalg import pardiso
from softgrasp.linalg.solve import SolverCache, assembly_threads
from softgrasp.physics.body import Body
from softgrasp.sim.inertia import Inertia
from softgrasp.sim.newton import SMALLER_STEPS, newton, unbalanced, valid
from softgrasp.sim.scene import Scene, State

#: The friction passes and the load increments at DEBUG level (Newton's iterations:
#: :mod:`softgrasp.sim.newton`).
log = logging.getLogger(__name__)

__all__ = [
    "StaticInfo",
    "solve_static",
    "solve_increment",
    "proximal_solve",
    "solve_rest",
    "rigid_constraints",
    "extrapolated",
    "MAX_HALVINGS",
]

#: How often :func:`solve_increment` halves a load increment that does not converge.
MAX_HALVINGS = 4
#: Most backward Euler steps :func:`proximal_solve` takes before its final static solve.
PROXIMAL_MAX_STEPS = 40
#: Failed steps (each retried a quarter as long) after which the backward Euler steps of
#: :func:`solve_increment` give up: the iterates cycle even held by the inertia spring (a contact
#: on its edge of touching, not a free motion), and a closing tries a little further instead.
PROXIMAL_MAX_FAILED = 8


@dataclass(frozen=True)
class StaticInfo:
    """Diagnostics of a static solve.

    Attributes
    ----------
    newton_iterations: total Newton iterations over all friction passes.
    friction_passes: number of stick-predictor / slip-return passes.
    residual_N: final largest unbalanced nodal force component [N].
    constraint_forces_N: reactions of the constraints (generalised forces, ``C^T r`` acts on the
        nodes), (k,).
    """

    newton_iterations: int
    friction_passes: int
    residual_N: float
    constraint_forces_N: NDArray[np.float64]


def rigid_constraints(
    x_ref: NDArray[np.float64], mass: NDArray[np.float64], modes: str = "xyXYZ"
) -> sp.csr_matrix:
    """Rows fixing the mass-weighted rigid motions of a body about its configuration ``x_ref``.

    ``modes`` picks translations (``x``, ``y``, ``z``) and linearised rotations about the centre of
    mass (``X``, ``Y``, ``Z``). Returns a sparse (k, 3N) matrix C; the constraints are
    ``C (x - x_ref) = 0``.
    """
    n = x_ref.shape[0]
    w = mass / mass.sum()
    r = x_ref - (w[:, None] * x_ref).sum(axis=0)
    rows = []
    axes = {"x": 0, "y": 1, "z": 2}
    for m in modes:
        row = np.zeros((n, 3))
        if m in axes:
            row[:, axes[m]] = w
        else:
            a = np.zeros(3)
            a["XYZ".index(m)] = 1.0
            row = w[:, None] * np.cross(a, r)  # rotation field a x r, mass weighted
            row /= max(float(np.sqrt((row**2).sum())), 1e-300)
        rows.append(row.ravel())
    return sp.csr_matrix(np.array(rows))


def extrapolated(
    last: NDArray[np.float64], before: NDArray[np.float64], ratio: float = 1.0
) -> NDArray[np.float64]:
    """A start for the next load step's Newton (``guess`` of :func:`solve_static`): the last two
    rests ``before`` and ``last`` extrapolated linearly, ``ratio`` being the next step's length
    over the last one's (1 for equal steps)."""
    return last + ratio * (last - before)


def solve_static(
    scene: Scene,
    state: State,
    *,
    t: float | None = None,
    constraints: sp.csr_matrix | None = None,
    x_ref: NDArray[np.float64] | None = None,
    rtol: float = 1e-9,
    max_iter: int = 60,
    max_friction_passes: int = 30,
    cache: SolverCache | None = None,
    guess: NDArray[np.float64] | None = None,
    patience: int | None = None,
) -> tuple[State, StaticInfo]:
    """Bring the scene to rest at time (load parameter) ``t``, starting from ``state``.

    Parameters
    ----------
    scene: the body and interactions.
    state: the starting positions and contact states (e.g. the previous load step).
    t: load parameter passed to the interactions (moving plates, fingertips); default ``state.t``.
    constraints: optional sparse (k, 3N) C with ``C (x - x_ref) = 0`` enforced.
    x_ref: reference positions for the constraints; default ``state.x``.
    rtol: convergence when the largest unbalanced force <= rtol x the largest force present.
    cache: linear-solver state to reuse across calls (e.g. the increments of one loading).
    guess: positions [m] (N, 3) Newton starts from instead of ``state.x`` (a prediction, e.g.
        the last increments' rests extrapolated); ignored if it inverts a tet, and dropped when
        Newton finds no rest from it, the solve then starting again from ``state.x`` (a release
        step of the hold check of the sphere at mu = 0.05, its fingers slipping, crawls out
        from its extrapolated guess on one thread and balances from the last rest). The contact
        states are still ``state``'s, so the rest found is the one found from ``state.x`` except
        where a contact pair starts during the step: it is anchored where the iterates first touch
        it (the planner's set-points moved by ~4e-6 relative).
    patience: Newton gives up once that many iterations in a row found no lower unbalanced force
        (:func:`~softgrasp.sim.newton.stalls`; None: never for that). A solve given a patience
        (a release step of a hold check: the body may not be held) starts again from
        ``state.x`` only after a failure from ``guess`` that a start nearer the rest can mend
        (:attr:`~softgrasp.errors.NotConverged.advice` :data:`~softgrasp.sim.newton.SMALLER_STEPS`:
        a crawl, a cycle, the iteration limit), not after iterates that climb, stall or creep,
        Newton's diagnosis that the body is not held there (over nine plans, spheres at mu = 0.8,
        0.3 and 0.05 and at two mesh sizes, the cube, a box, a cylinder and a ball: the eight
        such second starts all failed again, the one that balanced followed a crawl).

    Returns
    -------
    (State at rest with updated friction anchors and v = 0, StaticInfo)

    Raises
    ------
    NotConverged: Newton stalled, or the body is not held (singular stiffness).
    SimulationUnstable: the configuration is invalid (inverted tets) at the start.

    NumPy's BLAS runs on one thread meanwhile (:func:`~softgrasp.linalg.pardiso.blas_one_thread`, as
    the planner holds it for a whole plan): OpenBLAS's threads would compete with the multigrid
    products' and PARDISO's.
    """
    cache = cache if cache is not None else SolverCache()
    with pardiso.blas_one_thread(), _force_threads(scene.body, cache):
        common = (scene, state, t, constraints, x_ref, rtol, max_iter, max_friction_passes, cache)
        try:
            return _solve_static(*common, guess, patience)
        except NotConverged as exc:
            if guess is None or (patience is not None and exc.advice != SMALLER_STEPS):
                raise
            log.debug("no rest from the guess: solving again from the state's positions")
        return _solve_static(*common, None, patience)


def _force_threads(body: Body, cache: SolverCache) -> contextlib.AbstractContextManager:
    """Numba's threads for a large body's force evaluations during a static solve (its sums run
    on the calling thread's: :meth:`softgrasp.physics.body.Body.internal_forces`): the assembly's, the idle
    cores on the multigrid path (:func:`~softgrasp.linalg.solve.assembly_threads`). Nothing is
    changed for smaller bodies, or in a forked child whose Numba threads were lost."""
    from softgrasp.linalg.sparse import _Threads
    from softgrasp.physics.forces_compiled import PARTITIONED_MIN_NODES

    if body.n_nodes < PARTITIONED_MIN_NODES or backend.forked():
        return contextlib.nullcontext()
    return _Threads(assembly_threads(3 * body.n_nodes, cache))


def _solve_static(
    scene: Scene,
    state: State,
    t: float | None,
    constraints: sp.csr_matrix | None,
    x_ref: NDArray[np.float64] | None,
    rtol: float,
    max_iter: int,
    max_friction_passes: int,
    cache: SolverCache,
    guess: NDArray[np.float64] | None,
    patience: int | None,
) -> tuple[State, StaticInfo]:
    tt = state.t if t is None else float(t)
    x = np.array(state.x, dtype=np.float64)
    if not valid(scene.body, x):
        raise SimulationUnstable("static solve started from a configuration with inverted tets")
    if guess is not None and valid(scene.body, guess):
        x = np.array(guess, dtype=np.float64)
    C = constraints
    if C is not None:
        ref = state.x if x_ref is None else x_ref
        # Start on the constraint manifold (project the initial guess).
        viol = C @ (x - ref).ravel()
        if np.abs(viol).max() > 0:
            CCt = (C @ C.T).toarray()
            x = x - (C.T @ np.linalg.solve(CCt, viol)).reshape(-1, 3)
    zeros = np.zeros_like(x)
    # Register contacts that start at this load step without slip returns: slip is decided only
    # once the body has deformed under the new load (at the end of each pass).
    contacts = scene.refresh_contacts(x, tt, state.contacts)
    # The first pass's friction limits are those of the rest the solve starts from (its positions
    # at its time), not the guess's: a guess moves where Newton starts, not the law it solves.
    contacts = scene.begin_static(state.x, state.t, contacts)
    total_it = 0
    for p in range(1, max_friction_passes + 1):
        x, it, res, lam, contacts = newton(scene, x, tt, contacts, C, rtol, max_iter, cache, patience)
        total_it += it
        new_contacts = scene.static_update_contacts(x, tt, contacts)
        f = scene.static_forces(x, tt, new_contacts).ravel()
        if C is not None:
            f = f - C.T @ lam
        f_int = scene.body.internal_forces(x)
        scale = max(np.abs(f_int).max(), np.abs(scene.body.mass).max() * 9.81, 1e-300)
        contacts = new_contacts
        log.debug("friction pass %d: %d Newton its, unbalanced after the slip return %.3e N", p, it,
                  np.abs(f).max())  # fmt: skip
        if np.abs(f).max() <= max(10 * rtol * scale, 2 * res):
            contacts = scene.finish_static(x, tt, contacts)
            return State(x, zeros, tt, contacts), StaticInfo(total_it, p, float(np.abs(f).max()), -lam)
    raise NotConverged(f"friction did not settle in {max_friction_passes} stick/slip passes", SMALLER_STEPS)


def solve_increment(
    scene: Scene,
    state: State,
    t: float,
    *,
    cache: SolverCache | None = None,
    max_halvings: int = MAX_HALVINGS,
    guess: NDArray[np.float64] | None = None,
    rtol: float = 1e-9,
) -> tuple[State, int, int]:
    """Static solve of one load increment from ``state`` (at ``state.t``) to load parameter ``t``;
    an increment that does not converge is split in halves from the last converged state, up to
    ``max_halvings`` times (contact kinks can make Newton cycle on a large increment). ``guess``
    (see :func:`solve_static`) is used by the whole increment only, not by its halves; ``rtol`` is
    :func:`solve_static`'s.

    Returns
    -------
    (State at t, Newton iterations used, halvings needed)

    Raises
    ------
    NotConverged: the increment did not converge even when split into ``2**max_halvings`` parts.
    """
    t_prev = state.t
    for level in range(max_halvings + 1):
        n = 2**level
        try:
            s, iters = state, 0
            for k in range(1, n + 1):
                s, info = solve_static(
                    scene,
                    s,
                    t=t_prev + (t - t_prev) * k / n,
                    cache=cache,
                    guess=guess if n == 1 else None,
                    rtol=rtol,
                )
                iters += info.newton_iterations
            return s, iters, level
        except NotConverged as exc:
            log.debug("load increment to t = %.6g in %d part(s) failed: %s", t, n, exc)
            if level == max_halvings:
                try:
                    rest, its = proximal_solve(
                        scene, state, t, cache=cache, rtol=rtol, max_failed=PROXIMAL_MAX_FAILED
                    )
                    return rest, its, level
                except NotConverged as last:
                    raise NotConverged(
                        f"load increment to t = {t:.6g} did not converge even when split into {n} parts "
                        f"({diagnosis(exc)}), nor by backward Euler steps ({diagnosis(last)})",
                        SMALLER_STEPS,
                    ) from exc
    raise AssertionError("unreachable")  # pragma: no cover


def proximal_solve(
    scene: Scene,
    state: State,
    t: float,
    *,
    cache: SolverCache | None = None,
    rtol: float = 1e-9,
    max_steps: int = PROXIMAL_MAX_STEPS,
    max_failed: int | None = None,
) -> tuple[State, int]:
    """The rest at load parameter ``t`` reached from ``state`` by backward Euler steps that each
    start at rest (proximal steps), for where Newton on the static balance finds none (its
    iterates cycling as contacts flip in and out, or crawling along a nearly free rolling mode):
    each step balances the forces plus an inertia spring ``m / dt^2`` towards the last positions
    (:class:`~softgrasp.sim.inertia.Inertia`), which holds the iterates near them. The first step
    is ``1 / omega`` long (omega the body's lowest elastic frequency,
    :attr:`~softgrasp.physics.body.Body.fundamental_frequency`: the inertia spring is then about as
    stiff as the body), each next one twice the last, a step that fails retried a quarter as long,
    until the forces balance without the inertia spring (to ``rtol`` of the largest force, as
    :func:`solve_static`); where instead a step moves the positions by less than 1e-6 of the
    body's size, or after ``max_steps`` steps, the static solve from there (the inertia gone)
    gives the rest. The friction anchors follow the steps' path.

    Returns (the rest, the Newton iterations of every step and of the static solve).

    Raises NotConverged when that static solve fails (no rest near: the object slides away), or
    when ``max_failed`` steps fail (None: no limit but ``max_steps``)."""
    cache = cache if cache is not None else SolverCache()
    body = scene.body
    size = float(np.ptp(body.mesh.points, axis=0).max())
    dt = 1.0 / body.fundamental_frequency
    still = np.zeros_like(state.x)
    current = State(state.x, still, t, state.contacts)
    iterations = 0
    failed = 0  # steps failed
    for _ in range(max_steps):
        step = Scene(body, (*scene.interactions, Inertia(current.x, dt)))
        try:
            new, info = solve_static(
                step, State(current.x, still, t, (*current.contacts, None)), cache=cache, rtol=rtol
            )
        except NotConverged as exc:
            failed += 1
            if failed == max_failed:
                raise NotConverged(f"{failed} backward Euler steps found no rest ({diagnosis(exc)})") from exc
            dt /= 4.0
            continue
        iterations += info.newton_iterations
        moved = float(np.abs(new.x - current.x).max())
        current = State(new.x, still, t, new.contacts[:-1])
        f, _, scale = unbalanced(scene, current.x, t, current.contacts)
        if float(np.abs(f).max()) <= rtol * scale:
            return current, iterations  # the inertia spring holds no force left: a rest of the scene
        if moved < 1e-6 * size:
            break  # at rest under the inertia spring: the static solve from here
        dt *= 2.0
    rest, info = solve_static(scene, current, cache=cache, rtol=rtol)
    return rest, iterations + info.newton_iterations


def solve_rest(
    scene: Scene, state: State, *, cache: SolverCache | None = None, rtol: float = 1e-9
) -> tuple[State, int]:
    """The rest of ``scene`` from ``state`` at its load: :func:`solve_static`, or where Newton
    finds none (:class:`NotConverged`), :func:`proximal_solve`. Returns (the rest, its Newton
    iterations)."""
    try:
        rest, info = solve_static(scene, state, cache=cache, rtol=rtol)
        return rest, info.newton_iterations
    except NotConverged as exc:
        log.debug("static solve failed (%s); backward Euler steps from rest instead", exc)
        return proximal_solve(scene, state, state.t, cache=cache, rtol=rtol)
