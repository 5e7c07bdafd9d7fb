"""Fused compiled time stepping: many explicit steps of a scene in one call, without Python between.

One call of :meth:`FusedStepper.advance` runs K steps of semi-implicit Euler,

    f = ((f_internal(x, v) + m g) + f_planes(x, v, t)) + f_fingers(x, v, t)
    v <- v + dt f / m,   x <- x + dt v,   t <- t + dt,                                      (1)

or of classical RK4 (four force evaluations per step, the friction states of the step's start),
each step followed by the friction state updates of the planes (Algorithm 1 per node, as
:meth:`softgrasp.physics.planes.PlaneContact.update`) and of the fingertips
(:func:`softgrasp.physics.fingertip.compiled._fingertip_update`'s arithmetic, after one detection that the
forces at the new state share) and by the checks of
:class:`softgrasp.sim.stability.BlowupMonitor`: the per-step path of
:class:`~softgrasp.sim.explicit.SemiImplicitEuler` / :class:`~softgrasp.sim.explicit.RK4`
driven by :func:`~softgrasp.sim.explicit.simulate`, to round-off (tested to 1e-8; measured
1e-13). The pieces:

* body forces: the spring law, edge dashpots and volume term of :mod:`softgrasp.physics.forces_compiled`
  (polynomial laws only, :func:`softgrasp.physics.forces_compiled.polynomial_coefficients`), with the
  reciprocals of the rest lengths and volumes precomputed and multiply-adds fused (round-off);
  the same arithmetic as those kernels, in fewer instructions (:func:`pack_body`: flat arrays,
  unsigned node indices, packed parameters), the same results to the bit; or eight elements at a
  time in vector instructions (:mod:`softgrasp.sim.fused.blocks`, by
  default on x86-64: :data:`BLOCKS_DEFAULT`), the same to round-off;
* planes: :meth:`~softgrasp.physics.planes.PlaneContact.forces` and ``update`` written out per node;
* fingertips: the compiled kernels of :mod:`softgrasp.physics.fingertip.compiled` themselves (detection,
  forces, state update), the fingertips moving with their prescribed velocity. Their broad phase
  gets a margin from the surface's current stretch instead of the worst case (the same pairs,
  found scanning the facets near the fingertips only: :func:`_finger_reach`).

The blow-up monitor reuses the step's own force evaluations: the interaction forces evaluated at a
new state for the next step are the ones whose power the monitor integrates, and the elastic
energy and inverted tets of its checks come out of the same force evaluation (every
``check_every`` steps). A failed check stops the loop and is reported as a status code; the caller
raises the same :class:`~softgrasp.errors.SimulationUnstable` as the per-step path.

Threads: the body forces and the per-node work are computed in :data:`PARTS` parts, on as many
threads when :attr:`FusedStepper.threads` asks for them (see
:class:`softgrasp.sim.explicit.FusedThreads` for the choice), one part after the other
otherwise; the trajectory does not depend on it. Semi-implicit steps in two parts run as two
threads that each take the whole chunk of steps in one compiled call and meet on shared flags
three times a step (:func:`_advance_leader`, :func:`_advance_worker`, :mod:`softgrasp.sim.fused.spin`):
the second thread computes its body forces while the first does the fingertips (the first part's
share is the smaller by the fingertips' cost, :func:`leader_share`), and nothing is handed to a
thread pool between the steps. RK4 (and more parts) use Numba's parallel loops.
"""

from __future__ import annotations

import math
import os
import platform
import threading
import weakref
from dataclasses import dataclass, replace
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from softgrasp.sim.fused.blocks import BLOCK as _BLOCK
from softgrasp.sim.fused.blocks import (
    block_params,
    node_pair_step,
    node_pair_step_two,
    node_step,
    node_step_two,
    spring_block,
    spring_block_energy,
    spring_block_undamped,
    spring_block_undamped_energy,
    tet_spring_block,
    tet_spring_block_full,
    tet_spring_block_quadratic,
    tet_spring_block_quadratic_full,
    tet_spring_block_quadratic_undamped,
    tet_spring_block_quadratic_undamped_full,
    tet_spring_block_undamped,
    tet_spring_block_undamped_full,
    volume_block,
    volume_block_full,
    volume_block_quadratic,
    volume_block_quadratic_full,
)
from softgrasp.physics.fingertip.compiled import (
    _detect,
    _fingertip_forces,
    _pair_forces,
    _update_pairs,
)
from softgrasp.physics.forces_compiled import _J_FLOOR, _triple_product, polynomial_coefficients
from softgrasp.sim.fused.spin import STRIDE, load_acquire, relax, store_release

__all__ = [
    "METHODS",
    "PARTS",
    "STATUS_ENERGY",
    "STATUS_INVERTED",
    "STATUS_NONFINITE",
    "STATUS_OK",
    "Failure",
    "FusedStepper",
    "leader_share",
    "pack_body",
    "supported",
]

Array = NDArray[np.float64]

_jit = numba.njit(cache=True, fastmath=False, error_model="numpy")
_pjit = numba.njit(cache=True, fastmath=False, error_model="numpy", parallel=True)
# The body-force kernels fuse multiply-adds as softgrasp.physics.forces_compiled's do (the same results).
_fjit = numba.njit(cache=True, fastmath={"contract"}, error_model="numpy")
# The two threads of a chunk run without the GIL (softgrasp.sim.fused.spin).
_njit_nogil = numba.njit(cache=True, fastmath=False, error_model="numpy", nogil=True)
#: Methods the fused stepper runs (names of :func:`softgrasp.sim.stability.canonical_method`).
METHODS = ("semi-implicit", "rk4")

#: Status codes of :meth:`FusedStepper.advance`.
STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_INVERTED = 2
STATUS_ENERGY = 3

#: The body forces are summed from this many parts (edges and tets split in halves), each into its
#: own buffer, computed in parallel when threads are given (:attr:`FusedStepper.threads`) and one
#: after the other otherwise: the result does not depend on the thread count.
PARTS = 2

# Slots of the monitor's float array (see FusedStepper._mon).
_M_T, _M_POWER, _M_WORK, _M_ABS, _M_GRAV, _M_E0, _M_SCALE0, _M_FACTOR, _M_COM0 = 0, 1, 2, 3, 4, 5, 6, 7, 8
_M_SIZE = 11
# Slots of the failure report (see FusedStepper.failure).
_F_T, _F_DT, _F_COUNT, _F_FIRST, _F_EXCESS, _F_SCALE = 0, 1, 2, 3, 4, 5


# ---------------------------------------------------------------------------------- kernels
@_jit
def _plane_pass(
    x, v, p, p0, normal, pvel, mu, k, c, kt, ct, active, anchor, update, lo, hi, out
):  # pragma: no cover
    """Plane p (through its point now ``p0[p]``) on nodes ``lo:hi``: when ``update``, first its friction
    state after a step (:meth:`softgrasp.physics.planes.PlaneContact.update`, in place), then its force
    (:meth:`~softgrasp.physics.planes.PlaneContact.forces`) added to ``out``; returns the force's power
    [W]. One pass over the nodes, the per-node arithmetic written out here: a helper called per node
    with array arguments costs atomic reference-count updates, hundreds of cycles per node."""
    nx = normal[p, 0]
    ny = normal[p, 1]
    nz = normal[p, 2]
    px = p0[p, 0]
    py = p0[p, 1]
    pz = p0[p, 2]
    wx_p = pvel[p, 0]
    wy = pvel[p, 1]
    wz = pvel[p, 2]
    m = mu[p]
    power = 0.0
    # flat views and unsigned indices, as in _node_part (the same arithmetic, fewer instructions)
    N = np.uint64(x.shape[0])
    wx = np.uint64(x.shape[1])
    xf = x.reshape(-1)
    vf = v.reshape(-1)
    of = out.reshape(-1)
    wo = np.uint64(out.shape[1])
    af = anchor.reshape(-1)
    actf = active.reshape(-1)
    kf = k.reshape(-1)
    cf = c.reshape(-1)
    ktf = kt.reshape(-1)
    ctf = ct.reshape(-1)
    one = np.uint64(1)
    two = np.uint64(2)
    three = np.uint64(3)
    base = np.uint64(p) * N
    for i in range(np.uint64(lo), np.uint64(hi)):
        r = i * wx
        n = base + i  # the node's entry in the (P, N) arrays
        a3 = n * three  # its anchor in the (P, N, 3) one
        x0 = xf[r]
        x1 = xf[r + one]
        x2 = xf[r + two]
        if update:
            rx = x0 - px
            ry = x1 - py
            rz = x2 - pz
            pen = -rx * nx + -ry * ny + -rz * nz
            touching = pen > 0.0
            rn = rx * nx + ry * ny + rz * nz
            tx = rx - rn * nx
            ty = ry - rn * ny
            tz = rz - rn * nz
            actf[n] = touching
            if not touching or not m > 0.0:  # the anchor follows a free node
                af[a3] = tx
                af[a3 + one] = ty
                af[a3 + two] = tz
            else:
                sx = tx - af[a3]
                sy = ty - af[a3 + one]
                sz = tz - af[a3 + two]
                s_norm = math.sqrt(sx * sx + sy * sy + sz * sz)
                limit = m * kf[n] * max(pen, 0.0) / max(ktf[n], 1e-300)
                if s_norm > limit:  # slip: the anchor is dragged to the Coulomb limit
                    q = limit / s_norm
                    af[a3] = tx - sx * q
                    af[a3 + one] = ty - sy * q
                    af[a3 + two] = tz - sz * q
        pen = -(x0 - px) * nx + -(x1 - py) * ny + -(x2 - pz) * nz
        if not pen > 0.0:
            continue
        kn = kf[n]
        cn = cf[n]
        ktn = ktf[n]
        ctn = ctf[n]
        v0 = vf[r]
        v1 = vf[r + one]
        v2 = vf[r + two]
        vrx = v0 - wx_p
        vry = v1 - wy
        vrz = v2 - wz
        vn = vrx * nx + vry * ny + vrz * nz
        fn = max(kn * pen - cn * vn, 0.0)
        fx = fn * nx
        fy = fn * ny
        fz = fn * nz
        if m > 0.0:
            sx = x0 - (px + af[a3])
            sy = x1 - (py + af[a3 + one])
            sz = x2 - (pz + af[a3 + two])
            sn = sx * nx + sy * ny + sz * nz
            sx = sx - sn * nx
            sy = sy - sn * ny
            sz = sz - sn * nz
            tx = -ktn * sx - ctn * (vrx - vn * nx)
            ty = -ktn * sy - ctn * (vry - vn * ny)
            tz = -ktn * sz - ctn * (vrz - vn * nz)
            mag = math.sqrt(tx * tx + ty * ty + tz * tz)
            cap = m * fn
            if mag > cap:
                q = cap / max(mag, 1e-300)
                tx *= q
                ty *= q
                tz *= q
            fx += tx
            fy += ty
            fz += tz
        o = i * wo
        of[o] += fx
        of[o + one] += fy
        of[o + two] += fz
        power += fx * v0 + fy * v1 + fz * v2
    return power


