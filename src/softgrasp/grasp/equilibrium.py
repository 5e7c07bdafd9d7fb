"""Static equilibrium of a grasped object (paper Eq. 21-22) and friction-cone feasibility.

The object of mass ``m`` is held by ``k`` point contacts. Contact ``j`` is at ``p_j`` with unit
*inward* normal ``n_j`` (pointing into the object: the direction the fingertip pushes) and applies
the force ``f_j = f_n,j n_j + f_t,j`` ON the object. The equilibrium conditions are

* force balance (Eq. 21):   sum_j f_j + m g = 0,
* torque balance about the centre of mass ``c`` (Eq. 22):   sum_j (p_j - c) x f_j = 0,

with Coulomb's friction cone |f_t,j| <= mu f_n,j, linearised conservatively by the m-gon
inscribed in the circle of radius mu f_n,j:

    f_t,j = sum_k beta_jk d_jk,   beta_jk >= 0,   sum_k beta_jk <= mu f_n,j.

Tangent basis convention (:func:`friction_cone_edges`): for each normal ``n`` the helper axis
``a`` is the world axis ``e_i`` with the smallest ``|n_i|`` (exact ties go to the HIGHEST index
``i``); ``t1 = (a - (a.n) n) / |a - (a.n) n|``, ``t2 = n x t1`` (so ``t1 x t2 = n``), and the cone
edges are ``d_k = cos(2 pi k / m) t1 + sin(2 pi k / m) t2`` for ``k = 0 .. m-1``. A horizontal
normal (``n_z == 0``) therefore always gets ``t1 = e_z``: ``d_0`` points straight up and
``d_{m/2}`` straight down. The basis is well conditioned (``|a - (a.n) n| >= sqrt(2/3)``) but, like
any per-normal rule, not equivariant under arbitrary rotations: rotating a grasp may turn its
m-gons about their normals (by at most ``pi/m`` in effect), which changes m-gon results within
the linearisation error.

Linear programs are solved with :func:`scipy.optimize.linprog` (HiGHS) on rows scaled by ``m|g|``
(forces) and ``m|g| L`` (torques, ``L = max_j |p_j - c|``). SI units throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linprog

from softgrasp.errors import ConfigError, InfeasibleGrasp, NotConverged

__all__ = [
    "squeeze_utilisation",
    "wrench_residual",
    "friction_cone_edges",
    "Feasibility",
    "friction_feasibility",
    "minimum_normal_forces",
]

#: Allowed deviation of a normal's length from 1.
UNIT_TOL = 1e-6

_LP_OPTIONS = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}


# --------------------------------------------------------------------------------------------
# validation helpers (shared with closure.py)
# --------------------------------------------------------------------------------------------


def _vectors(a: ArrayLike, name: str, k: int | None = None) -> NDArray[np.float64]:
    """A finite (k, 3) float array, or ConfigError naming ``name``."""
    v = np.asarray(a, dtype=np.float64)
    if v.ndim == 1 and v.shape == (3,) and k in (None, 1):
        v = v[None, :]
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ConfigError(f"{name} has shape {v.shape}: it must be (k, 3) with k >= 1")
    if k is not None and v.shape[0] != k:
        raise ConfigError(f"{name} has {v.shape[0]} rows but there are {k} contacts")
    if not np.all(np.isfinite(v)):
        raise ConfigError(f"{name} contains NaN or inf")
    return v


def _unit_normals(normals: ArrayLike, k: int | None = None) -> NDArray[np.float64]:
    n = _vectors(normals, "normals", k)
    length = np.linalg.norm(n, axis=1)
    bad = np.flatnonzero(np.abs(length - 1.0) > UNIT_TOL)
    if bad.size:
        j = int(bad[0])
        raise ConfigError(
            f"normals[{j}] has length {length[j]:.9g}: normals must be unit vectors (within {UNIT_TOL})"
        )
    return n / length[:, None]


def _point3(a: ArrayLike, name: str) -> NDArray[np.float64]:
    v = np.asarray(a, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"{name} = {a!r} is invalid: it must be a finite 3-vector")
    return v


def _number(value: float, what: str, unit: str, *, strict: bool) -> float:
    """``value`` as a finite float, > 0 (strict) or >= 0, else a ConfigError naming ``what``."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} = {value!r} is invalid: it must be a number") from None
    if not (math.isfinite(x) and (x > 0.0 if strict else x >= 0.0)):
        bound = "> 0" if strict else ">= 0"
        raise ConfigError(f"{what} = {value}{unit} is invalid: it must be finite and {bound}")
    return x


def _mu(mu: float) -> float:
    return _number(mu, "friction coefficient mu", "", strict=False)


def _mass(mass: float) -> float:
    return _number(mass, "mass", " kg", strict=True)


