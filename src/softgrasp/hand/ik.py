"""Inverse kinematics of one finger: reaching a point, tracking it, following a straight line.

Each is the clamped WDLS descent of :mod:`softgrasp.hand.descent` on the finger's chain with the
palm fixed (:func:`softgrasp.hand.wdls.limited_step` steps, joint weights, a halving line search).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand.kinematics import FingerChain, HandModel, _kinematics, chain_stack

__all__ = ["LINE_TOLERANCE", "solve_ik", "track", "follow_line"]

#: Largest distance [m] :func:`follow_line` lets the fingertip stray from its commanded line point.
LINE_TOLERANCE = 5e-4

#: Largest Cartesian correction [m] one IK iteration aims at (longer errors are shortened).
MAX_CARTESIAN_STEP = 0.01

#: Step halvings of the IK line search before an iteration counts as "no progress".
MAX_HALVINGS = 30

#: An IK attempt stops when its error fell by less than this fraction over
#: :data:`STALL_WINDOW` iterations (slow creep towards the closest point of an unreachable target).
STALL_FRACTION = 1e-3
STALL_WINDOW = 10

#: Extra random starting configurations tried by :func:`solve_ik` after ``q0`` and mid-range.
IK_RESTARTS = 6

_EYE = np.eye(3)[None]
_ORIGIN = np.zeros((1, 3))


def _descend(
    chain: FingerChain,
    target: NDArray[np.float64],
    q: NDArray[np.float64],
    w: NDArray[np.float64],
    damping: float,
    tol: float,
    max_iter: int,
) -> tuple[NDArray[np.float64], float]:
    """Clamped WDLS iterations from ``q`` (inside the limits, joint weights ``w``) towards the
    fingertip ``target`` (palm frame); returns the last ``q`` and its error [m]."""
    from softgrasp.hand import descent  # compiled: loaded at the first solve
    from softgrasp.hand.wdls import LIMIT_EPS

    out = descent.solve(
        chain_stack((chain,)),
        target[None],
        _EYE,
        _ORIGIN,
        q[None],
        winv=1.0 / w,
        palm_fixed=True,
        reach_tol=tol,
        max_iter=max_iter,
        max_step=MAX_CARTESIAN_STEP,
        damping=damping,
        stall_fraction=STALL_FRACTION,
        stall_window=STALL_WINDOW,
        max_halvings=MAX_HALVINGS,
        limit_eps=LIMIT_EPS,
    )
    return out.q[0], float(out.error[0])


def _point(v: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(v, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ConfigError(f"{what} must be 3 finite coordinates [m]; got shape {p.shape}")
    return p


def _mm(p: NDArray[np.float64]) -> str:
    """``(x, y, z)`` in mm with one decimal, for messages."""
    return "(" + ", ".join(f"{1e3 * v:.1f}" for v in p) + ")"


def _ik_options(
    model: HandModel, finger: str, q0: ArrayLike, damping: float, weights: ArrayLike | None
) -> tuple[FingerChain, NDArray[np.float64], NDArray[np.float64], float]:
    from softgrasp.hand.wdls import _weights

    chain, q = model._q(finger, q0)
    lam = float(damping)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ConfigError(f"damping = {damping} is invalid: it must be finite and >= 0")
    return chain, np.clip(q, chain.lower, chain.upper), _weights(weights, chain.dof), lam


def solve_ik(
    model: HandModel,
    finger: str,
    target: ArrayLike,
    q0: ArrayLike,
    *,
    damping: float = 1e-3,
    weights: ArrayLike | None = None,
    tol: float = 1e-5,
    max_iter: int = 200,
) -> NDArray[np.float64]:
    """Independent joint vector placing the ``finger``'s fingertip centre at ``target`` [m].

    Iterates WDLS steps (:func:`softgrasp.hand.descent.solve` with the palm fixed, joint weights
    ``weights``, default 1) on the fingertip error, each aimed at most :data:`MAX_CARTESIAN_STEP`
    along the error and shortened by halving until the error decreases. Joint limits: ``q0`` is first clipped into the limits;
    at every iteration a joint sitting at a limit whose step would push it further out is removed
    from the step (infinite weight) and the step recomputed with the other joints; the trial
    ``q`` is clipped into the limits, so the result never leaves them. Iterations stop at an error
    ``<= tol`` [m], after ``max_iter`` iterations, when no shortened step decreases the error, or
    when the error fell by less than :data:`STALL_FRACTION` over :data:`STALL_WINDOW` iterations.
    If ``q0`` fails, the mid-range configuration and :data:`IK_RESTARTS` fixed pseudo-random ones
    are tried. :class:`InfeasibleGrasp` names the finger and the closest distance reached.
    """
    chain, q, w, lam = _ik_options(model, finger, q0, damping, weights)
    p = _point(target, "target")
    if not (math.isfinite(tol) and tol > 0.0):
        raise ConfigError(f"tol = {tol} m is invalid: it must be finite and > 0")
    if int(max_iter) != max_iter or max_iter < 1:
        raise ConfigError(f"max_iter = {max_iter} must be an integer >= 1")
    rng = np.random.default_rng(0)
    seeds = [q, 0.5 * (chain.lower + chain.upper)]
    seeds += list(rng.uniform(chain.lower, chain.upper, size=(IK_RESTARTS, chain.dof)))
    best = math.inf
    for seed in seeds:
        q_end, err = _descend(chain, p, seed, w, lam, tol, int(max_iter))
        if err <= tol:
            return q_end
        best = min(best, err)
    raise InfeasibleGrasp(
        f"the {finger} fingertip cannot reach target {_mm(p)} mm: closest {1e3 * best:.3f} mm away"
    )


def track(
    model: HandModel,
    finger: str,
    target: ArrayLike,
    q: ArrayLike,
    *,
    iterations: int = 10,
    damping: float = 1e-3,
) -> NDArray[np.float64]:
    """Joint vector moving the fingertip from its posture ``q`` towards ``target`` (palm frame):
    up to ``iterations`` limit-clamped WDLS iterations, no restarts, so successive calls give a
    continuous motion (a Cartesian controller's inner loop). Never leaves the joint limits."""
    chain, q0, w, lam = _ik_options(model, finger, q, damping, None)
    return _descend(chain, _point(target, "target"), q0, w, lam, 1e-7, int(iterations))[0]


def follow_line(
    model: HandModel,
    finger: str,
    q0: ArrayLike,
    start: ArrayLike,
    end: ArrayLike,
    steps: int,
    *,
    damping: float = 1e-3,
    weights: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Joint trajectory ``(steps + 1, dof)`` moving the fingertip straight from ``start`` to ``end``.

    Row 0 is ``q0`` (clipped into the limits) if its fingertip is within 1e-6 m of ``start``,
    otherwise :func:`solve_ik` from ``q0`` to ``start``. Row ``k`` tracks the line point
    ``start + k / steps (end - start)`` by limit-clamped WDLS iterations (as :func:`solve_ik`,
    without restarts, so the trajectory is continuous) from row ``k - 1``. If the fingertip ends
    a row more than :data:`LINE_TOLERANCE` (0.5 mm) from its commanded point (so possibly off
    the line), :class:`InfeasibleGrasp` names the finger and the step.
    """
    chain, q, w, lam = _ik_options(model, finger, q0, damping, weights)
    a = _point(start, "start")
    b = _point(end, "end")
    if isinstance(steps, bool) or int(steps) != steps or steps < 1:
        raise ConfigError(f"steps = {steps} must be an integer >= 1")
    steps = int(steps)
    if np.linalg.norm(_kinematics(chain, q, False)[0] - a) > 1e-6:
        q = solve_ik(model, finger, a, q, damping=lam, weights=w, tol=1e-7)
    out = np.empty((steps + 1, chain.dof))
    out[0] = q
    for k in range(1, steps + 1):
        point = a + (k / steps) * (b - a)
        q, err = _descend(chain, point, q, w, lam, 1e-7, 50)
        if err > LINE_TOLERANCE:
            raise InfeasibleGrasp(
                f"the {finger} fingertip cannot follow the line from "
                f"{_mm(a)} to {_mm(b)} mm: "
                f"{1e3 * err:.2f} mm off at step {k}/{steps}"
            )
        out[k] = q
    return out