@_jit
def _plane_points(t, pl_point, pl_vel, p0):  # pragma: no cover - compiled
    """Each plane's point at time t, ``point + t velocity`` (Plane.point_at), into p0 (P, 3)."""
    for p in range(pl_point.shape[0]):
        for d in range(3):
            p0[p, d] = pl_point[p, d] + t * pl_vel[p, d]


# The body-force kernels below compute what softgrasp.physics.forces_compiled's _springs, _volumes and
# _inverted compute, operation for operation (so the same bits), on data laid out by pack_body:
# positions, velocities and forces as flat (4N,) views of (N, 4) arrays, node indices stored times 4
# and unsigned (Numba adds no negative-index wrap-around to unsigned indices, nor a stride multiply
# to a flat array), each element's parameters side by side. Measured (2 196 nodes, one thread):
# 218 -> 182 us, the loops being bound by their instruction count (~5 per cycle) more than by
# memory. Blocks of eight elements go to softgrasp.sim.fused.blocks (vector instructions; the same
# arithmetic without fused multiply-adds: round-off): 182 -> 115 us.


@_fjit
def _edge_pass(x, v, eq, ep, a2, a3, damped, want_energy, lo, hi, out):  # pragma: no cover - compiled
    """Springs (+ dashpots) ``lo:hi`` added to ``out``; returns their energy (0 unless
    ``want_energy``). ``eq`` (2E,): the edges' nodes times 4; ``ep`` (4E,): their L0 [m],
    1 / L0 [1/m], k L0 [N], c [N s/m]. :func:`softgrasp.physics.forces_compiled._springs`."""
    energy = 0.0
    a2_3 = a2 / 3.0
    a3_4 = 0.25 * a3
    one = np.uint64(1)
    two = np.uint64(2)
    for e in range(np.uint64(lo), np.uint64(hi)):
        i = np.uint64(eq[two * e])
        j = np.uint64(eq[two * e + one])
        q = np.uint64(4) * e
        dx = x[j] - x[i]
        dy = x[j + one] - x[i + one]
        dz = x[j + two] - x[i + two]
        L = math.sqrt(dx * dx + dy * dy + dz * dz)
        inv = 1.0 / L
        eps = L * ep[q + one] - 1.0
        e2 = eps * eps
        kl0 = ep[q + two]
        T = kl0 * (eps + a2 * e2 + a3 * e2 * eps)
        if want_energy:
            energy += kl0 * ep[q] * (0.5 * e2 + a2_3 * e2 * eps + a3_4 * e2 * e2)
        if damped:
            rate = (
                (v[j] - v[i]) * dx + (v[j + one] - v[i + one]) * dy + (v[j + two] - v[i + two]) * dz
            ) * inv
            T += ep[q + np.uint64(3)] * rate
        s = T * inv
        out[i] += s * dx
        out[i + one] += s * dy
        out[i + two] += s * dz
        out[j] -= s * dx
        out[j + one] -= s * dy
        out[j + two] -= s * dz
    return energy


@_jit
def _lower(first, index):  # pragma: no cover - compiled
    """The lower of a tet index ``first`` found so far (-1: none yet) and ``index``."""
    i = np.int64(index)
    return i if first < 0 or i < first else first


@_fjit
def _tet_pass(x, tq, tp, order, kappa, barrier, want_energy, check, lo, hi, out):  # pragma: no cover
    """Volume-term forces of tets ``lo:hi`` added to ``out`` (``kappa`` != 0), or only their
    inverted count (``kappa`` = 0). ``tq`` (4M,): the tets' nodes times 4; ``tp`` (2M,):
    1 / (6 V0) [1/m^3] and V0 [m^3]; ``order`` (M,): each tet's index in the body's mesh. Returns
    (energy, 0 unless ``want_energy``; the tets with non-positive signed volume and the lowest
    mesh index among them, 0 and -1 unless ``check``): :func:`softgrasp.physics.forces_compiled._volumes`
    and ``_inverted``."""
    energy = 0.0
    count = 0
    first = -1
    vol = kappa != 0.0
    ck = -kappa / 6.0
    one = np.uint64(1)
    two = np.uint64(2)
    for t in range(np.uint64(lo), np.uint64(hi)):
        b = np.uint64(4) * t
        p0 = np.uint64(tq[b])
        p1 = np.uint64(tq[b + one])
        p2 = np.uint64(tq[b + two])
        p3 = np.uint64(tq[b + np.uint64(3)])
        x0 = x[p0]
        y0 = x[p0 + one]
        z0 = x[p0 + two]
        ax = x[p1] - x0
        ay = x[p1 + one] - y0
        az = x[p1 + two] - z0
        bx = x[p2] - x0
        by = x[p2 + one] - y0
        bz = x[p2 + two] - z0
        cx = x[p3] - x0
        cy = x[p3 + one] - y0
        cz = x[p3 + two] - z0
        c1x = by * cz - bz * cy
        c1y = bz * cx - bx * cz
        c1z = bx * cy - by * cx
        if not vol:
            if check:
                det = _triple_product(ax, ay, az, bx, by, bz, cx, cy, cz)
                if not det / 6.0 > 0.0:
                    first = _lower(first, order[t])
                    count += 1
            continue
        c2x = cy * az - cz * ay
        c2y = cz * ax - cx * az
        c2z = cx * ay - cy * ax
        c3x = ay * bz - az * by
        c3y = az * bx - ax * bz
        c3z = ax * by - ay * bx
        det = ax * c1x + ay * c1y + az * c1z
        if check:
            if not det / 6.0 > 0.0:  # signed_volumes(x, tets) <= 0
                first = _lower(first, order[t])
                count += 1
        q = two * t
        J = det * tp[q]
        if barrier:
            Jc = J if J > _J_FLOOR else _J_FLOOR
            dw = 1.0 - 1.0 / Jc
            if want_energy:
                energy += kappa * tp[q + one] * (J - 1.0 - math.log(Jc))
        else:
            dw = J - 1.0
            if want_energy:
                energy += kappa * tp[q + one] * (0.5 * dw * dw)
        s = ck * dw
        out[p1] += s * c1x
        out[p1 + one] += s * c1y
        out[p1 + two] += s * c1z
        out[p2] += s * c2x
        out[p2 + one] += s * c2y
        out[p2 + two] += s * c2z
        out[p3] += s * c3x
        out[p3 + one] += s * c3y
        out[p3 + two] += s * c3z
        out[p0] -= s * (c1x + c2x + c3x)
        out[p0 + one] -= s * (c1y + c2y + c3y)
        out[p0 + two] -= s * (c1z + c2z + c3z)
    return energy, count, first


@_jit
def _part_range(part, parts, n, lead):  # pragma: no cover - compiled
    """Items ``lo:hi`` of part ``part`` of ``parts`` out of ``n``: two parts split at ``int(n lead)``
    (:func:`pack_body`'s ``lead``), more parts in even shares."""
    if parts == 2:
        cut = int(n * lead)
        return (0, cut) if part == 0 else (cut, n)
    return part * n // parts, (part + 1) * n // parts


