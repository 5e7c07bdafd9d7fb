"""Static equilibrium of a scene: Newton's method with a sparse Jacobian and a line search.

The equilibrium is the minimum of the total potential (elastic + gravity + contact penalty + the
tangential springs of sticking contacts). Friction is advanced incrementally: Newton solves with the
contact anchors held fixed (stick predictor); then anchors whose spring exceeds the Coulomb limit are
dragged back onto it (slip return, :meth:`Scene.update_contacts`) and Newton runs again, until the
anchors no longer move.

Linear constraints ``C (x - x_ref) = 0`` (e.g. fixing the rigid motions a frictionless set-up leaves
free) are enforced with Lagrange multipliers in a saddle-point system.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import backend
from softgrasp.physics.body import Body
from softgrasp.errors import NotConverged, SimulationUnstable
from softgrasp.linalg import pardiso
from softgrasp.linalg.solve import (
    _SINGULAR,
    SolverCache,
    _rigid_motion_free,
    assembly_threads,
    solve_newton_system,
)
from softgrasp.sim.scene import Scene, State

#: Newton's progress at DEBUG level: each iteration's unbalanced force and accepted step, each friction pass.
log = logging.getLogger(__name__)

__all__ = [
    "StaticInfo",
    "solve_static",
    "solve_increment",
    "rigid_constraints",
    "extrapolated",
    "MAX_HALVINGS",
]

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
#: it) is only kicked off its balance. The 18 233-node sphere's settle, balanced to 1.2e-6 at its
#: 9th iteration, was followed 4x, then 16x, and wandered for 47 iterations or found no rest in
#: 60; with the plain shifted step it is balanced at the 9th.
FOLLOW_RTOL = 1e-4
#: Longest multiple of an indefinite matrix's shifted step that :func:`_follow_negative_curvature`
#: tries (in doublings).
NEGATIVE_CURVATURE_MAX_GROWTH = 1024.0
#: How often :func:`solve_increment` halves a load increment that does not converge.
MAX_HALVINGS = 4
#: Newton gives up after this many consecutive accepted steps no longer than ``CREEP_ALPHA`` of
#: the Newton step that reduced the largest unbalanced force by less than 1 %.
CREEP_ITERATIONS = 6
CREEP_ALPHA = 1.0 / 64
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
#: Largest nodal displacement of the forward difference in the exact Newton product, as a fraction
#: of the body's size. Its truncation error relative to the product is about the step over the
#: shallowest contact depth (1e-5 at 0.1 mm on a 128 mm body), its round-off about 1e-16 times the
#: inverse (1e-11): both far below the Newton solves' forcing term (<= 1e-4). One contact
#: evaluation per product instead of the two of a central difference.
FD_STEP = 1e-8


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


def _valid(body: Body, x: NDArray[np.float64]) -> bool:
    """Whether every tet of ``body`` has a positive signed volume at ``x`` (the compiled count:
    the line search asks at every trial step)."""
    from softgrasp.physics.volume import count_inverted

    return count_inverted(x, body.mesh.tets) == 0


def _residual(scene: Scene, x, t, contacts, C, lam) -> NDArray[np.float64]:
    r = scene.static_forces(x, t, contacts).ravel()
    return r - C.T @ lam if C is not None else r


@dataclass(frozen=True)
class _BodyPattern:
    """Where the entries of a body's Jacobian pattern sit in its CSR data.

    Attributes
    ----------
    keys: sorted keys ``3N row + col`` of the scalar entries, in CSR data order, (nnz,).
    diagonal: the data positions of each node's diagonal 3x3 block, row by row, (N, 9).
    """

    keys: NDArray[np.int64]
    diagonal: NDArray[np.int64]


_PATTERNS: weakref.WeakKeyDictionary[Body, _BodyPattern] = weakref.WeakKeyDictionary()


def _body_pattern(body: Body) -> _BodyPattern:
    """The :class:`_BodyPattern` of ``body``'s Jacobian (built once, kept while the body lives)."""
    pat = _PATTERNS.get(body)
    if pat is None:
        J = body.internal_jacobian(np.asarray(body.mesh.points, dtype=np.float64))
        n = J.shape[0]
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(J.indptr))
        keys = rows * n + J.indices.astype(np.int64)
        i = 3 * np.arange(body.n_nodes, dtype=np.int64)
        a = np.arange(3)
        want = ((i[:, None, None] + a[None, :, None]) * n + i[:, None, None] + a[None, None, :]).reshape(
            -1, 9
        )
        diagonal = np.searchsorted(keys, want)
        if not np.array_equal(keys[np.minimum(diagonal, keys.size - 1)], want):
            raise AssertionError("a node without its diagonal block in the body's Jacobian pattern")
        pat = _PATTERNS[body] = _BodyPattern(keys, diagonal)
    return pat


