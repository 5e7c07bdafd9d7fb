"""Newton's method on a scene's unbalanced forces, with a line search on two merits (the
unbalanced force and the potential energy), Levenberg-Marquardt shifts where no step length makes
progress, a negative-curvature step for a body tipping over, and the early ends of a solve that
will not converge (a stall balanced to :data:`STALL_RTOL`, creeping, crawling, climbing, cycling).

One Newton solve holds the contacts' friction anchors fixed (the stick predictor of
:func:`softgrasp.sim.static.solve_static`, which runs the friction passes around it).
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import NotConverged
from softgrasp.linalg.solve import (
    _SINGULAR,
    SolverCache,
    _rigid_motion_free,
    assembly_threads,
    solve_newton_system,
)
from softgrasp.physics.body import Body
from softgrasp.sim.newton_matrix import newton_matrix
from softgrasp.sim.scene import Scene

#: Newton's progress at DEBUG level: each iteration's unbalanced force and accepted step.
log = logging.getLogger(__name__)

__all__ = [
    "newton",
    "unbalanced",
    "valid",
    "climbs",
    "stalls",
    "cycle_period",
    "STALL_RTOL",
    "NEGATIVE_CURVATURE_MAX_GROWTH",
    "SMALLER_STEPS",
]

#: The advice of a static solve that did not converge (:attr:`NotConverged.advice`): a load step
#: that moves less starts Newton nearer its solution.
SMALLER_STEPS = "use smaller load steps"

#: A Newton iteration that stalls (contact kinks) is accepted when the largest unbalanced force
#: is below this fraction of the largest force present (the target is ``rtol``).
STALL_RTOL = 1e-6
#: An iterate balanced to ``STALL_RTOL`` is accepted when the linear solver had to shift an
#: indefinite Newton matrix (the step is Levenberg-Marquardt's, not Newton's) and the previous step
#: reduced the largest unbalanced force by less than this factor: the shifted steps crawl along a
#: nearly neutral mode (a sphere rolling on its contact patch, its rolling stiffness ~1e-10 of the
#: largest stiffness and of either sign) and would creep at ~1 % per iteration to the limit.
INDEFINITE_STALL = 0.5
#: An indefinite matrix's step is followed (:func:`_follow_negative_curvature`) only where the
#: largest unbalanced force exceeds this fraction of the largest force present: a body tipping
#: over is unbalanced by a good part of its weight's moment, while one balanced to round-off on a
#: nearly neutral mode (a sphere on its contact patch, whose potential falls by nanojoules along
#: it) is only kicked off its balance, and wanders (the fine sphere's settle on the table).
FOLLOW_RTOL = 1e-4
#: Longest multiple of an indefinite matrix's shifted step that :func:`_follow_negative_curvature`
#: tries (in doublings).
NEGATIVE_CURVATURE_MAX_GROWTH = 1024.0
#: Newton gives up after this many consecutive accepted steps no longer than ``CREEP_ALPHA`` of
#: the Newton step that reduced the largest unbalanced force by less than 1 %.
CREEP_ITERATIONS = 6
CREEP_ALPHA = 1.0 / 64
#: Newton gives up on a crawl: when each of its last ``CRAWL_ITERATIONS`` iterations reduced the
#: largest unbalanced force, no faster at the last than at the first, and so little that even the
#: best of those rates, kept up for the iterations left, would not balance the forces to the
#: solve's tolerance, or to ``STALL_RTOL`` of the largest force if that is looser. An object
#: sliding out of fingers that cannot hold it crawls at ~1.5 % per iteration: hundreds of them.
CRAWL_ITERATIONS = 4
#: Newton gives up on a climb: when the largest unbalanced force rose at each of its last
#: ``CLIMB_ITERATIONS`` iterations, each after a full Newton step on a positive definite matrix
#: (unshifted), the line search taking every step whole while the forces grow. The iterates then
#: run away from any balance: an object sliding out of fingers that cannot
#: hold it (the table's support gone) rose so at each of its 16-18 iterations up to the release
#: step's limit. Solves that converged rose at most 7 times in a row (a foam cube's closing
#: increment whose contacts engaged over several iterates), 2 on the spheres; a body tipping over
#: rises for longer, but on an indefinite matrix's shifted steps, which do not count.
CLIMB_ITERATIONS = 10
#: Newton gives up when its iterates cycle: the unbalanced force repeats (to this relative
#: tolerance: the inexact linear solves leave ~1e-7 of noise) with a period of 2 to 4 iterations,
#: twice in a row (a node or a contact pair switching in and out on every other step, or a step
#: the energy merit accepts undone by one the force merit accepts; it would cycle to the
#: iteration limit).
CYCLE_RTOL = 1e-5
#: Largest relative residual of a Newton step's linear solve (the inexact Newton forcing term is
#: the relative unbalanced force, capped here). With looser solves the iterates wander further and
#: the friction problem, whose equilibria are not unique, was seen to settle in a neighbouring one
#: (plans a few per cent apart).
FORCING_MAX = 1e-4


def valid(body: Body, x: NDArray[np.float64]) -> bool:
    """Whether every tet of ``body`` has a positive signed volume at ``x`` (the compiled count:
    the line search asks at every trial step)."""
    from softgrasp.physics.volume import count_inverted

    return count_inverted(x, body.mesh.tets) == 0


def unbalanced(
    scene: Scene, x: NDArray[np.float64], t: float, contacts: tuple
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """The static forces on the nodes at ``x`` (N, 3) [N], the body's internal part of them, and
    the scale a static solve's tolerance is relative to: the largest internal force, other
    force or node weight [N]."""
    body = scene.body
    f_int = body.internal_forces(x)
    f = scene.static_forces(x, t, contacts, internal=f_int)
    grav = np.abs(body.mass[:, None] * body.gravity[None, :]).max()
    return f, f_int, max(float(np.abs(f_int).max()), float(np.abs(f - f_int).max()), float(grav), 1e-300)


def _residual(scene: Scene, x, t, contacts, C, lam) -> NDArray[np.float64]:
    r = scene.static_forces(x, t, contacts).ravel()
    return r - C.T @ lam if C is not None else r


def newton(
    scene: Scene,
    x: NDArray[np.float64],
    t: float,
    contacts: tuple,
    C: sp.csr_matrix | None,
    rtol: float,
    max_iter: int,
    cache: SolverCache,
    patience: int | None = None,
) -> tuple[NDArray[np.float64], int, float, NDArray[np.float64], tuple]:
    """Newton's method on the unbalanced forces, globalised on their norm.

    Contact forces are not all exact gradients (fingertip friction, the patch rule's weights), so a
    step is accepted when it reduces the 2-norm of the unbalanced forces or the potential energy;
    when no step length does either, the stiffness diagonal is added (Levenberg-Marquardt) until one
    does. ``patience``: give up once that many iterations in a row found no lower largest
    unbalanced force than an earlier one (:func:`stalls`; None: never for that).
    """
    body = scene.body
    L = float(np.ptp(body.mesh.points, axis=0).max())
    lam = np.zeros(0 if C is None else C.shape[0])
    grav = np.abs(body.mass[:, None] * body.gravity[None, :]).max()
    shift = 0.0
    creep, last_res = 0, np.inf
    history: list[float] = []  # the unbalanced force [N] at the start of each iteration
    plain: list[bool] = []  # whether each iteration's step was a full Newton step, unshifted
    start = contacts  # the pass's contact states (limits from its start: Scene.begin_static)
    for it in range(1, max_iter + 1):
        f, f_int, scale = unbalanced(scene, x, t, contacts)
        if C is None and (res := float(np.abs(f).max())) <= rtol * scale:
            return x, it - 1, res, lam, contacts  # balanced already: no system to solve
        A, exact = newton_matrix(
            scene, x, t, contacts, L, assembly_threads(3 * body.n_nodes, cache), exact_body=cache.exact_body
        )
        # Inexact Newton: the linear solve need only be as accurate as the step is far from
        # convergence (the forcing term; quadratic convergence is kept).
        forcing = min(FORCING_MAX, float(np.abs(f).max()) / scale)
        accepted = False
        while not accepted:
            As = A if shift == 0.0 else (A + sp.diags(shift * np.abs(A.diagonal()) + 1e-300)).tocsr()
            shifted_before = cache.stats.get("shifted", 0)
            indefinite_before = cache.stats.get("indefinite_factor", 0)
            try:
                dx, lam_new = solve_newton_system(
                    As, f.ravel(), C, x, cache, matvec=exact if shift == 0.0 else None, rtol=forcing
                )
            except NotConverged:
                if C is not None or shift >= 1e6:
                    raise
                # A singular Newton matrix whose system has no solution (a body standing on
                # nodes that carry no force yet, about to tip): step along the solution of the
                # diagonally shifted matrix instead, a descent direction (Levenberg-Marquardt, as
                # when the line search below accepts no step).
                shift = max(10.0 * shift, 1e-4)
                log.debug("newton it %d: singular system, the diagonal shifted by %.1e", it, shift)
                continue
            r0 = f.ravel() - (C.T @ lam_new if C is not None else 0.0)
            res = float(np.abs(r0).max())
            if res <= rtol * scale:
                return x, it - 1, res, lam_new, contacts
            if (
                cache.stats.get("shifted", 0) > shifted_before
                and res <= STALL_RTOL * scale
                and res > INDEFINITE_STALL * last_res
            ):
                # Balanced to 1e-6 of the largest force on an indefinite (nearly neutral) matrix,
                # the shifted steps no longer converging: accept.
                log.debug("newton it %d: unbalanced %.6e N, indefinite matrix, stalled: accepted", it, res)
                return x, it - 1, res, lam_new, contacts
            n0 = float(np.linalg.norm(r0))
            d = dx.reshape(-1, 3)
            step_max = float(np.abs(d).max())
            cap = min(1.0, 0.1 * L / step_max) if step_max > 0 else 1.0
            e0: float | None = None  # the energy at x, computed when the energy merit is first asked
            descent = float(f.ravel() @ dx) * cap
            for alpha in 0.5 ** np.arange(11):
                xn = x + alpha * cap * d
                if not valid(body, xn):
                    continue
                rn = float(np.linalg.norm(_residual(scene, xn, t, contacts, C, lam_new)))
                # Either merit certifies progress: the unbalanced force, or the potential energy
                # (which is exact where every force is conservative, and gets past contact kinks).
                if rn < (1.0 - 1e-4 * alpha) * n0:
                    accepted = True
                    break
                if descent > 0:
                    e0 = scene.energy(x, t, contacts) if e0 is None else e0
                    if scene.energy(xn, t, contacts) <= e0 - 1e-4 * alpha * descent:
                        accepted = True
                        break
            if (
                accepted
                and alpha == 1.0
                and cap == 1.0
                and descent > 0
                and exact is None
                and C is None
                and cache.stats.get("indefinite_factor", 0) > indefinite_before
                and res > FOLLOW_RTOL * scale
            ):
                # The step came from a shifted matrix whose factorisation found it indefinite (a
                # body tipping over on its few supporting nodes, still far from balanced): follow
                # it while the potential keeps falling. (Not where only conjugate gradients met
                # negative curvature: on the 27 749-node ball, round-off on its nearly neutral
                # rolling mode, followed, left Newton creeping at a constant unbalanced force.)
                xn, grown = _follow_negative_curvature(scene, x, d, t, contacts, L)
                if grown > 1.0:
                    log.debug("newton it %d: indefinite matrix, the step followed %g times as far", it, grown)
            if not accepted:
                if shift >= 1e6:
                    if res <= STALL_RTOL * scale:
                        # Cycling across a contact kink (a node flipping in and out of contact)
                        # with the forces balanced to 1e-6 of the largest force: accept.
                        return x, it, res, lam_new, contacts
                    raise NotConverged(
                        f"static solve stalled at iteration {it}: largest unbalanced force {res:.3g} N "
                        f"(scale {scale:.3g} N); the load step may be too large or the body unstable"
                    )
                shift = max(10.0 * shift, 1e-4)
        # Creeping: tiny accepted steps that barely reduce the unbalanced force mean Newton is
        # crawling along a nearly free or unstable motion (a body balanced on a vertex tipping
        # over); it will not converge, so say so now rather than after max_iter iterations.
        creep = creep + 1 if alpha <= CREEP_ALPHA and res > 0.99 * last_res else 0
        last_res = res
        if creep >= CREEP_ITERATIONS and res > STALL_RTOL * scale:
            raise NotConverged(
                f"static solve creeps (steps of {alpha:.1e} of Newton's for {creep} iterations, largest "
                f"unbalanced force {res:.3g} N): the body is not held in this configuration"
            )
        history.append(res)
        if rate := _crawl_rate(history, max_iter - it + 1, max(rtol, STALL_RTOL) * scale):
            if _free_rigid_motion(scene, x, t, contacts, C):
                raise NotConverged(f"static solve did not converge: {_SINGULAR}")
            raise NotConverged(
                f"static solve crawls (largest unbalanced force {res:.3g} N, falling by at most "
                f"{1.0 - rate:.1%} per iteration, too slowly to balance in the {max_iter} Newton "
                f"iterations it is given)",
                SMALLER_STEPS,
            )
        if patience is not None and stalls(history, patience):
            raise NotConverged(
                f"static solve makes no progress (the largest unbalanced force, {res:.3g} N, not below "
                f"its lowest, {min(history):.3g} N, for {patience} iterations): the body is not held "
                "in this configuration"
            )
        if climbs(history, plain):
            if _free_rigid_motion(scene, x, t, contacts, C):
                raise NotConverged(f"static solve did not converge: {_SINGULAR}")
            raise NotConverged(
                f"static solve climbs (the largest unbalanced force rose at each of the last "
                f"{CLIMB_ITERATIONS} iterations, to {res:.3g} N): the iterates run away from any "
                "balance; the body is not held in this configuration"
            )
        plain.append(
            alpha == 1.0
            and cap == 1.0
            and shift == 0.0
            and cache.stats.get("shifted", 0) == shifted_before
            and cache.stats.get("indefinite_factor", 0) == indefinite_before
        )
        if period := cycle_period(history):
            if res <= STALL_RTOL * scale:
                return x, it, res, lam_new, contacts  # balanced to 1e-6 of the largest force: accept
            if _free_rigid_motion(scene, x, t, contacts, C):
                raise NotConverged(f"static solve did not converge: {_SINGULAR}")
            raise NotConverged(
                f"static solve cycles (the same {period} iterates over and over, largest unbalanced force "
                f"{res:.3g} N)",
                SMALLER_STEPS,
            )
        log.debug(
            "newton it %d: unbalanced %.6e N (scale %.3e), step %.3g x %.3g, shift %.1e",
            it, res, scale, alpha, cap, shift,
        )  # fmt: skip
        lam = lam_new
        shift = shift / 10.0 if shift > 1e-4 else 0.0
        small = float(np.abs(xn - x).max()) <= 1e-13 * L
        x = xn
        # Between Newton steps the contacts are refreshed from the pass's starting state: pairs
        # that touched then keep their anchors; pairs that touch only now are anchored where they
        # are, carrying their anchors along until the pass converges (a contact made during a load
        # step starts unloaded at the step's equilibrium, wherever the iterates first touched);
        # limits stay lagged until the end of the pass.
        contacts = scene.refresh_contacts(x, t, start)
        if small:
            return x, it, res, lam, contacts
    res = float(np.abs(_residual(scene, x, t, contacts, C, lam)).max())
    f_int = body.internal_forces(x)
    scale = max(np.abs(f_int).max(), grav, 1e-300)
    if res <= STALL_RTOL * scale:
        return x, max_iter, res, lam, contacts
    if _free_rigid_motion(scene, x, t, contacts, C):
        raise NotConverged(f"static solve did not converge: {_SINGULAR}")
    raise NotConverged(
        f"static solve did not converge in {max_iter} Newton iterations (largest unbalanced force "
        f"{res:.3g} N)",
        SMALLER_STEPS,
    )


def _crawl_rate(history: list[float], left: int, target: float) -> float:
    """The best rate of a crawl, or 0 when the unbalanced forces ``history`` [N] do not crawl: they
    fell at each of the last :data:`CRAWL_ITERATIONS` iterations, no faster at the last than at the
    first of them (a Newton solve that speeds up on its way to quadratic convergence does not
    crawl), and the best of those rates kept up for ``left`` more iterations does not bring the
    last one down to ``target`` [N]."""
    if len(history) <= CRAWL_ITERATIONS or history[-1] <= target:
        return 0.0
    recent = np.asarray(history[-CRAWL_ITERATIONS - 1 :])
    rates = recent[1:] / recent[:-1]
    if not (rates < 1.0).all() or rates[-1] < rates[0]:
        return 0.0  # another merit accepted a step, or the solve is speeding up
    best = float(rates.min())
    return best if history[-1] * best**left > target else 0.0


def _follow_negative_curvature(
    scene: Scene,
    x: NDArray[np.float64],
    d: NDArray[np.float64],
    t: float,
    contacts: tuple,
    L: float,
) -> tuple[NDArray[np.float64], float]:
    """The point ``x + g d`` (g = 1, 2, 4, ...) of lowest potential energy, the first rise ending
    the search, for a full step ``d`` accepted at ``x + d`` that was solved with a shifted,
    indefinite Newton matrix. Returns (that point, g).

    Along a direction of negative curvature (a body tipping over on the few nodes it stands on)
    the shifted matrix allows only a step of about the unbalanced force over the shift, and the
    tipping then grows by ~15 % per iteration: dozens of iterations before the body reaches the
    node that stops it. The potential is exact for such conservative scenes, so following the
    step while it falls is safe; steps stay within the line search's cap (a tenth of the body's
    size) and :data:`NEGATIVE_CURVATURE_MAX_GROWTH`.
    """
    best, grown = x + d, 1.0
    e_best = scene.energy(best, t, contacts)
    g = 2.0
    step_max = float(np.abs(d).max())
    while g <= NEGATIVE_CURVATURE_MAX_GROWTH and g * step_max <= 0.1 * L:
        xg = x + g * d
        if not valid(scene.body, xg):
            break
        e = scene.energy(xg, t, contacts)
        if not e < e_best:
            break
        best, e_best, grown = xg, e, g
        g *= 2.0
    return best, grown


def climbs(history: list[float], plain: list[bool]) -> bool:
    """Whether the unbalanced forces ``history`` [N] rose at each of the last
    :data:`CLIMB_ITERATIONS` iterations, each after a plain step: ``plain[i]`` says whether the
    step from ``history[i]`` to ``history[i + 1]`` was a full Newton step on a positive definite,
    unshifted matrix."""
    if len(history) <= CLIMB_ITERATIONS:
        return False
    recent = np.asarray(history[-CLIMB_ITERATIONS - 1 :])
    steps = plain[len(history) - CLIMB_ITERATIONS - 1 : len(history) - 1]
    return len(steps) == CLIMB_ITERATIONS and all(steps) and bool((np.diff(recent) > 0.0).all())


def stalls(history: list[float], patience: int) -> bool:
    """Whether none of the last ``patience`` unbalanced forces of ``history`` [N] fell below the
    lowest before them: the iterates wander without balancing (an object sliding out of fingers
    that cannot hold it, each step taken for the energy it frees while the forces grow)."""
    return len(history) > patience and min(history[-patience:]) >= min(history[:-patience])


def cycle_period(history: list[float]) -> int:
    """The period (2-4) with which the last values of ``history`` repeat, twice in a row, to
    :data:`CYCLE_RTOL`; 0 if they do not."""
    for p in (2, 3, 4):
        if len(history) >= 2 * p and all(
            abs(history[-1 - k] - history[-1 - k - p]) <= CYCLE_RTOL * history[-1 - k] for k in range(p)
        ):
            return p
    return 0


def _free_rigid_motion(scene: Scene, x: NDArray[np.float64], t: float, contacts: tuple, C) -> bool:
    """Whether a rigid translation or rotation of the body meets (almost) no stiffness at ``x``:
    nothing holds the body in place, which is why Newton could not converge. (Singular Newton
    systems are used on the way, e.g. before the body touches the table, so this is asked only
    once Newton has failed.)"""
    if C is not None:
        return False
    return _rigid_motion_free((-scene.jacobian(x, t, contacts)).tocsr(), x)