def _edges_count(m: int) -> int:
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 3:
        raise ConfigError(f"number of friction-cone edges m = {m!r} is invalid: it must be an integer >= 3")
    return int(m)


def _length_scale(r: NDArray[np.float64]) -> float:
    L = float(np.max(np.linalg.norm(r, axis=1)))
    return L if L > 0.0 else 1.0


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


def wrench_residual(
    points: ArrayLike,
    forces: ArrayLike,
    com: ArrayLike,
    mass: float,
    gravity: ArrayLike = (0.0, 0.0, -9.81),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Residuals of Eq. 21-22 for contact forces ``forces`` (k, 3) [N] ON the object at ``points``.

    Returns ``(sum_j f_j + m g, sum_j (p_j - com) x f_j)``: the force residual (3,) [N] and the
    torque residual about the centre of mass (3,) [N m]. Both vanish at static equilibrium.
    """
    p = _vectors(points, "points")
    f = _vectors(forces, "forces", p.shape[0])
    c = _point3(com, "com")
    g = _point3(gravity, "gravity")
    m = _mass(mass)
    force = f.sum(axis=0) + m * g
    torque = np.cross(p - c, f).sum(axis=0)
    return force, torque


def friction_cone_edges(normals: ArrayLike, m: int = 8) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Tangent bases and unit cone-edge directions of the m-gon friction-cone linearisation.

    Parameters
    ----------
    normals:
        Unit inward contact normals, shape ``(k, 3)``.
    m:
        Number of edges (>= 3).

    Returns
    -------
    tangents:
        ``(k, 2, 3)``: ``tangents[j, 0] = t1_j`` and ``tangents[j, 1] = t2_j = n_j x t1_j``
        (basis convention in the module docstring).
    edges:
        ``(k, m, 3)`` unit tangents ``d_jk = cos(2 pi k/m) t1_j + sin(2 pi k/m) t2_j``. The friction
        forces ``sum_k beta_jk d_jk`` with ``sum_k beta_jk <= mu f_n`` fill the m-gon inscribed in
        the circle of radius ``mu f_n``: a conservative (inner) approximation of Coulomb's cone.
    """
    n = _unit_normals(normals)
    m = _edges_count(m)
    axis = 2 - np.argmin(np.abs(n)[:, ::-1], axis=1)  # first minimum of the reversed row: ties -> highest
    a = np.eye(3)[axis]
    t1 = a - np.einsum("ij,ij->i", a, n)[:, None] * n
    t1 /= np.linalg.norm(t1, axis=1)[:, None]  # |t1| >= sqrt(2/3) before normalising
    t2 = np.cross(n, t1)
    ang = 2.0 * np.pi * np.arange(m) / m
    edges = np.cos(ang)[None, :, None] * t1[:, None, :] + np.sin(ang)[None, :, None] * t2[:, None, :]
    return np.stack([t1, t2], axis=1), edges


@dataclass(frozen=True)
class Feasibility:
    """Outcome of :func:`friction_feasibility`.

    Attributes
    ----------
    feasible:
        The load can be balanced with friction inside the linearised cones (``utilisation <= 1``).
    utilisation:
        Smallest ``rho`` such that friction inside the linearised cones of coefficient ``rho mu``
        balances the load; ``inf`` when no ``rho`` works.
    margin:
        ``1 - utilisation`` (``>= 0`` iff feasible; ``-inf`` when no ``rho`` works).
    tangential:
        The friction forces found, ``(k, 3)`` [N] (zeros when no ``rho`` works).
    force_residual_N, torque_residual_Nm:
        Norms of the Eq. 21-22 residuals with those friction forces [N], [N m].
    """

    feasible: bool
    utilisation: float
    margin: float
    tangential: NDArray[np.float64]
    force_residual_N: float
    torque_residual_Nm: float


def _setup(points, normals, mu, com, mass, gravity, m):  # type: ignore[no-untyped-def]
    p = _vectors(points, "points")
    n = _unit_normals(normals, p.shape[0])
    mu = _mu(mu)
    c = _point3(com, "com")
    g = _point3(gravity, "gravity")
    mass = _mass(mass)
    _, d = friction_cone_edges(n, m)
    r = p - c
    F = mass * float(np.linalg.norm(g))
    F = F if F > 0.0 else 1.0
    L = _length_scale(r)
    return p, n, mu, c, g, mass, d, r, F, L


def friction_feasibility(
    points: ArrayLike,
    normals: ArrayLike,
    normal_forces: ArrayLike,
    mu: float,
    com: ArrayLike,
    mass: float,
    gravity: ArrayLike = (0.0, 0.0, -9.81),
    m: int = 8,
) -> Feasibility:
    """Can friction balance the load with the given contacts and normal forces? (Eq. 21-22).

    With fixed contact points, unit inward normals and normal-force magnitudes ``f_n,j >= 0`` [N],
    solves the LP: minimise ``rho`` over ``beta_jk >= 0``, ``rho >= 0`` subject to Eq. 21-22 with
    ``f_j = f_n,j n_j + sum_k beta_jk d_jk`` and ``sum_k beta_jk <= rho mu f_n,j``.

    Raises
    ------
    ConfigError
        Invalid shapes or values.
    NotConverged
        HiGHS stopped without an optimum or a proof of infeasibility.
    """
    p, n, mu, c, g, mass, d, r, F, L = _setup(points, normals, mu, com, mass, gravity, m)
    k, mm = d.shape[0], d.shape[1]
    fn = np.asarray(normal_forces, dtype=np.float64)
    if fn.shape != (k,):
        raise ConfigError(f"normal_forces has shape {fn.shape}: it must be ({k},), one per contact")
    if not np.all(np.isfinite(fn) & (fn >= 0.0)):
        raise ConfigError(f"normal_forces = {fn} is invalid: they must be finite and >= 0")

    fnormal = fn[:, None] * n
    rhs_f = -(fnormal.sum(axis=0) + mass * g) / F
    rhs_t = -np.cross(r, fnormal).sum(axis=0) / (F * L)
    # variables x = [b (k*m) in units of F, rho]
    A_eq = np.zeros((6, k * mm + 1))
    A_eq[:3, :-1] = d.reshape(-1, 3).T
    A_eq[3:, :-1] = np.cross(r[:, None, :], d).reshape(-1, 3).T / L
    b_eq = np.concatenate([rhs_f, rhs_t])
    A_ub = np.zeros((k, k * mm + 1))
    for j in range(k):
        A_ub[j, j * mm : (j + 1) * mm] = 1.0
    A_ub[:, -1] = -mu * fn / F
    cost = np.zeros(k * mm + 1)
    cost[-1] = 1.0
    res = _linprog(cost, A_ub, np.zeros(k), A_eq, b_eq)
    if res.status == 2:
        ft = np.zeros((k, 3))
        rho = math.inf
    elif res.status == 0:
        beta = res.x[:-1].reshape(k, mm) * F
        ft = np.einsum("jk,jki->ji", beta, d)
        # rho is irrelevant where mu f_n = 0; report the tightest value the solution needs
        cap = mu * fn
        used = beta.sum(axis=1)
        active = cap > 0.0
        rho = float(np.max(used[active] / cap[active])) if np.any(active) else 0.0
    else:
        raise NotConverged(f"friction feasibility LP failed: {res.message}")
    fres, tres = wrench_residual(p, fnormal + ft, c, mass, g)
    return Feasibility(
        feasible=bool(rho <= 1.0),
        utilisation=rho,
        margin=1.0 - rho,
        tangential=ft,
        force_residual_N=float(np.linalg.norm(fres)),
        torque_residual_Nm=float(np.linalg.norm(tres)),
    )


def _holding_system(n, d, r, L: float, weight, mu: float, extra: int, torsion=None):  # type: ignore[no-untyped-def]
    """Eq. 21-22 and the linearised cones for unknown normal forces, in units of the weight.

    Variables ``x = [f_n (k), beta (k*m), extra...]``: equality rows ``A_eq x = b_eq`` (forces,
    then torques about the centre of mass over the length scale L) and cone rows
    ``sum_k beta_jk - mu f_n,j <= 0``. ``weight``: m g in units of the force scale.

    ``torsion`` kappa ``(k,)`` [m] (soft-finger contacts): ``2 k`` more variables after the cones',
    the moments ``tau+_j, tau-_j >= 0`` about each normal, and the cone rows become the linearised
    limit surface ``sum_k beta_jk + (mu / kappa_j)(tau+_j + tau-_j) - mu f_n,j <= 0``."""
    k, mm = d.shape[0], d.shape[1]
    spin = 0 if torsion is None else 2 * k
    nv = k + k * mm + spin + extra
    A_eq = np.zeros((6, nv))
    A_eq[:3, :k] = n.T
    A_eq[:3, k : k + k * mm] = d.reshape(-1, 3).T
    A_eq[3:, :k] = np.cross(r, n).T / L
    A_eq[3:, k : k + k * mm] = np.cross(r[:, None, :], d).reshape(-1, 3).T / L
    b_eq = np.concatenate([-np.asarray(weight), np.zeros(3)])
    cone = np.zeros((k, nv))
    cone[:, :k] = -mu * np.eye(k)
    for j in range(k):
        cone[j, k + j * mm : k + (j + 1) * mm] = 1.0
    if torsion is not None:
        t0 = k + k * mm
        for j, kappa in enumerate(np.asarray(torsion, dtype=np.float64)):
            A_eq[3:, t0 + j] = n[j] / L
            A_eq[3:, t0 + k + j] = -n[j] / L
            if kappa > 0 and mu > 0:
                cone[j, [t0 + j, t0 + k + j]] = mu / kappa
            else:  # no patch or no friction: no moment
                A_eq[3:, [t0 + j, t0 + k + j]] = 0.0
    return A_eq, b_eq, cone


def _linprog(cost, A_ub, b_ub, A_eq, b_eq):  # type: ignore[no-untyped-def]
    """HiGHS on non-negative variables."""
    return linprog(
        cost,
        A_ub=A_ub,
        b_ub=b_ub,
        A_eq=A_eq,
        b_eq=b_eq,
        bounds=(0, None),
        method="highs",
        options=_LP_OPTIONS,
    )


def minimum_normal_forces(
    points: ArrayLike,
    normals: ArrayLike,
    mu: float,
    com: ArrayLike,
    mass: float,
    gravity: ArrayLike = (0.0, 0.0, -9.81),
    m: int = 8,
    torsion: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Normal-force magnitudes (k,) [N] of smallest sum that hold the object (Eq. 21-22).

    LP over ``f_n,j >= 0`` and ``beta_jk >= 0`` with ``sum_k beta_jk <= mu f_n,j`` (friction in
    the linearised cones of :func:`friction_cone_edges`), minimising ``sum_j f_n,j``; with
    ``torsion`` kappa ``(k,)`` [m], soft-finger contacts (:func:`_holding_system`).

    Raises
    ------
    InfeasibleGrasp
        No such forces exist (e.g. ``mu = 0`` with all contacts on a horizontal great circle).
    ConfigError
        Invalid shapes or values.
    NotConverged
        HiGHS stopped without an optimum or a proof of infeasibility.
    """
    p, n, mu, c, g, mass, d, r, F, L = _setup(points, normals, mu, com, mass, gravity, m)
    k, mm = d.shape[0], d.shape[1]
    A_eq, b_eq, A_ub = _holding_system(n, d, r, L, mass * g / F, mu, extra=0, torsion=torsion)
    cost = np.zeros(A_ub.shape[1])
    cost[:k] = 1.0
    res = _linprog(cost, A_ub, np.zeros(k), A_eq, b_eq)
    if res.status == 2:
        raise InfeasibleGrasp(
            f"no normal forces with friction inside the {mm}-gon cones of mu = {mu} hold the "
            f"{mass} kg object against gravity {tuple(g.tolist())} m/s^2 with these {k} contacts"
        )
    if res.status != 0:
        raise NotConverged(f"minimum normal force LP failed: {res.message}")
    return res.x[:k] * F


def squeeze_utilisation(
    points: ArrayLike,
    normals: ArrayLike,
    normal_forces: ArrayLike,
    mu: float,
    com: ArrayLike,
    mass: float,
    gravity: ArrayLike = (0.0, 0.0, -9.81),
    m: int = 8,
    torsion: ArrayLike | None = None,
) -> float:
    """Smallest s such that normal forces ``f_n,j' <= s f_n,j`` with friction inside the
    linearised cones hold the object (Eq. 21-22); ``inf`` if no s does. ``torsion`` kappa ``(k,)``
    [m]: soft-finger contacts (:func:`_holding_system`).

    Unlike :func:`friction_feasibility` the normal forces may redistribute below the given ones:
    an object squeezed on the table, whose normal forces the table's friction balances, shifts in
    the fingers when lifted until they balance by themselves. ``s <= 1``: the current squeeze can
    hold the object; ``1 - s`` is its margin.
    """
    p, n, mu, c, g, mass, d, r, F, L = _setup(points, normals, mu, com, mass, gravity, m)
    fn = np.asarray(normal_forces, dtype=np.float64).reshape(-1)
    k = d.shape[0]
    if fn.shape != (k,) or not (np.isfinite(fn).all() and (fn >= 0).all()):
        raise ConfigError(f"normal_forces must be {k} finite values >= 0 N, got {normal_forces!r}")
    if not fn.any():
        return math.inf
    A_eq, b_eq, cone = _holding_system(n, d, r, L, mass * g / F, mu, extra=1, torsion=torsion)
    # f_n,j - s f_n,j(given) <= 0 (forces in units of F)
    cap = np.zeros((k, cone.shape[1]))
    cap[:, :k] = np.eye(k)
    cap[:, -1] = -fn / F
    cost = np.zeros(cone.shape[1])
    cost[-1] = 1.0
    res = _linprog(cost, np.vstack([cone, cap]), np.zeros(2 * k), A_eq, b_eq)
    if res.status == 2:
        return math.inf
    if res.status != 0:
        raise NotConverged(f"squeeze utilisation LP failed: {res.message}")
    return float(res.x[-1])