@_jit
def _carrying_block(xf, vf, tq, tp8, kappa, a2, a3, blk, of, barrier, damped, full):  # pragma: no cover
    """Tet block ``blk`` with the springs it carries (:data:`softgrasp.sim.fused.blocks.tet_spring_block`:
    the variant for the volume law, the dashpots and whether the check's energy and inverted mask
    are wanted); returns (energy, mask), (0, 0) unless ``full``."""
    f = _J_FLOOR
    if full:
        if barrier:
            if damped:
                return tet_spring_block_full(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
            return tet_spring_block_undamped_full(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
        if damped:
            return tet_spring_block_quadratic_full(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
        return tet_spring_block_quadratic_undamped_full(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
    if barrier:
        if damped:
            tet_spring_block(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
        else:
            tet_spring_block_undamped(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
    elif damped:
        tet_spring_block_quadratic(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
    else:
        tet_spring_block_quadratic_undamped(xf, vf, tq, tp8, kappa, f, a2, a3, blk, of)
    return 0.0, np.int64(0)


@_jit
def _body_part(part, parts, x, v, body, want_energy, check, out, info):  # pragma: no cover - compiled
    """Part ``part`` of ``parts`` of the internal forces: its share of the edges and tets, into its
    own buffer ``out`` (N, 4) (zeroed here); energy, inverted count and lowest inverted tet into
    ``info``. ``x``, ``v``: positions and velocities (N, 4), C-contiguous; ``body`` is
    :func:`pack_body`'s. The blocks of eight elements go to :mod:`softgrasp.sim.fused.blocks` when
    ``body`` asks for it, split between the parts by blocks (:func:`_part_range`), the last part
    taking the elements left over (a body without the volume term counts its inverted tets on the
    scalar loop)."""
    eq, ep, tq, tp, a2, a3, damped, kappa, barrier, use_blocks, ep8, tp8, _, order, lead, carry = body
    xf = x.reshape(-1)
    vf = v.reshape(-1)
    of = out.reshape(-1)
    # Zeroed by writing only the values that are not zero yet: the rows no element of this part
    # touches (half the nodes, or more) stay clean, and on two threads the other one's node pass
    # reads them from its own cache instead of taking each line over from this thread's core.
    for i in range(of.shape[0]):
        if of[i] != 0.0:
            of[i] = 0.0
    E = eq.shape[0] // 2
    M = tq.shape[0] // 4
    if use_blocks:
        nb = E // _BLOCK
        e = 0.0
        lo, hi = _part_range(part, parts, nb, lead)
        for b in range(lo, hi):
            if damped:
                if want_energy:
                    e += spring_block_energy(xf, vf, eq, ep8, a2, a3, b, of)
                else:
                    spring_block(xf, vf, eq, ep8, a2, a3, b, of)
            elif want_energy:
                e += spring_block_undamped_energy(xf, vf, eq, ep8, a2, a3, b, of)
            else:
                spring_block_undamped(xf, vf, eq, ep8, a2, a3, b, of)
        lo = nb * _BLOCK if part == parts - 1 else E
        e += _edge_pass(xf, vf, eq, ep, a2, a3, damped, want_energy, lo, E, of)
    else:
        lo, hi = _part_range(part, parts, E, lead)
        e = _edge_pass(xf, vf, eq, ep, a2, a3, damped, want_energy, lo, hi, of)
    count = 0
    first = -1
    if kappa != 0.0 and use_blocks:
        nb = M // _BLOCK
        full = want_energy or check
        lo, hi = _part_range(part, parts, nb, lead)
        for b in range(lo, hi):
            if carry:
                ev, bad = _carrying_block(xf, vf, tq, tp8, kappa, a2, a3, b, of, barrier, damped, full)
                if not full:
                    continue
            elif not full:
                if barrier:
                    volume_block(xf, tq, tp8, kappa, _J_FLOOR, b, of)
                else:
                    volume_block_quadratic(xf, tq, tp8, kappa, _J_FLOOR, b, of)
                continue
            elif barrier:
                ev, bad = volume_block_full(xf, tq, tp8, kappa, _J_FLOOR, b, of)
            else:
                ev, bad = volume_block_quadratic_full(xf, tq, tp8, kappa, _J_FLOOR, b, of)
            if want_energy:
                e += ev
            if check and bad != 0:
                for k in range(_BLOCK):
                    if (bad >> k) & 1:
                        first = _lower(first, order[b * _BLOCK + k])
                        count += 1
        lo = nb * _BLOCK if part == parts - 1 else M
        ev, n_bad, first_bad = _tet_pass(xf, tq, tp, order, kappa, barrier, want_energy, check, lo, M, of)
        e += ev
        count += n_bad
        if n_bad > 0:
            first = _lower(first, first_bad)
    elif kappa != 0.0 or check:
        lo, hi = _part_range(part, parts, M, lead)
        ev, count, first = _tet_pass(xf, tq, tp, order, kappa, barrier, want_energy, check, lo, hi, of)
        e += ev
    info[0] = e
    info[1] = count
    info[2] = first


@_pjit
def _body_forces_parallel(x, v, body, want_energy, check, fint, info):  # pragma: no cover - compiled
    """:func:`_body_part` for every part, one thread each."""
    parts = fint.shape[0]
    for p in numba.prange(parts):
        _body_part(p, parts, x, v, body, want_energy, check, fint[p], info[p])


@_jit
def _max_facet_edge(x, facets):  # pragma: no cover - compiled
    """Longest edge of the boundary facets at positions x [m]."""
    best = 0.0
    for j in range(facets.shape[0]):
        for r in range(3):
            a = facets[j, r]
            b = facets[j, (r + 1) % 3]
            dx = x[a, 0] - x[b, 0]
            dy = x[a, 1] - x[b, 1]
            dz = x[a, 2] - x[b, 2]
            best = max(best, dx * dx + dy * dy + dz * dz)
    return math.sqrt(best)


@_jit
def _finger_reach(x, t, fingers, x_ref, track, near, centres):  # pragma: no cover - compiled
    """The fingertips' centres at time t into ``centres``, and the broad phase of their detection
    at x: returns (margin, the number of surface nodes to scan: ``near[:n]``).

    The margin is the kernels' own ``reach`` (the rest mesh's longest facet edge x a stretch
    allowance), or less where the surface is known to be less stretched: a touching facet has a
    vertex within R + (1 + 3 inside_tol) L of the fingertip centre, L its longest edge now; every
    facet edge is at most L_ref + 2 u, where L_ref is the longest facet edge at the reference
    positions ``x_ref`` and u the largest node displacement since (``track`` = [L_ref, u^2, the
    number of near nodes, the centres when they were listed (3 a fingertip)], u^2 kept up to date
    by the integration loop). So margin ``(1 + 3 inside_tol) (L_ref + 2 u)`` finds exactly the
    same pairs as ``reach``, scanning only facets near the fingertips.

    The surface nodes scanned are those that were within R + margin + L_ref of a centre when the
    reference was taken (``near``, a Verlet list): a node outside it is still farther than
    R + margin from every centre while u (1 + 2 (1 + 3 inside_tol)) plus the largest centre
    displacement since stays below L_ref (the margin itself grows by at most 2 (1 + 3 inside_tol) u),
    so the same pairs are found. The reference and the list are renewed when that fails or u
    exceeds L_ref / 4. At 2 196 nodes ~70 of the 1 053 surface nodes: the leader no longer reads
    every surface node's position, half of them just written by the other thread."""
    facets = fingers[1]
    boundary = fingers[2]
    reach = fingers[5]
    radii = fingers[9]
    grow = 1.0 + 3.0 * fingers[13]  # inside_tol
    _fingers_at(t, fingers, centres)
    nf = centres.shape[0]
    u = math.sqrt(track[1])
    moved = 0.0
    for f in range(nf):
        dx = centres[f, 0] - track[3 + 3 * f]
        dy = centres[f, 1] - track[4 + 3 * f]
        dz = centres[f, 2] - track[5 + 3 * f]
        moved = max(moved, math.sqrt(dx * dx + dy * dy + dz * dz))
    stale = track[2] < 0.0 or u > 0.25 * track[0]
    if stale or u * (1.0 + 2.0 * grow * (1.0 + 1e-9)) + moved >= track[0]:
        for i in range(x.shape[0]):
            x_ref[i, 0] = x[i, 0]
            x_ref[i, 1] = x[i, 1]
            x_ref[i, 2] = x[i, 2]
        track[0] = _max_facet_edge(x, facets)
        track[1] = 0.0
        u = 0.0
        margin = min(reach, grow * track[0] * (1.0 + 1e-9))
        n = 0
        for b in range(boundary.shape[0]):
            node = boundary[b]
            for f in range(nf):
                lim = radii[f] + margin + track[0]
                dx = x[node, 0] - centres[f, 0]
                dy = x[node, 1] - centres[f, 1]
                dz = x[node, 2] - centres[f, 2]
                if dx * dx + dy * dy + dz * dz < lim * lim:
                    near[n] = node
                    n += 1
                    break
        track[2] = n
        for f in range(nf):
            for d in range(3):
                track[3 + 3 * f + d] = centres[f, d]
    return min(reach, grow * (track[0] + 2.0 * u) * (1.0 + 1e-9)), np.int64(track[2])


@_jit
def _clear_finger(active, anchor, offset, slip, memory):  # pragma: no cover - compiled
    """Zero a finger state buffer that only holds entries where ``active`` is set."""
    for f in range(active.shape[0]):
        for j in range(active.shape[1]):
            if active[f, j]:
                active[f, j] = False
                for d in range(3):
                    anchor[f, j, d] = 0.0
                    offset[f, j, d] = 0.0
                    slip[f, j, d] = 0.0
        for d in range(3):
            memory[f, d] = 0.0


@_jit
def _body_forces(parallel, x, v, body, want_energy, check, fint, info):  # pragma: no cover - compiled
    """Internal forces split in ``fint.shape[0]`` parts (summed by the caller), on as many threads
    when ``parallel``; returns (energy, inverted count, lowest inverted tet or -1). ``x``, ``v``:
    positions and velocities (N, 4) (the stepper's layout, fourth column zero, C-contiguous);
    ``fint`` (parts, N, 4), its fourth column left zero."""
    n = body[12]
    if x.shape != (n, 4) or v.shape != (n, 4) or fint.shape[1] != n or fint.shape[2] != 4:
        raise ValueError("body forces: x and v must be (N, 4) and fint (parts, N, 4), N the body's nodes")
    if parallel:
        _body_forces_parallel(x, v, body, want_energy, check, fint, info)
    else:
        for p in range(fint.shape[0]):
            _body_part(p, fint.shape[0], x, v, body, want_energy, check, fint[p], info[p])
    return _body_totals(info)


@_jit
def _body_totals(info):  # pragma: no cover - compiled
    """The body-force parts' ``info`` rows summed: (energy, inverted count, the lowest mesh index of
    an inverted tet or -1)."""
    e = 0.0
    count = 0
    first = -1
    for p in range(info.shape[0]):
        e += info[p, 0]
        n = int(info[p, 1])
        if n > 0:
            count += n
            first = _lower(first, int(info[p, 2]))
    return e, count, first


@_jit
def _fingers_at(t, fingers, centres):  # pragma: no cover - compiled
    """Fingertip centres at time t, ``centre + t velocity`` (Fingertip.centre_at), into centres."""
    c0 = fingers[6]
    vel = fingers[7]
    for f in range(c0.shape[0]):
        for d in range(3):
            centres[f, d] = c0[f, d] + t * vel[f, d]


@_jit
def _finger_forces(x, v, fingers, fstate, cur, reach, nodes, centres, out):  # pragma: no cover - compiled
    """Fingertip forces with the centres ``centres``, the surface nodes ``nodes`` scanned and
    buffer ``cur`` of the friction state ``fstate``, added to ``out``
    (:func:`softgrasp.physics.fingertip.compiled._fingertip_forces`)."""
    active, anchor, _, memory, offset = fstate
    (_, facets, _, indptr, indices, _, _, vel, omega, radii, K, C, closest, inside_tol, mu, n_exp,
     hunt_crossley, patch, ratio, min_depth_ratio) = fingers  # fmt: skip
    _fingertip_forces(
        x, v, facets, nodes, indptr, indices, reach, centres, radii, vel, omega, K, C, closest, inside_tol,
        mu, n_exp, hunt_crossley, patch, ratio, min_depth_ratio, active[cur], anchor[cur], offset[cur],
        memory[cur], out,
    )  # fmt: skip


@_jit
def _acceleration(i, d, m, fint, grav, fplane, ffinger, clear):  # pragma: no cover - compiled
    """Component d of node i's acceleration [m/s^2]: the parts of its internal force summed, plus
    gravity, the planes' and the fingertips' forces, over its mass m; the interaction forces are
    zeroed after reading when ``clear`` (they are summed afresh at the next state)."""
    fi = fint[0, i, d]
    for q in range(1, fint.shape[0]):
        fi += fint[q, i, d]
    a = (((fi + grav[i, d]) + fplane[i, d]) + ffinger[i, d]) / m
    if clear:
        fplane[i, d] = 0.0
        ffinger[i, d] = 0.0
    return a


@_jit
def _node_part(part, parts, dt, x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active,
               pl_anchor, sums):  # pragma: no cover - compiled  # fmt: skip
    """Nodes of part ``part`` of ``parts``: the step (v += dt f / m, x += dt v), then each plane's
    friction state update and force at the new state (the contact force buffers are cleared for the
    new state's forces first). Into ``sums``: whether a value became non-finite, the largest squared
    displacement from ``x_ref`` (for the fingertip broad phase), sum m x (3) and the planes' power."""
    point, normal, pvel, mu, k, c, kt, ct = planes
    N = x.shape[0]
    lo = part * N // parts
    hi = (part + 1) * N // parts
    bad = False
    u2 = 0.0
    mx = 0.0
    my = 0.0
    mz = 0.0
    # flat views and unsigned indices (no wrap-around, no stride multiplies): the same arithmetic as
    # _acceleration and the update written with 2-D indices, in fewer instructions
    xf = x.reshape(-1)
    vf = v.reshape(-1)
    rf = x_ref.reshape(-1)
    ff = fint.reshape(-1)
    gf = grav.reshape(-1)
    pf = fplane.reshape(-1)
    qf = ffinger.reshape(-1)
    wx = np.uint64(x.shape[1])  # the row width of every (N, .) array here (4 in the stepper)
    if (
        fint.shape[2] != wx or x_ref.shape[1] != wx or grav.shape[1] != wx or fplane.shape[1] != wx
        or ffinger.shape[1] != wx
    ):  # fmt: skip
        raise ValueError("node pass: the rows of x, x_ref, grav, fplane, ffinger and fint differ in width")
    wf = np.uint64(fint.shape[1]) * wx  # one part of fint
    P = np.uint64(fint.shape[0])
    rows = wx == 4 and P <= 2  # a node's row at a time (softgrasp.sim.fused.blocks.node_step)
    i0 = np.uint64(lo)
    if rows:  # two nodes at a time (the same arithmetic and sums, in the same order)
        while i0 + np.uint64(1) < np.uint64(hi):
            ma = mass[i0]
            mb = mass[i0 + np.uint64(1)]
            r = i0 * wx
            if P == 2:
                da, db, nonfinite = node_pair_step_two(xf, vf, rf, ff, gf, pf, qf, r, wf, ma, mb, dt)
            else:
                da, db, nonfinite = node_pair_step(xf, vf, rf, ff, gf, pf, qf, r, wf, ma, mb, dt)
            bad |= nonfinite != 0
            u2 = max(u2, da)
            mx += ma * xf[r]
            my += ma * xf[r + np.uint64(1)]
            mz += ma * xf[r + np.uint64(2)]
            u2 = max(u2, db)
            mx += mb * xf[r + np.uint64(4)]
            my += mb * xf[r + np.uint64(5)]
            mz += mb * xf[r + np.uint64(6)]
            i0 += np.uint64(2)
    for i in range(i0, np.uint64(hi)):
        m = mass[i]
        r = i * wx
        if rows:
            if P == 2:
                du2, nonfinite = node_step_two(xf, vf, rf, ff, gf, pf, qf, r, wf, m, dt)
            else:
                du2, nonfinite = node_step(xf, vf, rf, ff, gf, pf, qf, r, wf, m, dt)
            bad |= nonfinite != 0
        else:
            du2 = 0.0
            for d in range(np.uint64(3)):
                fi = ff[r + d]
                for q in range(np.uint64(1), P):
                    fi += ff[q * wf + r + d]
                a = (((fi + gf[r + d]) + pf[r + d]) + qf[r + d]) / m
                pf[r + d] = 0.0
                qf[r + d] = 0.0
                vi = vf[r + d] + dt * a
                xi = xf[r + d] + dt * vi
                vf[r + d] = vi
                xf[r + d] = xi
                bad |= not (abs(vi) < math.inf and abs(xi) < math.inf)
                du = xi - rf[r + d]
                du2 += du * du
        u2 = max(u2, du2)
        mx += m * xf[r]
        my += m * xf[r + np.uint64(1)]
        mz += m * xf[r + np.uint64(2)]
    power = 0.0
    for p in range(point.shape[0]):
        power += _plane_pass(x, v, p, p0, normal, pvel, mu, k, c, kt, ct, pl_active, pl_anchor, True, lo, hi,
                             fplane)  # fmt: skip
    sums[0] = 1.0 if bad else 0.0
    sums[1] = u2
    sums[2] = mx
    sums[3] = my
    sums[4] = mz
    sums[5] = power


@_pjit
def _node_pass_parallel(dt, x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active, pl_anchor,
                        sums):  # pragma: no cover - compiled  # fmt: skip
    """:func:`_node_part` for every part, one thread each."""
    parts = sums.shape[0]
    for q in numba.prange(parts):
        _node_part(q, parts, dt, x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active,
                   pl_anchor, sums[q])  # fmt: skip


@_jit
def _node_totals(sums, track):  # pragma: no cover - compiled
    """The node parts' ``sums`` (see :func:`_node_part`) together: (whether a value became
    non-finite, sum m x (3), the planes' power); the largest squared displacement goes to
    ``track[1]``."""
    bad = False
    u2 = track[1]
    mx = 0.0
    my = 0.0
    mz = 0.0
    p_plane = 0.0
    for q in range(sums.shape[0]):
        bad |= sums[q, 0] != 0.0
        u2 = max(u2, sums[q, 1])
        mx += sums[q, 2]
        my += sums[q, 3]
        mz += sums[q, 4]
        p_plane += sums[q, 5]
    track[1] = u2
    return bad, mx, my, mz, p_plane


@_jit
def _forces_at(
    x, v, t, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel
):  # pragma: no cover
    """All forces at the state (x, v, t) into the workspace, with the friction states as they are:
    before the first step (the loops keep them up to date after), and at each RK4 stage (the
    step's friction states frozen, as :meth:`softgrasp.sim.scene.Scene.forces` on the state's
    contacts)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, _, near = work
    point, normal, pvel, mu, k, c, kt, ct = planes
    _body_forces(parallel, x, v, body, False, False, fint, info)
    _plane_points(t, point, pvel, p0)
    for i in range(x.shape[0]):
        for d in range(3):
            fplane[i, d] = 0.0
            ffinger[i, d] = 0.0
    for p in range(point.shape[0]):
        _plane_pass(
            x, v, p, p0, normal, pvel, mu, k, c, kt, ct, pl_active, pl_anchor, False, 0, x.shape[0], fplane
        )
    if fingers[0]:
        reach, n_near = _finger_reach(x, t, fingers, x_ref, track, near, centres)
        _finger_forces(x, v, fingers, fstate, cur, reach, near[:n_near], centres, ffinger)


@_jit
def _after_step(x, v, t, t_prev, mass, total_mass, gvec, mon, fail, power, mx, my, mz, check, e_int, count,
                first):  # pragma: no cover - compiled  # fmt: skip
    """:meth:`softgrasp.sim.stability.BlowupMonitor.after_step` for the state (x, v, t) reached by a
    step from ``t_prev``: ``power`` of the interactions there, ``sum m x`` = (mx, my, mz), and when
    ``check``, the inverted tets (``count``, ``first``) and elastic energy ``e_int`` of the force
    evaluation at that state. Returns a status; the failure's details go to ``fail``."""
    hb = t - mon[_M_T]
    mon[_M_WORK] += 0.5 * (mon[_M_POWER] + power) * hb
    mon[_M_ABS] += 0.5 * (abs(mon[_M_POWER]) + abs(power)) * hb
    mon[_M_POWER] = power
    mon[_M_T] = t
    dz = (
        (mx / total_mass - mon[_M_COM0]) * gvec[0]
        + (my / total_mass - mon[_M_COM0 + 1]) * gvec[1]
        + (mz / total_mass - mon[_M_COM0 + 2]) * gvec[2]
    ) * total_mass
    mon[_M_GRAV] = max(mon[_M_GRAV], abs(dz))
    if not check:
        return STATUS_OK
    if count > 0:
        fail[_F_T] = t
        fail[_F_DT] = t - t_prev
        fail[_F_COUNT] = count
        fail[_F_FIRST] = first
        return STATUS_INVERTED
    kin = 0.0
    pot = 0.0
    for i in range(x.shape[0]):
        kin += mass[i] * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
        pot += mass[i] * (x[i, 0] * gvec[0] + x[i, 1] * gvec[1] + x[i, 2] * gvec[2])
    excess = (0.5 * kin + e_int - pot) - mon[_M_E0] - mon[_M_WORK]
    scale = max(mon[_M_SCALE0], mon[_M_ABS], mon[_M_GRAV])
    if not excess <= mon[_M_FACTOR] * scale:
        fail[_F_T] = t
        fail[_F_DT] = t - t_prev
        fail[_F_EXCESS] = excess
        fail[_F_SCALE] = scale
        return STATUS_ENERGY
    return STATUS_OK


@_jit
def _finger_step(x, v, t, fingers, fstate, cur, work, monitor_on):  # pragma: no cover - compiled
    """The fingertips after a step: friction states updated at (x, t), then their forces at the new
    state into ``ffinger`` (cleared by the caller). Returns the new current buffer and the forces'
    power (0 unless ``monitor_on``)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, sums, near = work
    reach, n_near = _finger_reach(x, t, fingers, x_ref, track, near, centres)
    (_, facets, _, indptr, indices, _, _, vel, omega, radii, K, C, closest, inside_tol, mu, n_exp,
     hunt_crossley, patch, ratio, min_depth_ratio) = fingers  # fmt: skip
    active, anchor, slip, memory, offset = fstate
    # one detection for the update and the forces: the same state (x, t), the same pairs
    finger, facet, val = _detect(
        x, facets, near[:n_near], indptr, indices, reach, centres, radii, closest, inside_tol
    )
    nxt = 1 - cur
    _clear_finger(active[nxt], anchor[nxt], offset[nxt], slip[nxt], memory[nxt])
    _update_pairs(
        finger, facet, val, x, facets, centres, radii, K, mu, n_exp, patch, ratio, min_depth_ratio,
        active[cur], anchor[cur], offset[cur], slip[cur], memory[cur], active[nxt], anchor[nxt], offset[nxt],
        slip[nxt], memory[nxt],
    )  # fmt: skip
    cur = nxt
    _pair_forces(
        finger, facet, val, x, v, facets, centres, radii, vel, omega, K, C, mu, n_exp, hunt_crossley, patch,
        ratio, min_depth_ratio, active[cur], anchor[cur], offset[cur], memory[cur], False, ffinger,
    )  # fmt: skip
    power = 0.0
    if monitor_on:  # over the touching facets' nodes, each once: the only ones with a fingertip force
        seen = np.zeros(x.shape[0], np.bool_)
        for p in range(facet.shape[0]):
            for r in range(3):
                i = facets[facet[p], r]
                if not seen[i]:
                    seen[i] = True
                    power += ffinger[i, 0] * v[i, 0] + ffinger[i, 1] * v[i, 1] + ffinger[i, 2] * v[i, 2]
    return cur, power


@_jit
def _check_step(monitor_on, msteps, check_every):  # pragma: no cover - compiled
    """Whether monitored step number ``msteps`` runs the monitor's energy and volume checks (the
    body forces then return the energy and the inverted tets too). The leader and the worker of a
    two-thread chunk each count the steps and must agree."""
    return monitor_on and msteps % check_every == 0


@_jit
def _end_step(
    x, v, t, t_prev, fingers, fstate, cur, work, monitor_on, msteps, check_every, parallel, body, fint, info,
    mass, total_mass, gvec, mon, fail, p_plane, mx, my, mz,
):  # fmt: skip  # pragma: no cover - compiled
    """The end of every step, for both methods: the fingertips' friction states and their forces at
    the new state, the body forces there (the next step's), and the monitor's checks (power of the
    planes ``p_plane`` and the fingertips, momentum ``mx, my, mz``). Returns (status, the fingertip
    state cursor, monitored steps)."""
    p_finger = 0.0
    if fingers[0]:
        cur, p_finger = _finger_step(x, v, t, fingers, fstate, cur, work, monitor_on)
    msteps += 1
    check = _check_step(monitor_on, msteps, check_every)
    e_int, count, first = _body_forces(parallel, x, v, body, check, check, fint, info)
    status = STATUS_OK
    if monitor_on:
        power = p_plane + p_finger
        status = _after_step(
            x, v, t, t_prev, mass, total_mass, gvec, mon, fail, power, mx, my, mz, check, e_int, count, first,
        )  # fmt: skip
    return status, cur, msteps


@_jit
def _advance(n_steps, h, land, t_end, t, x, v, mass, grav, total_mass, body, planes, pl_active, pl_anchor,
             fingers, fstate, cur, work, have_forces, parallel, monitor_on, mon, msteps, check_every, gvec,
             fail):  # pragma: no cover - compiled  # fmt: skip
    """Up to ``n_steps`` steps of Eq. (1); see :meth:`FusedStepper.advance`.

    Returns (status, steps taken, t, current finger buffer, monitor step count)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, sums, _ = work
    point, normal, pvel, mu, k, c, kt, ct = planes
    parts = fint.shape[0]
    if not have_forces:
        _forces_at(x, v, t, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
    for s in range(n_steps):
        t_prev = t
        dt = t_end - t if (land and s == n_steps - 1) else h
        t = t + dt
        _plane_points(t, point, pvel, p0)
        # The nodes (in parts, on threads when parallel): the step, the planes' friction states and
        # forces at the new state, the sums the monitor needs.
        if parallel:
            _node_pass_parallel(dt, x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active,
                                pl_anchor, sums)  # fmt: skip
        else:
            for q in range(parts):
                _node_part(
                    q, parts, dt, x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active,
                    pl_anchor, sums[q],
                )  # fmt: skip
        bad, mx, my, mz, p_plane = _node_totals(sums, track)
        if bad:
            fail[_F_T] = t
            fail[_F_DT] = t - t_prev
            return STATUS_NONFINITE, s + 1, t, cur, msteps + 1
        # the fingertips' friction states after the step, then the forces at the new state: the next
        # step's, and the monitor's power, volumes and energy
        status, cur, msteps = _end_step(
            x, v, t, t_prev, fingers, fstate, cur, work, monitor_on, msteps, check_every, parallel, body,
            fint, info, mass, total_mass, gvec, mon, fail, p_plane, mx, my, mz,
        )  # fmt: skip
        if status != STATUS_OK:
            return status, s + 1, t, cur, msteps
    return STATUS_OK, n_steps, t, cur, msteps


# Slots of the flags the leader and worker of a two-thread chunk meet on (softgrasp.sim.fused.spin):
# the step the leader has started (dt and the planes' points set), the steps whose node part each
# thread has finished, the steps whose body-force part the worker has finished, and stop.
_S_GO, _S_NODES0, _S_NODES1, _S_BODY1, _S_STOP = (k * STRIDE for k in range(5))
_S_SIZE = 5 * STRIDE
#: Internal status of a two-thread chunk whose worker failed (its exception is raised).
_STATUS_ABORTED = -1


@_jit
def _wait(flags, slot, value):  # pragma: no cover - compiled
    """Spin until ``flags[slot] >= value`` (True) or the stop slot is set (False)."""
    polls = 0
    while load_acquire(flags, slot) < value:
        if load_acquire(flags, _S_STOP) != 0:
            return False
        relax(polls)
        polls += 1
    return True


@_njit_nogil
def _advance_leader(n_steps, h, land, t_end, t, x, v, mass, grav, total_mass, body, planes, pl_active,
                    pl_anchor, fingers, fstate, cur, work, have_forces, monitor_on, mon, msteps, check_every,
                    gvec, fail, flags, shared):  # pragma: no cover - compiled  # fmt: skip
    """:func:`_advance` on two threads, this one's share: part 0 of the nodes and of the body forces,
    and everything serial (the steps' times, the fingertips, the monitor); :func:`_advance_worker`,
    started with the same arrays on another thread, does part 1. They meet on ``flags``
    (:data:`_S_SIZE` zeros, :mod:`softgrasp.sim.fused.spin`) three times a step: the worker starts a
    step's node part when the leader has set the step up (its dt in ``shared[0]``); the body forces
    wait until both node parts are done (the elements reach across them); the leader's checks and
    the next step wait until the worker's body part is done. The same arithmetic on the same parts
    as :func:`_advance` (the same trajectory to the bit). Sets the stop slot when it returns;
    returns as :func:`_advance` does, or :data:`_STATUS_ABORTED` when the stop slot was set by
    someone else (the worker failed). After a non-finite state the worker still computes its body
    part there (harmless: a failed chunk leaves the forces to be computed again)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, sums, _ = work
    point, normal, pvel, mu, k, c, kt, ct = planes
    if not have_forces:
        _forces_at(x, v, t, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, False)
    status = STATUS_OK
    steps = n_steps
    for s in range(n_steps):
        t_prev = t
        dt = t_end - t if (land and s == n_steps - 1) else h
        t = t + dt
        _plane_points(t, point, pvel, p0)
        shared[0] = dt
        store_release(flags, _S_GO, s + 1)
        _node_part(0, 2, dt, x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active, pl_anchor,
                   sums[0])  # fmt: skip
        store_release(flags, _S_NODES0, s + 1)
        if not _wait(flags, _S_NODES1, s + 1):
            return _STATUS_ABORTED, s, t, cur, msteps
        bad, mx, my, mz, p_plane = _node_totals(sums, track)
        if bad:
            fail[_F_T] = t
            fail[_F_DT] = t - t_prev
            status = STATUS_NONFINITE
            steps = s + 1
            msteps += 1
            break
        p_finger = 0.0
        if fingers[0]:
            cur, p_finger = _finger_step(x, v, t, fingers, fstate, cur, work, monitor_on)
        msteps += 1
        check = _check_step(monitor_on, msteps, check_every)
        _body_part(0, 2, x, v, body, check, check, fint[0], info[0])
        if not _wait(flags, _S_BODY1, s + 1):
            return _STATUS_ABORTED, s, t, cur, msteps
        if monitor_on:
            e_int, count, first = _body_totals(info)
            status = _after_step(
                x, v, t, t_prev, mass, total_mass, gvec, mon, fail, p_plane + p_finger, mx, my, mz, check,
                e_int, count, first,
            )  # fmt: skip
            if status != STATUS_OK:
                steps = s + 1
                break
    store_release(flags, _S_STOP, 1)
    return status, steps, t, cur, msteps


@_njit_nogil
def _advance_worker(x, v, mass, grav, body, planes, pl_active, pl_anchor, work, monitor_on, msteps,
                    check_every, flags, shared):  # pragma: no cover - compiled  # fmt: skip
    """The other thread of :func:`_advance_leader`: part 1 of the nodes and of the body forces, step
    after step until the leader stops. Returns the steps done."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, sums, _ = work
    s = 0
    while _wait(flags, _S_GO, s + 1):
        _node_part(1, 2, shared[0], x, v, mass, grav, fint, fplane, ffinger, x_ref, planes, p0, pl_active,
                   pl_anchor, sums[1])  # fmt: skip
        store_release(flags, _S_NODES1, s + 1)
        if not _wait(flags, _S_NODES0, s + 1):
            break
        msteps += 1
        check = _check_step(monitor_on, msteps, check_every)
        _body_part(1, 2, x, v, body, check, check, fint[1], info[1])
        store_release(flags, _S_BODY1, s + 1)
        s += 1
    return s


@_jit
def _rk4_stage(stage, x, v, xs, vs, ax, av, mass, grav, work, h):  # pragma: no cover - compiled
    """Accumulate RK4 stage ``stage`` (1-4) from the forces in the workspace (a_k = F / m at the
    stage state) and set the next stage state, as :meth:`softgrasp.sim.explicit.RK4.step`:
    ``v2 = v + h/2 a1, x2 = x + h/2 v``; ``v3 = v + h/2 a2, x3 = x + h/2 v2``;
    ``v4 = v + h a3, x4 = x + h v3``; sums ``a1 + 2 a2 + 2 a3 (+ a4)`` and
    ``v + 2 v2 + 2 v3 (+ v4)`` in that order. Updates the largest squared displacement from
    ``x_ref`` of the stage positions (the fingertip broad phase)."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, sums, _ = work
    h2 = 0.5 * h
    u2 = track[1]
    for i in range(x.shape[0]):
        m = mass[i]
        du2 = 0.0
        for d in range(3):
            a = _acceleration(i, d, m, fint, grav, fplane, ffinger, False)
            if stage == 1:
                av[i, d] = a
                ax[i, d] = v[i, d]
                vs[i, d] = v[i, d] + h2 * a
                xs[i, d] = x[i, d] + h2 * v[i, d]
            elif stage == 2:
                av[i, d] = av[i, d] + 2.0 * a
                ax[i, d] = ax[i, d] + 2.0 * vs[i, d]
                xs[i, d] = x[i, d] + h2 * vs[i, d]
                vs[i, d] = v[i, d] + h2 * a
            else:  # stage 3
                av[i, d] = av[i, d] + 2.0 * a
                ax[i, d] = ax[i, d] + 2.0 * vs[i, d]
                xs[i, d] = x[i, d] + h * vs[i, d]
                vs[i, d] = v[i, d] + h * a
            du = xs[i, d] - x_ref[i, d]
            du2 += du * du
        u2 = max(u2, du2)
    track[1] = u2


@_jit
def _advance_rk4(n_steps, h, land, t_end, t, x, v, mass, grav, total_mass, body, planes, pl_active,
                 pl_anchor, fingers, fstate, cur, work, have_forces, parallel, monitor_on, mon, msteps,
                 check_every, gvec, fail, rk):  # pragma: no cover - compiled  # fmt: skip
    """Up to ``n_steps`` classical RK4 steps (:class:`softgrasp.sim.explicit.RK4`): four force
    evaluations per step with the friction states of the step's start, then the state updates
    and the forces at the new state (the next step's first stage and the monitor's). Returns as
    :func:`_advance`."""
    fint, info, fplane, ffinger, centres, x_ref, track, p0, sums, _ = work
    xs, vs, ax, av = rk
    N = x.shape[0]
    if not have_forces:
        _forces_at(x, v, t, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
    for s in range(n_steps):
        t_prev = t
        dt = t_end - t if (land and s == n_steps - 1) else h
        h2 = 0.5 * dt
        _rk4_stage(1, x, v, xs, vs, ax, av, mass, grav, work, dt)
        _forces_at(xs, vs, t + h2, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
        _rk4_stage(2, x, v, xs, vs, ax, av, mass, grav, work, dt)
        _forces_at(xs, vs, t + h2, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
        _rk4_stage(3, x, v, xs, vs, ax, av, mass, grav, work, dt)
        _forces_at(xs, vs, t + dt, body, planes, pl_active, pl_anchor, fingers, fstate, cur, work, parallel)
        # x += dt / 6 (v + 2 v2 + 2 v3 + v4), v += dt / 6 (a1 + 2 a2 + 2 a3 + a4)
        w = dt / 6.0
        bad = False
        u2 = track[1]
        mx = 0.0
        my = 0.0
        mz = 0.0
        for i in range(N):
            m = mass[i]
            du2 = 0.0
            for d in range(3):
                a = _acceleration(i, d, m, fint, grav, fplane, ffinger, True)
                xi = x[i, d] + w * (ax[i, d] + vs[i, d])
                vi = v[i, d] + w * (av[i, d] + a)
                x[i, d] = xi
                v[i, d] = vi
                bad |= not (abs(vi) < math.inf and abs(xi) < math.inf)
                du = xi - x_ref[i, d]
                du2 += du * du
            u2 = max(u2, du2)
            mx += m * x[i, 0]
            my += m * x[i, 1]
            mz += m * x[i, 2]
        track[1] = u2
        t = t + dt
        if bad:
            fail[_F_T] = t
            fail[_F_DT] = t - t_prev
            return STATUS_NONFINITE, s + 1, t, cur, msteps + 1
        # friction states after the step, then the forces at the new state (Scene.update_contacts, forces)
        point, normal, pvel, mu, k, c, kt, ct = planes
        _plane_points(t, point, pvel, p0)
        p_plane = 0.0
        for p in range(point.shape[0]):
            p_plane += _plane_pass(
                x, v, p, p0, normal, pvel, mu, k, c, kt, ct, pl_active, pl_anchor, True, 0, N, fplane
            )
        status, cur, msteps = _end_step(
            x, v, t, t_prev, fingers, fstate, cur, work, monitor_on, msteps, check_every, parallel, body,
            fint, info, mass, total_mass, gvec, mon, fail, p_plane, mx, my, mz,
        )  # fmt: skip
        if status != STATUS_OK:
            return status, s + 1, t, cur, msteps
    return STATUS_OK, n_steps, t, cur, msteps


# ---------------------------------------------------------------------------------- Python side
def supported(body: Any, planes: list[Any], fingers: list[Any]) -> str | None:
    """Why the fused stepper cannot run this body and these interactions, or None when it can.

    It needs a polynomial stress-strain law (:func:`softgrasp.physics.forces_compiled.polynomial_coefficients`)
    and at most one fingertip interaction.
    """
    if polynomial_coefficients(body.material.law) is None:
        return f"stress-strain law {type(body.material.law).__name__} is not a polynomial"
    if len(fingers) > 1:
        return "more than one fingertip interaction"
    return None


def _f64(a: Any, shape: tuple[int, ...] | None = None) -> Array:
    """A fresh writeable C-contiguous float64 copy (one compiled signature whatever the input:
    read-only mesh arrays would make another)."""
    out = np.array(a, dtype=np.float64, order="C", copy=True)
    return out.reshape(shape) if shape is not None else out


def _i64(a: Any) -> NDArray[np.int64]:
    """A fresh writeable C-contiguous int64 copy."""
    return np.array(a, dtype=np.int64, order="C", copy=True)


def aligned_zeros(shape: tuple[int, ...], dtype: Any = np.float64) -> Array:
    """Zeros of ``shape`` (8-byte ``dtype``), C-contiguous, the data 64-byte aligned (the 4-wide
    rows of the block kernels then never straddle a cache line)."""
    n = int(np.prod(shape))
    raw = np.zeros(n + 8, dtype)
    start = (-raw.ctypes.data % 64) // 8
    return raw[start : start + n].reshape(shape)


def _host_is_x86_64() -> bool:
    """Whether the host is x86-64, where the block kernels' gain was measured."""
    return platform.machine().lower() in ("x86_64", "amd64")


def _blocks_default() -> bool:
    """:data:`BLOCKS_DEFAULT` from ``SOFTGRASP_BLOCKS`` (1/true/yes/on, 0/false/no/off) or the host."""
    value = os.environ.get("SOFTGRASP_BLOCKS", "").strip().lower()
    if not value:
        return _host_is_x86_64()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise ValueError(
        f"SOFTGRASP_BLOCKS={os.environ['SOFTGRASP_BLOCKS']!r}: use 1 (block kernels) or 0 (scalar loops), "
        "or unset it to choose by the CPU"
    )


#: Whether :func:`pack_body` selects the block kernels of :mod:`softgrasp.sim.fused.blocks` by default:
#: on x86-64, where they were measured faster than the scalar loops with every instruction set
#: Numba was told to compile for (on an AMD Zen 4: 1.58x with AVX-512, 1.51x with AVX2, 1.23x
#: with SSE2 alone, on the body forces); elsewhere the scalar loops, whose speed there is known.
#: ``SOFTGRASP_BLOCKS=1`` / ``0`` overrides (read at import).
BLOCKS_DEFAULT = _blocks_default()
#: SHA-256 of the kernel modules whose compiled code the cached kernels here inline (the block
#: kernels' IR, the contact kernels, the elastic helpers, the spin-wait atomics). Numba checks only
#: a cached function's own file for changes, never the files of the functions it calls: an edit
#: there must come with an edit here (tests/test_fused_step.py compares), or the stepper would run
#: the stale machine code of the earlier source.
_INLINED_SOURCES_SHA256 = {
    "blocks.py": "b464bc75601d1ab561186c820feb0e33a62b705bfeae0e87d6ca8956cb9138fc",
    "contact.py": "df52d63b2eb1875689239d82377f0b77e0a75f5a93b7777fee38a62d4c641a01",
    "elastic.py": "f9f85e76422adfe02f119d0231a51c9fd04a1a75480b085565cb13725914297d",
    "spin.py": "27ac392cd2fbfe5999365d7ed215697cc1054c28b37c5b886f4033e5beea1908",
}


#: A fingertip's step (detection, friction update, forces) costs about this many times the square
#: root of the body's element count in element force evaluations (measured on the rubber sphere at
#: 549, 2 196 and 7 576 nodes: 12.0, 11.9 and 8.9, with the tets carrying springs).
_FINGER_COST = 11.9


def leader_share(fingertips: int, elements: int) -> float:
    """The first of two body-force parts' share of the elements (:func:`pack_body`'s ``lead``) for a
    scene with ``fingertips`` fingertips and ``elements`` edges and tets.

    On two threads the leader computes the fingertips' step besides the first part, the worker the
    second part alone, at the same time: the leader's smaller share ``1/2 - n C / sqrt(E)``
    (:data:`_FINGER_COST` C) evens their work out (at 2 196 nodes with one fingertip 0.42; 0.43
    measured the best of 0.40-0.50 before the tets carried springs: 6-8 % more steps a second than
    0.5); at least a quarter. The split is
    a property of the scene, never of the threads or of timings: one thread computes the same two
    parts and gets the same sums to the bit."""
    if fingertips <= 0 or elements <= 0:
        return 0.5
    return max(0.25, 0.5 - fingertips * _FINGER_COST / math.sqrt(elements))


#: How far past the first element not yet placed :func:`_block_order` looks for elements to fill a
#: block with.
_ORDER_WINDOW = 400


@_jit
def _block_order(nodes, window):  # pragma: no cover - compiled
    """An order of the elements (rows of ``nodes``, (n, k)) in which the blocks of :data:`BLOCK`
    consecutive elements share no node wherever a greedy pass finds one: block by block, the next
    elements in the given order that share no node with those already in the block, looking at
    most ``window`` elements past the first one not yet placed; a block still short takes the next
    elements as they come. The elements stay near their place, and with them the locality of their
    nodes. Returns the permutation (n,)."""
    n, k = nodes.shape
    taken = np.zeros(n, np.bool_)
    order = np.empty(n, np.int64)
    used = np.empty(_BLOCK * k, np.int64)
    pos = 0
    start = 0
    while pos < n:
        while taken[start]:
            start += 1
        filled = 0
        nu = 0
        for i in range(start, min(n, start + window)):
            if filled == _BLOCK:
                break
            if taken[i]:
                continue
            clash = False
            for a in range(k):
                for u in range(nu):
                    if used[u] == nodes[i, a]:
                        clash = True
            if clash:
                continue
            for a in range(k):
                used[nu] = nodes[i, a]
                nu += 1
            taken[i] = True
            order[pos] = i
            pos += 1
            filled += 1
        i = start
        while filled < _BLOCK and pos < n:
            if not taken[i]:
                taken[i] = True
                order[pos] = i
                pos += 1
                filled += 1
            i += 1
    return order


# A tet's vertex orders that bring each of its six edges to (0, 1), all even permutations of
# (0, 1, 2, 3) (the signed volume keeps its sign).
_EDGE_FIRST = np.array(
    [[0, 1, 2, 3], [0, 2, 3, 1], [0, 3, 1, 2], [1, 2, 0, 3], [1, 3, 2, 0], [2, 3, 0, 1]], dtype=np.int64
)


@_jit
def _carried_springs(tets, edges, n_nodes, n_carrying):  # pragma: no cover - compiled
    """The spring each of the first ``n_carrying`` tets carries in the tets-with-a-spring kernels
    (:data:`softgrasp.sim.fused.blocks.tet_spring_block`): each tet in turn takes, of its edges whose
    spring no tet has taken yet, the one with the fewest tets left to take it (the first such).

    Returns (each tet's vertex order bringing its spring to vertices 0 and 1, (M, 4); each tet's
    spring, (M,), -1 for none; each spring's tet, (E,), -1 for none)."""
    E = edges.shape[0]
    start = np.zeros(n_nodes + 1, np.int64)  # the edges by their lower node
    for e in range(E):
        start[min(edges[e, 0], edges[e, 1]) + 1] += 1
    for i in range(n_nodes):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    upper = np.empty(E, np.int64)
    edge_of = np.empty(E, np.int64)
    for e in range(E):
        lo = min(edges[e, 0], edges[e, 1])
        upper[fill[lo]] = max(edges[e, 0], edges[e, 1])
        edge_of[fill[lo]] = e
        fill[lo] += 1
    M = tets.shape[0]
    local = np.full((M, 6), -1, np.int64)  # each tet's edges in _EDGE_FIRST's order
    left = np.zeros(E, np.int64)  # carrying tets still to come, per edge
    for t in range(min(M, n_carrying)):
        for r in range(6):
            a = tets[t, _EDGE_FIRST[r, 0]]
            b = tets[t, _EDGE_FIRST[r, 1]]
            lo = min(a, b)
            hi = max(a, b)
            for q in range(start[lo], start[lo + 1]):
                if upper[q] == hi:
                    local[t, r] = edge_of[q]
                    left[edge_of[q]] += 1
                    break
    owner = np.full(E, -1, np.int64)
    perm = np.zeros((M, 4), np.int64)
    carried = np.full(M, -1, np.int64)
    for t in range(M):
        perm[t] = _EDGE_FIRST[0]
        if t >= n_carrying:
            continue
        best = -1
        for r in range(6):
            e = local[t, r]
            if e >= 0 and owner[e] < 0 and (best < 0 or left[e] < left[local[t, best]]):
                best = r
        for r in range(6):
            if local[t, r] >= 0:
                left[local[t, r]] -= 1
        if best >= 0:
            perm[t] = _EDGE_FIRST[best]
            owner[local[t, best]] = t
            carried[t] = local[t, best]
    return perm, carried, owner


def pack_body(body: Any, blocks: bool | None = None, lead: float = 0.5) -> tuple:
    """The body's static data in the layout of the fused body-force kernels (:func:`_body_part`).

    Parameters
    ----------
    body:
        The :class:`softgrasp.physics.body.Body` (polynomial stress-strain law).
    blocks:
        Whether the forces go through the block kernels of :mod:`softgrasp.sim.fused.blocks` (eight
        elements a time); None: :data:`BLOCKS_DEFAULT`.
    lead:
        The first part's share of the elements when the forces are computed in two parts
        (:func:`leader_share`), in (0, 1).

    Returns
    -------
    tuple
        ``(eq, ep, tq, tp, a2, a3, damped, kappa, barrier, blocks, ep8, tp8, n, order, lead, carry)``: the
        edges' nodes times 4, (2E,) unsigned; their L0 [m], 1 / L0 [1/m], k L0 [N] and dashpot c
        [N s/m] side by side, (4E,) (c = 0 undamped); the tets' nodes times 4, (4M,) unsigned;
        their 1 / (6 V0) [1/m^3] and V0 [m^3], (2M,); the law's ``a2``, ``a3``
        (:func:`softgrasp.physics.forces_compiled.polynomial_coefficients`); whether the dashpots act;
        ``kappa`` [Pa]; whether the volume term is the barrier; whether the block kernels are used;
        (1 / L0, k L0, c, L0) and (1 / (6 V0), V0) a block at a time
        (:func:`softgrasp.sim.fused.blocks.block_params`); the body's node count; each packed tet's
        index in the mesh (M,); ``lead``; whether the tets carry springs (below).

        For the block kernels the edges and tets are packed in :func:`_block_order` (a block's
        elements share no node, wherever a greedy pass finds such: its read-modify-writes of the
        forces then do not wait for one another; 7 % off the body forces on the reference
        machine); the scalar loops keep the mesh's order (the reference kernels' sums to the bit).
        With the volume term, each tet of a whole block also carries a spring when one of its
        edges has a spring no tet took before it (none: an empty place, no force, no energy)
        (:func:`_carried_springs`; all 9 720 such tets at 2 196 nodes, 3 251 of the 12 971 springs
        left for the springs' kernels): its vertices reordered (an even permutation) so that the
        spring joins vertices 0 and 1, and ``tp8`` holds the spring's columns after the tet's
        (:data:`softgrasp.sim.fused.blocks.TET_SPRING_COLUMNS`); ``eq``, ``ep`` and ``ep8`` then
        hold the springs left. Body forces 57 -> 53 us on one thread at 2 196 nodes.
    """
    if not 0.0 < lead < 1.0:
        raise ValueError(f"pack_body: the first part's share must lie in (0, 1), got {lead}")
    a2, a3 = polynomial_coefficients(body.material.law)  # type: ignore[misc]
    damped = body.damping_time > 0
    rest = np.asarray(body.rest_length, dtype=np.float64)
    c = np.asarray(body.damping, dtype=np.float64) if damped else np.zeros_like(rest)
    vol = np.asarray(body.mesh.volumes, dtype=np.float64)
    index = np.uint32 if 4 * body.n_nodes < 2**32 else np.uint64
    kl0 = np.asarray(body.stiffness, dtype=np.float64) * rest
    use_blocks = BLOCKS_DEFAULT if blocks is None else bool(blocks)
    edges = np.asarray(body.edges, dtype=np.int64)
    tets = np.asarray(body.mesh.tets, dtype=np.int64)
    carry = use_blocks and float(body.kappa) != 0.0
    if use_blocks:
        to = _block_order(tets, _ORDER_WINDOW)
        tets, vol = tets[to], vol[to]
    else:
        to = np.arange(len(tets))
    tp8 = block_params([1.0 / (6.0 * vol), vol])
    if carry:  # the tets of whole blocks carry a spring each; the others go through the springs' kernels
        perm, carried, owner = _carried_springs(tets, edges, body.n_nodes, _BLOCK * (len(tets) // _BLOCK))
        tets = np.take_along_axis(tets, perm, axis=1)
        on = carried >= 0
        k = np.where(on, carried, 0)
        tp8 = block_params(
            [
                1.0 / (6.0 * vol),
                vol,
                np.where(on, 1.0 / rest[k], 1.0),  # none: no force, no energy
                np.where(on, kl0[k], 0.0),
                np.where(on, c[k], 0.0),
                np.where(on, rest[k], 1.0),
            ]
        )
        alone = np.flatnonzero(owner < 0)
        edges, rest, kl0, c = edges[alone], rest[alone], kl0[alone], c[alone]
    if use_blocks:
        eo = _block_order(edges, _ORDER_WINDOW)
        edges, rest, kl0, c = edges[eo], rest[eo], kl0[eo], c[eo]
    return (
        np.ascontiguousarray(4 * edges, dtype=index).ravel(),
        np.ascontiguousarray(np.stack([rest, 1.0 / rest, kl0, c], axis=1)).ravel(),
        np.ascontiguousarray(4 * tets, dtype=index).ravel(),
        np.ascontiguousarray(np.stack([1.0 / (6.0 * vol), vol], axis=1)).ravel(),
        float(a2),
        float(a3),
        bool(damped),
        float(body.kappa),
        bool(body.barrier),
        use_blocks,
        block_params([1.0 / rest, kl0, c, rest]),
        tp8,
        int(body.n_nodes),
        np.ascontiguousarray(to, dtype=np.int64),
        float(lead),
        carry,
    )


#: pack_body's tuples by body, then by (block kernels, lead): a body's packing is computed once
#: (~1.8 ms at 2 196 nodes, most of it the block order) and shared by its steppers, whose kernels
#: only read it.
_PACKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_PACKED_LOCK = threading.Lock()


def _packed(body: Any, lead: float) -> tuple:
    """:func:`pack_body` of ``body`` with the default kernels and ``lead``, computed once a body."""
    key = (BLOCKS_DEFAULT, float(lead))
    with _PACKED_LOCK:
        per_body = _PACKED.setdefault(body, {})
        if key not in per_body:
            per_body[key] = pack_body(body, lead=lead)
        return per_body[key]


@dataclass
class Failure:
    """What stopped :meth:`FusedStepper.advance`.

    Attributes
    ----------
    status: :data:`STATUS_NONFINITE`, :data:`STATUS_INVERTED` or :data:`STATUS_ENERGY`.
    t: time of the failing state [s].  dt: length of the step that reached it [s].
    count, first: inverted tets and the lowest mesh index among them (:data:`STATUS_INVERTED`).
    excess, scale: the energy test's excess and scale [J] (:data:`STATUS_ENERGY`).
    """

    status: int
    t: float
    dt: float
    count: int = 0
    first: int = -1
    excess: float = 0.0
    scale: float = 0.0


class FusedStepper:
    """Explicit steps (semi-implicit Euler or RK4) of a body with plane and fingertip contacts in
    compiled chunks.

    The stepper owns copies of the positions, velocities and friction states; :meth:`advance` moves
    them on; :meth:`arrays`, :meth:`plane_states` and :meth:`finger_state` read them out (copies).

    Parameters
    ----------
    body:
        The :class:`softgrasp.physics.body.Body` (polynomial stress-strain law).
    planes:
        :class:`softgrasp.physics.planes.PlaneContact` interactions, with their states ``plane_states``
        (:class:`~softgrasp.physics.planes.PlaneState`).
    fingers:
        A :class:`softgrasp.physics.fingertip.contact.FingertipContact` or None, with its state
        ``finger_state`` (:class:`~softgrasp.physics.fingertip.contact.FingerState`).
    x, v, t:
        Initial positions [m] (N, 3), velocities [m/s] (N, 3) and time [s].
    monitor:
        A :class:`softgrasp.sim.stability.BlowupMonitor` whose checks run inside the loop and whose
        bookkeeping (``steps``, ``balance``) is kept up to date after every :meth:`advance`; None for
        no checks.
    method:
        ``"semi-implicit"`` or ``"rk4"``.
    parts:
        Parts the body forces and node updates are split in (:data:`PARTS`).

    Attributes
    ----------
    threads: threads the next :meth:`advance` computes on (1: the parts one after the other).
    failure: what stopped the last :meth:`advance` early (:class:`Failure`), or None.
    """

    def __init__(
        self,
        body: Any,
        planes: list[Any],
        plane_states: list[Any],
        fingers: Any | None,
        finger_state: Any | None,
        x: Array,
        v: Array,
        t: float,
        monitor: Any | None = None,
        *,
        method: str = "semi-implicit",
        parts: int = PARTS,
    ) -> None:
        if method not in METHODS:
            raise ValueError(f"the fused stepper runs {' or '.join(METHODS)}, not {method!r}")
        self.method = method
        reason = supported(body, planes, [] if fingers is None else [fingers])
        if reason is not None:
            raise ValueError(f"the fused stepper cannot run this scene: {reason}")
        N = body.n_nodes
        self.body = body
        self.t = float(t)
        # positions and velocities (N, 4), the fourth column zero: the rows the block kernels load
        self.x = aligned_zeros((N, 4))
        self.v = aligned_zeros((N, 4))
        self.x[:, :3] = _f64(x, (N, 3))
        self.v[:, :3] = _f64(v, (N, 3))
        # The leader's smaller share pays only where a leader does the fingertips beside its part
        # (semi-implicit on two threads); RK4's stages split their parts on Numba's threads, the
        # fingertips after them: even parts there. Chosen by the method, never by the threads.
        tips = 0 if fingers is None or method != "semi-implicit" else len(fingers.fingertips)
        self._body = _packed(body, leader_share(tips, len(body.edges) + len(body.mesh.tets)))
        self.parts = max(1, int(parts))
        self.threads = 1
        self._mass = _f64(body.mass)
        # m g and the contact forces as (N, 4) rows too (fourth column zero), like the positions
        self._grav = aligned_zeros((N, 4))
        self._grav[:, :3] = body.mass[:, None] * np.asarray(body.gravity, dtype=np.float64)[None, :]
        self._gvec = _f64(body.gravity, (3,))
        self._total_mass = float(body.mass.sum())
        self._fint = aligned_zeros((self.parts, N, 4))
        # a part's energy, inverted count and first inverted tet; its row padded to a cache line
        # of its own (two threads write them)
        self._info = aligned_zeros((self.parts, 8))
        self._fplane = aligned_zeros((N, 4))
        self._ffinger = aligned_zeros((N, 4))
        self._have_forces = False
        # planes: (P, ...) parameter arrays and states
        P = len(planes)
        self._pl = [np.zeros((P, 3)), np.zeros((P, 3)), np.zeros((P, 3)), np.zeros(P)]
        pk, pc, pkt, pct = (np.zeros((P, N)) for _ in range(4))
        self.pl_active = np.zeros((P, N), np.bool_)
        self.pl_anchor = np.zeros((P, N, 3))
        for p, (inter, st) in enumerate(zip(planes, plane_states, strict=True)):
            self._pl[0][p] = inter.plane.point
            self._pl[1][p] = inter.plane.normal
            self._pl[2][p] = inter.plane.velocity
            self._pl[3][p] = inter.mu
            # the same per-node coefficients as PlaneContact.forces / update
            pk[p], pc[p], pkt[p], pct[p] = inter._coeffs(body)
            self.pl_active[p] = st.active
            self.pl_anchor[p] = st.anchor
        self._pl = (*self._pl, pk, pc, pkt, pct)
        # fingertips: constant geometry and parameters, double-buffered state
        if fingers is not None:
            kw = fingers._compiled_kwargs(body, 0.0)  # the arguments FingertipContact's kernels get
            tips = fingers.fingertips
            nf, F = len(tips), len(body.mesh.facets)
            self._fg = (
                True,
                _i64(kw["facets"]),
                _i64(kw["boundary_nodes"]),
                _i64(kw["indptr"]),
                _i64(kw["indices"]),
                float(kw["reach"]),
                _f64([f.centre for f in tips], (nf, 3)),
                _f64([f.velocity for f in tips], (nf, 3)),
                _f64([f.omega for f in tips], (nf, 3)),
                _f64(kw["radii"], (nf,)),
                _f64(kw["K"], (nf,)),
                _f64(fingers.damping(), (nf,)),
                bool(kw["closest"]),
                float(kw["inside_tol"]),
                float(kw["mu"]),
                float(kw["exponent"]),
                fingers.params.damping == "hunt-crossley",
                bool(kw["patch"]),
                float(kw["ratio"]),
                float(kw["min_depth_ratio"]),
            )
            st = finger_state
            act = np.asarray(st.active, dtype=np.bool_)
            self.f_active = np.zeros((2, nf, F), np.bool_)
            self.f_anchor = np.zeros((2, nf, F, 3))
            self.f_offset = np.zeros((2, nf, F, 3))
            self.f_slip = np.zeros((2, nf, F, 3))
            self.f_memory = np.zeros((2, nf, 3))
            # buffer 0 holds the state; entries of inactive pairs are never read and kept zero so that
            # a buffer can be cleared through its active flags
            self.f_active[0] = act
            self.f_anchor[0] = np.where(act[:, :, None], st.anchor, 0.0)
            self.f_offset[0] = np.where(act[:, :, None], st.offset, 0.0)
            self.f_slip[0] = np.where(act[:, :, None], st.slip, 0.0)
            self.f_memory[0] = st.memory
        else:
            z1, z2 = np.zeros(1), np.zeros((1, 3))
            zi = np.zeros(1, np.int64)
            self._fg = (
                False, np.zeros((1, 3), np.int64), zi, zi, zi, 0.0, z2, z2, z2, z1, z1, z1,
                0.0, 0.0, 0.0, 1.0, False, False, 0.0, 0.0,
            )  # fmt: skip
            nf, F = 1, 1
            self.f_active = np.zeros((2, 1, 1), np.bool_)
            self.f_anchor = np.zeros((2, 1, 1, 3))
            self.f_offset = np.zeros((2, 1, 1, 3))
            self.f_slip = np.zeros((2, 1, 1, 3))
            self.f_memory = np.zeros((2, 1, 3))
        self._cur = 0
        self._fstate = (self.f_active, self.f_anchor, self.f_slip, self.f_memory, self.f_offset)
        # RK4: stage positions and velocities, and the weighted sums of the stage velocities and
        # accelerations
        self._rk = tuple(aligned_zeros((N, 4) if method == "rk4" else (1, 4)) for _ in range(4))
        # workspace: force buffers, fingertip centres, the fingertip broad phase's bookkeeping (see
        # _finger_reach: its reference positions, track, and near list, listed at the first use),
        # the planes' points now
        track = np.zeros(3 + 3 * nf)
        track[0] = _max_facet_edge(self.x, _i64(body.mesh.facets))
        track[2] = -1.0
        self._work = (
            self._fint, self._info, self._fplane, self._ffinger, np.zeros((nf, 3)), self.x.copy(), track,
            np.zeros((P, 3)),
            aligned_zeros((self.parts, 8)),  # the node parts' sums (6), a cache line each
            np.zeros(max(1, len(self._fg[2])), np.int64),
        )  # fmt: skip
        # monitor
        self.monitor = monitor
        self._mon = np.zeros(_M_SIZE)
        self._fail = np.zeros(6)
        if monitor is not None:
            b = monitor.balance
            self._mon[:] = (
                b.t, b.power, b.work, b.abs_work, b.gravity_work,
                monitor.energy0, monitor.scale0, monitor.energy_factor, *monitor.com0,
            )  # fmt: skip
        self.failure: Failure | None = None
        self._broken = False

    # ------------------------------------------------------------------ stepping
    def advance(self, n_steps: int, dt: float, t_end: float | None = None) -> int:
        """Take ``n_steps`` steps of ``dt`` [s] (the last one ending exactly at ``t_end`` [s] when
        given: ``t_end - t``, as :func:`softgrasp.sim.explicit.simulate` lands).

        Returns
        -------
        int
            The steps taken: ``n_steps``, or fewer when a blow-up check failed (then
            :attr:`failure` says which, and the stepper's state is that of the failed step).
        """
        if self._broken:
            raise RuntimeError(
                "this fused stepper failed in an earlier advance() and its state is undefined: make a new one"
            )
        if n_steps <= 0:
            return 0
        mon = self.monitor
        parallel = self.threads > 1 and self.parts > 1
        # semi-implicit steps in two parts: a leader and a worker thread for the whole chunk;
        # otherwise Numba's threads, parallel region by parallel region
        two = self.parts == 2 and numba.config.NUMBA_NUM_THREADS >= 2
        pair = parallel and self.method == "semi-implicit" and two
        pool = parallel and not pair
        previous = numba.get_num_threads()
        if pool:
            numba.set_num_threads(min(self.threads, self.parts, numba.config.NUMBA_NUM_THREADS))
        try:
            status, steps, t, cur, msteps = self._call(n_steps, dt, t_end, parallel, pair)
        except BaseException:
            # positions, velocities and contact states moved on while the time and the state
            # cursor did not: refuse to go on from there
            self._broken = True
            raise
        finally:
            if pool:
                numba.set_num_threads(previous)
        self.t = float(t)
        self._cur = int(cur)
        self._have_forces = status == STATUS_OK
        if mon is not None:
            mon.steps = int(msteps)
            b = mon.balance
            b.t, b.power, b.work, b.abs_work, b.gravity_work = (float(a) for a in self._mon[:5])
        if status != STATUS_OK:
            f = self._fail
            self.failure = Failure(
                int(status), float(f[_F_T]), float(f[_F_DT]), int(f[_F_COUNT]), int(f[_F_FIRST]),
                float(f[_F_EXCESS]), float(f[_F_SCALE]),
            )  # fmt: skip
        return int(steps)

    def _call(self, n_steps: int, dt: float, t_end: float | None, parallel: bool, pair: bool) -> tuple:
        mon = self.monitor
        monitor = (mon is not None, self._mon, int(mon.steps if mon is not None else 0),
                   int(mon.check_every if mon is not None else 1))  # fmt: skip
        head = (
            int(n_steps), float(dt), t_end is not None, float(t_end if t_end is not None else 0.0), self.t,
            self.x, self.v, self._mass, self._grav, self._total_mass, self._body, self._pl, self.pl_active,
            self.pl_anchor, self._fg, self._fstate, self._cur, self._work, self._have_forces,
        )  # fmt: skip
        tail = (*monitor, self._gvec, self._fail)
        if pair:
            return self._call_pair(head, tail, monitor)
        if self.method == "rk4":
            return _advance_rk4(*head, parallel, *tail, self._rk)
        return _advance(*head, parallel, *tail)

    def _call_pair(self, head: tuple, tail: tuple, monitor: tuple) -> tuple:
        """:func:`_advance_leader` here on :func:`_call`'s arguments and :func:`_advance_worker` on
        a thread of its own."""
        monitor_on, _, msteps, check_every = monitor
        flags = aligned_zeros((_S_SIZE,), np.int64)
        shared = np.zeros(1)
        failed: list[BaseException] = []

        def worker() -> None:
            try:
                _advance_worker(
                    self.x, self.v, self._mass, self._grav, self._body, self._pl, self.pl_active,
                    self.pl_anchor, self._work, monitor_on, msteps, check_every, flags, shared,
                )  # fmt: skip
            except BaseException as exc:  # the leader must not wait for a thread that is gone
                failed.append(exc)
                flags[_S_STOP] = 1

        thread = threading.Thread(target=worker, name="softgrasp-fused-worker", daemon=True)
        thread.start()
        try:
            result = _advance_leader(*head, *tail, flags, shared)
        finally:
            flags[_S_STOP] = 1
            thread.join()
        if failed:
            raise RuntimeError("the fused stepper's second thread failed") from failed[0]
        if result[0] == _STATUS_ABORTED:  # the worker set the stop slot without failing: a defect
            raise RuntimeError("the fused stepper's second thread stopped before the leader")
        return result

    # ------------------------------------------------------------------ reading out
    def arrays(self) -> tuple[Array, Array, float]:
        """Copies of the positions [m] and velocities [m/s] (N, 3), and the time [s]."""
        return self.x[:, :3].copy(), self.v[:, :3].copy(), self.t

    def plane_states(self, templates: list[Any]) -> list[Any]:
        """The planes' friction states: ``templates`` (their states at the start) with ``active``
        and ``anchor`` replaced by copies of the current ones."""
        return [
            replace(st, active=self.pl_active[p].copy(), anchor=self.pl_anchor[p].copy())
            for p, st in enumerate(templates)
        ]

    def finger_state(self, template: Any) -> Any:
        """The fingertips' contact state (``template`` with its arrays replaced by copies)."""
        c = self._cur
        return replace(
            template,
            active=self.f_active[c].copy(),
            anchor=self.f_anchor[c].copy(),
            offset=self.f_offset[c].copy(),
            slip=self.f_slip[c].copy(),
            memory=self.f_memory[c].copy(),
        )