def _add_into_pattern(
    pat: _BodyPattern, data: NDArray[np.float64], M: sp.spmatrix
) -> tuple[sp.csr_matrix, sp.csr_matrix | None]:
    """Add the entries of ``M`` that lie in the body's pattern to its CSR ``data`` (in place).
    Returns (those entries, the others or None) as sparse matrices."""
    M = sp.csr_matrix(M)
    M.sum_duplicates()
    n = M.shape[0]
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(M.indptr))
    cols = M.indices.astype(np.int64)
    keys = rows * n + cols
    pos = np.minimum(np.searchsorted(pat.keys, keys), pat.keys.size - 1)
    inside = pat.keys[pos] == keys
    data[pos[inside]] += M.data[inside]
    kept = sp.csr_matrix((M.data[inside], (rows[inside], cols[inside])), shape=M.shape)
    if inside.all():
        return kept, None
    out = ~inside
    return kept, sp.csr_matrix((M.data[out], (rows[out], cols[out])), shape=M.shape)


def _static_forces_of(inter, body: Body, t: float, st, x: NDArray[np.float64]) -> NDArray[np.float64]:
    return inter.static_forces(body, x, t, st)


def _newton_matrix(
    scene: Scene, x: NDArray[np.float64], t: float, contacts: tuple, L: float, threads: int = 1
) -> tuple[sp.csr_matrix, Callable[[NDArray[np.float64]], NDArray[np.float64]] | None]:
    """The Newton matrix A = -d f / d x as assembled (symmetric: interactions whose Jacobian is a
    symmetrised approximation contribute that), and, where there are such interactions, the
    product with the exact matrix: their part of ``A v`` replaced by a forward difference of their
    forces along v. (A Newton iteration with the symmetrised matrix converges only linearly,
    about tenfold per iteration; with the exact product, quadratically.)"""
    body = scene.body
    J = body.internal_jacobian(x, threads=threads)  # in the body's fixed pattern, data fresh
    pat = _body_pattern(body)
    data = J.data
    approx = []
    outside: list[sp.csr_matrix] = []
    # Each interaction's Jacobian is summed straight into the body pattern's data, in the
    # interactions' order (the same sums, entry by entry, as adding the sparse matrices), so
    # that every Newton matrix has one pattern: no sparse additions, and the factorisation's
    # analysis and its gather of the upper triangle are reused as they are.
    for inter, st in zip(scene.interactions, contacts, strict=True):
        diagonal = getattr(inter, "jacobian_diagonal", None)
        if diagonal is not None:
            nodes, blocks = diagonal(body, x, t, st)
            data[pat.diagonal[nodes]] += blocks.reshape(-1, 9)
            continue
        Ji = inter.jacobian(body, x, t, st)
        if not Ji.nnz:
            continue
        kept, rest = _add_into_pattern(pat, data, Ji)
        if not getattr(inter, "symmetric_jacobian", True):
            # Only a preconditioner now: kept inside the body's pattern, so that the factorisation's
            # analysis stays valid as contacts come and go.
            pinned = getattr(inter, "pinned_static_forces", None)
            if pinned is not None:
                forces_at = pinned(body, x, t, st)
            else:
                forces_at = functools.partial(_static_forces_of, inter, body, t, st)
            approx.append((forces_at, kept))
        elif rest is not None:
            outside.append(rest)  # couples nodes that no edge or tet joins
    np.negative(data, out=data)
    A = J
    for M in outside:
        A = A - M
    A = A.tocsr()
    if not approx:
        return A, None
    return A, _ExactProduct(A, approx, x, L)


class _ExactProduct:
    """The product with the exact Newton matrix: ``matrix @ v`` with the approximated
    interactions' part of it replaced by a forward difference of their forces along v, i.e.
    ``correction(v, matrix @ v)`` (a solver with a faster product of ``matrix`` applies that and
    passes it to :meth:`correction`)."""

    def __init__(self, A: sp.csr_matrix, approx: list, x: NDArray[np.float64], L: float) -> None:
        self.matrix = A
        self._approx = approx
        self._x = x
        self._L = L
        self._base: list[NDArray[np.float64]] = []

    def correction(self, v: NDArray[np.float64], out: NDArray[np.float64]) -> NDArray[np.float64]:
        """Add to ``out`` (``matrix @ v``) what turns it into the exact product: for each
        approximated interaction, its matrix part taken back out and the forward difference of its
        forces along v put in. Returns ``out``."""
        V = v.reshape(-1, 3)
        vmax = float(np.abs(V).max())
        if vmax == 0:
            return out
        h = FD_STEP * self._L / vmax
        if not self._base:
            self._base.extend(forces_at(self._x) for forces_at, _ in self._approx)
        for (forces_at, Ji), f0 in zip(self._approx, self._base, strict=True):
            out += Ji @ v - ((forces_at(self._x + h * V) - f0) / h).ravel()
        return out

    def __call__(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.correction(v, self.matrix @ v)


def _newton(
    scene: Scene,
    x: NDArray[np.float64],
    t: float,
    contacts: tuple,
    C: sp.csr_matrix | None,
    rtol: float,
    max_iter: int,
    cache: SolverCache,
) -> tuple[NDArray[np.float64], int, float, NDArray[np.float64], tuple]:
    """Newton's method on the unbalanced forces, globalised on their norm.

    Contact forces are not all exact gradients (fingertip friction, the patch rule's weights), so a
    step is accepted when it reduces the 2-norm of the unbalanced forces or the potential energy;
    when no step length does either, the stiffness diagonal is added (Levenberg-Marquardt) until one
    does.
    """
    body = scene.body
    L = float(np.ptp(body.mesh.points, axis=0).max())
    lam = np.zeros(0 if C is None else C.shape[0])
    grav = np.abs(body.mass[:, None] * body.gravity[None, :]).max()
    shift = 0.0
    creep, last_res = 0, np.inf
    history: list[float] = []  # the unbalanced force [N] at the start of each iteration
    start = contacts
    for it in range(1, max_iter + 1):
        f_int = body.internal_forces(x)
        f = scene.static_forces(x, t, contacts, internal=f_int)
        scale = max(np.abs(f_int).max(), np.abs(f - f_int).max(), grav, 1e-300)
        if C is None and (res := float(np.abs(f).max())) <= rtol * scale:
            return x, it - 1, res, lam, contacts  # balanced already: no system to solve
        A, exact = _newton_matrix(scene, x, t, contacts, L, assembly_threads(3 * body.n_nodes, cache))
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
                if not _valid(body, xn):
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
        if period := _cycle(history):
            if res <= STALL_RTOL * scale:
                return x, it, res, lam_new, contacts  # balanced to 1e-6 of the largest force: accept
            if _free_rigid_motion(scene, x, t, contacts, C):
                raise NotConverged(f"static solve did not converge: {_SINGULAR}")
            raise NotConverged(
                f"static solve cycles (the same {period} iterates over and over, largest unbalanced force "
                f"{res:.3g} N); use smaller load steps"
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
        f"{res:.3g} N); use smaller load steps"
    )


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
        if not _valid(scene.body, xg):
            break
        e = scene.energy(xg, t, contacts)
        if not e < e_best:
            break
        best, e_best, grown = xg, e, g
        g *= 2.0
    return best, grown


def _cycle(history: list[float]) -> int:
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
        the last increments extrapolated); ignored if it inverts a tet. The contact states are
        still ``state``'s, so the rest found is the one found from ``state.x`` except where a
        contact pair starts during the step: it is anchored where the iterates first touch it
        (the planner's set-points moved by ~4e-6 relative).

    Returns
    -------
    (State at rest with updated friction anchors and v = 0, StaticInfo)

    Raises
    ------
    NotConverged: Newton stalled, or the body is not held (singular stiffness).
    SimulationUnstable: the configuration is invalid (inverted tets) at the start.

    NumPy's BLAS runs on one thread meanwhile (:func:`~softgrasp.linalg.pardiso.blas_one_thread`, as
    the planner holds it for a whole plan): the 27 749-node settle called alone took 18.2 s with
    OpenBLAS's threads competing with the multigrid products' and PARDISO's.
    """
    cache = cache if cache is not None else SolverCache()
    with pardiso.blas_one_thread(), _force_threads(scene.body, cache):
        return _solve_static(
            scene, state, t, constraints, x_ref, rtol, max_iter, max_friction_passes, cache, guess
        )


def _force_threads(body: Body, cache: SolverCache) -> contextlib.AbstractContextManager:
    """Numba's threads for a large body's force evaluations during a static solve (its sums run
    on the calling thread's: :meth:`softgrasp.physics.body.Body.internal_forces`): the assembly's, the idle
    cores on the multigrid path (:func:`~softgrasp.linalg.solve.assembly_threads`). Nothing is
    changed for smaller bodies, or in a forked child whose Numba threads were lost."""
    from softgrasp.physics.forces_compiled import PARTITIONED_MIN_NODES
    from softgrasp.linalg.sparse import _Threads

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
) -> tuple[State, StaticInfo]:
    tt = state.t if t is None else float(t)
    x = np.array(state.x, dtype=np.float64)
    if not _valid(scene.body, x):
        raise SimulationUnstable("static solve started from a configuration with inverted tets")
    if guess is not None and _valid(scene.body, guess):
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
    total_it = 0
    for p in range(1, max_friction_passes + 1):
        x, it, res, lam, contacts = _newton(scene, x, tt, contacts, C, rtol, max_iter, cache)
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
            return State(x, zeros, tt, contacts), StaticInfo(total_it, p, float(np.abs(f).max()), -lam)
    raise NotConverged(
        f"friction did not settle in {max_friction_passes} stick/slip passes; use smaller load steps"
    )


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
                raise NotConverged(
                    f"load increment to t = {t:.6g} did not converge even when split into {n} parts: {exc}"
                ) from exc
    raise AssertionError("unreachable")  # pragma: no cover
