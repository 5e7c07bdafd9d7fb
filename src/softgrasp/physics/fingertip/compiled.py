"""The fingertip contact's compiled entry points: detection, forces and friction update in one call each.

* :func:`detect_arrays` (:mod:`softgrasp.physics.fingertip.detect`): the touching pairs (Sec. 3.1).
* :func:`fingertip_pair_laws`: each given pair's normal force, friction, weight, k_t, stick and
  Coulomb cap (the per-pair values of :func:`fingertip_forces`; what the contact's reports and
  Jacobian read).
* :func:`fingertip_forces`: detection, relative velocity (Eq. 1-8), normal force (Eq. 9-14) with
  the patch or literal rule, elastic-slider friction with the Coulomb cap (Eq. 15-16, Algorithm 1)
  and the nodal distribution (Eq. 17-20) of
  :meth:`softgrasp.physics.fingertip.contact.FingertipContact.forces`, in one compiled call;
  :func:`fingertip_update` likewise for the friction state update (Algorithm 1) of
  :meth:`~softgrasp.physics.fingertip.contact.FingertipContact.update`, and :func:`fingertip_static_forces`
  for the forces at rest, of the touching pairs or of a pinned pair set (the static solver's
  residual and its exact Newton product, one compiled call each).

The per-pair laws are in :mod:`softgrasp.physics.fingertip.forces` (normal force, friction cap,
distribution) and :mod:`softgrasp.physics.fingertip.friction` (the elastic slider); Algorithm 1's
state update of the touching pairs is :func:`_update_pairs` here.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from softgrasp import jitcache
from softgrasp.physics.fingertip.detect import _detect, _geometry_args, _pinned_values
from softgrasp.physics.fingertip.forces import (
    _finger_laws,
    _normal_force,
    _pair_forces,
    _pair_table,
    _pair_normal_law,
    _patch,
    _weight_depth,
)
from softgrasp.physics.fingertip.friction import _stick
from softgrasp.physics.fingertip.laws import LAW_COLUMNS

__all__ = ["fingertip_forces", "fingertip_pair_laws", "fingertip_static_forces", "fingertip_update"]

_jit = jitcache.jit(fastmath=False, error_model="numpy")


def _law_args(law, closest, inside_tol, mu, exponent, patch, ratio, min_depth_ratio) -> tuple:
    """The contact law's arguments of the compiled kernels, as the types they are compiled for."""
    return (
        np.ascontiguousarray(law, dtype=np.float64).reshape(-1, LAW_COLUMNS),
        bool(closest),
        float(inside_tol),
        float(mu),
        float(exponent),
        bool(patch),
        float(ratio),
        float(min_depth_ratio),
    )


def _state_args(active, anchor, offset) -> tuple:
    """The friction state's pair arrays (active, anchor, offset) as the compiled kernels take them."""
    f64 = np.float64
    return (
        np.ascontiguousarray(active, dtype=np.bool_),
        np.ascontiguousarray(anchor, dtype=f64),
        np.ascontiguousarray(offset, dtype=f64),
    )


@_jit
def _fingertip_forces(
    x,
    v,
    facets,
    corners,
    boundary,
    indptr,
    indices,
    reach,
    centres,
    radii,
    velocities,
    omegas,
    law,
    C,
    closest,
    inside_tol,
    mu,
    n_exp,
    hunt_crossley,
    patch,
    ratio,
    min_depth_ratio,
    active,
    anchor,
    offset,
    memory,
    out,
):  # pragma: no cover - compiled
    """Dynamic contact forces added to ``out`` (N, 3) (or wider: columns 0-2); returns the number of
    touching pairs."""
    finger, facet, val = _detect(
        x, facets, corners, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
    )
    _pair_forces(
        finger, facet, val, x, v, facets, centres, radii, velocities, omegas, law, C, mu, n_exp,
        hunt_crossley, patch, ratio, min_depth_ratio, active, anchor, offset, memory, False, out,
    )  # fmt: skip
    return finger.shape[0]


@_jit
def _static_forces(
    x, facets, corners, boundary, indptr, indices, reach, centres, radii, law, closest, inside_tol, mu, n_exp,
    patch, ratio, min_depth_ratio, active, anchor, offset, memory, pinned, finger, facet, out,
):  # pragma: no cover - compiled
    """Contact forces at rest added to ``out`` (N, 3), of the touching pairs (detected), or with
    ``pinned`` of the given pairs (finger, facet) followed to ``x``."""
    if pinned:
        val = _pinned_values(x, facets, corners, centres, radii, finger, facet, closest)
    else:
        finger, facet, val = _detect(
            x, facets, corners, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
        )
    # At rest (static=True) the loop reads no velocities: x, centres and radii stand in for v, the
    # fingertips' velocities and spins, and C (which only multiplies the zero penetration rate).
    # The flags as np.bool_, not literals: the pair law then compiles once for every caller.
    _pair_forces(
        finger, facet, val, x, x, facets, centres, radii, centres, centres, law, radii, mu, n_exp,
        np.bool_(False), patch, ratio, min_depth_ratio, active, anchor, offset, memory, np.bool_(True), out,
    )  # fmt: skip


@_jit
def _fingertip_update(
    x,
    facets,
    corners,
    boundary,
    indptr,
    indices,
    reach,
    centres,
    radii,
    law,
    closest,
    inside_tol,
    mu,
    n_exp,
    patch,
    ratio,
    min_depth_ratio,
    active,
    anchor,
    offset,
    slip,
    memory,
    new_active,
    new_anchor,
    new_offset,
    new_slip,
    new_memory,
):  # pragma: no cover - compiled
    """Algorithm 1's state update into the zeroed ``new_*`` arrays; returns the pair count."""
    finger, facet, val = _detect(
        x, facets, corners, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
    )
    return _update_pairs(
        finger, facet, val, x, facets, centres, radii, law, mu, n_exp, patch, ratio, min_depth_ratio, active,
        anchor, offset, slip, memory, new_active, new_anchor, new_offset, new_slip, new_memory,
    )  # fmt: skip


@_jit
def _update_pairs(
    finger, facet, val, x, facets, centres, radii, law, mu, n_exp, patch, ratio, min_depth_ratio, active,
    anchor, offset, slip, memory, new_active, new_anchor, new_offset, new_slip, new_memory,
):  # fmt: skip  # pragma: no cover - compiled
    """:func:`_fingertip_update` on the touching pairs ``finger, facet, val`` found by :func:`_detect`
    (the fused stepper detects once for the update and the forces at the same state)."""
    nf = centres.shape[0]
    deep, total = _patch(finger, val, nf)
    fl = _finger_laws(deep, val, radii, law, n_exp, ratio, min_depth_ratio)
    wsum = np.zeros(nf)
    for p in range(finger.shape[0]):
        f = finger[p]
        j = facet[p]
        w, depth = _weight_depth(p, f, val, deep, total, patch)
        F, _, _, dn, kt = _pair_normal_law(p, f, val, radii, law, n_exp, ratio, min_depth_ratio, patch, fl)
        elastic = _normal_force(depth, F, dn, 0.0, 0.0, False)
        sx, sy, sz, cont, ax, ay, az = _stick(
            p, f, j, val, x, facets, centres, active, anchor, offset, memory
        )
        ux = slip[f, j, 0] if cont else 0.0
        uy = slip[f, j, 1] if cont else 0.0
        uz = slip[f, j, 2] if cont else 0.0
        if mu > 0.0:
            lim = mu * w * elastic
            s_norm = math.sqrt(sx * sx + sy * sy + sz * sz)
            keff = w * kt
            if keff * s_norm > lim:  # slip: the stick is cut back to the Coulomb limit
                r = lim / (keff * s_norm)
                nsx = sx * r
                nsy = sy * r
                nsz = sz * r
                ux += sx - nsx
                uy += sy - nsy
                uz += sz - nsz
                sx = nsx
                sy = nsy
                sz = nsz
        else:
            sx = 0.0
            sy = 0.0
            sz = 0.0
        # the anchor stays (a new pair's at its contact point); the offset takes the slip
        for m in range(3):
            new_anchor[f, j, m] = anchor[f, j, m] if cont else val[p, m]
        new_offset[f, j, 0] = centres[f, 0] - ax - sx
        new_offset[f, j, 1] = centres[f, 1] - ay - sy
        new_offset[f, j, 2] = centres[f, 2] - az - sz
        new_active[f, j] = True
        new_slip[f, j, 0] = ux
        new_slip[f, j, 1] = uy
        new_slip[f, j, 2] = uz
        wsum[f] += w
        new_memory[f, 0] += w * sx
        new_memory[f, 1] += w * sy
        new_memory[f, 2] += w * sz
    for f in range(nf):
        ws = max(wsum[f], 1e-300)
        new_memory[f, 0] /= ws
        new_memory[f, 1] /= ws
        new_memory[f, 2] /= ws
    return finger.shape[0]


def fingertip_forces(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    facets: NDArray[np.int64],
    corners: NDArray[np.float64] | None,
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    velocities: NDArray[np.float64],
    omegas: NDArray[np.float64],
    law: NDArray[np.float64],
    C: NDArray[np.float64],
    *,
    closest: bool,
    inside_tol: float,
    mu: float,
    exponent: float,
    hunt_crossley: bool,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    memory: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Contact forces on the nodes [N], (N, 3), of fingertips (centres, radii, velocities, omegas,
    normal law ``law`` (n_f, 6) as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.law_table` gives it, damping C
    [N s/m]) with friction state (active
    (n_f, F), anchor (n_f, F, 3), offset (n_f, F, 3) [m], memory (n_f, 3) [m]); parameters as in
    :class:`softgrasp.physics.fingertip.params.ContactParams` (``ratio`` = k_t / k_n); ``corners``
    the mesh's corner normals for the smooth surface's normal, None for the facets'
    (:func:`~softgrasp.physics.fingertip.detect.detect_arrays`)."""
    f64 = np.float64
    geometry = _geometry_args(x, facets, corners, boundary_nodes, indptr, indices, reach, centres, radii)
    out = np.zeros_like(geometry[0])
    _fingertip_forces(
        geometry[0],
        np.ascontiguousarray(v, dtype=f64),
        *geometry[1:],
        np.ascontiguousarray(velocities, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(omegas, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(law, dtype=f64).reshape(-1, LAW_COLUMNS),
        np.ascontiguousarray(C, dtype=f64).ravel(),
        bool(closest),
        float(inside_tol),
        float(mu),
        float(exponent),
        bool(hunt_crossley),
        bool(patch),
        float(ratio),
        float(min_depth_ratio),
        np.ascontiguousarray(active, dtype=np.bool_),
        np.ascontiguousarray(anchor, dtype=f64),
        np.ascontiguousarray(offset, dtype=f64),
        np.ascontiguousarray(memory, dtype=f64),
        out,
    )
    return out


def fingertip_static_forces(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    corners: NDArray[np.float64] | None,
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    law: NDArray[np.float64],
    *,
    closest: bool,
    inside_tol: float,
    mu: float,
    exponent: float,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    memory: NDArray[np.float64],
    pairs: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None,
) -> NDArray[np.float64]:
    """Contact forces at rest on the nodes [N], (N, 3), as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.static_forces` (no relative velocity: no
    damping; a slipping pair's stick force capped at mu f_n): of the touching pairs, or of the
    given ``pairs`` (finger (k,), facet (k,)) followed to ``x`` whether they touch there or not
    (:meth:`~softgrasp.physics.fingertip.contact.FingertipContact.pinned_static_forces`). Arguments as
    :func:`fingertip_forces`."""
    f64, i64 = np.float64, np.int64
    geometry = _geometry_args(x, facets, corners, boundary_nodes, indptr, indices, reach, centres, radii)
    out = np.zeros_like(geometry[0])
    finger, facet = (np.zeros(0, i64), np.zeros(0, i64)) if pairs is None else pairs
    _static_forces(
        *geometry,
        *_law_args(law, closest, inside_tol, mu, exponent, patch, ratio, min_depth_ratio),
        *_state_args(active, anchor, offset),
        np.ascontiguousarray(memory, dtype=f64),
        pairs is not None,
        np.ascontiguousarray(finger, dtype=i64),
        np.ascontiguousarray(facet, dtype=i64),
        out,
    )
    return out


def fingertip_update(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    corners: NDArray[np.float64] | None,
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    law: NDArray[np.float64],
    *,
    closest: bool,
    inside_tol: float,
    mu: float,
    exponent: float,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    slip: NDArray[np.float64],
    memory: NDArray[np.float64],
) -> tuple[
    NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]
]:
    """The friction state after an accepted step (Algorithm 1, as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.update`): new (active (n_f, F), anchor
    (n_f, F, 3), offset (n_f, F, 3) [m], slip (n_f, F, 3) [m], memory (n_f, 3) [m])."""
    f64 = np.float64
    new_active = np.zeros(active.shape, np.bool_)
    new_anchor = np.zeros(anchor.shape)
    new_offset = np.zeros(offset.shape)
    new_slip = np.zeros(slip.shape)
    new_memory = np.zeros(memory.shape)
    _fingertip_update(
        *_geometry_args(x, facets, corners, boundary_nodes, indptr, indices, reach, centres, radii),
        *_law_args(law, closest, inside_tol, mu, exponent, patch, ratio, min_depth_ratio),
        *_state_args(active, anchor, offset),
        np.ascontiguousarray(slip, dtype=f64),
        np.ascontiguousarray(memory, dtype=f64),
        new_active,
        new_anchor,
        new_offset,
        new_slip,
        new_memory,
    )
    return new_active, new_anchor, new_offset, new_slip, new_memory


def fingertip_pair_laws(
    x: NDArray[np.float64],
    v: NDArray[np.float64] | None,
    finger: NDArray[np.int64],
    facet: NDArray[np.int64],
    val: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    velocities: NDArray[np.float64],
    omegas: NDArray[np.float64],
    law: NDArray[np.float64],
    C: NDArray[np.float64],
    *,
    mu: float,
    exponent: float,
    hunt_crossley: bool,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    memory: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The contact law of the pairs (finger (k,), facet (k,), their detection values (k, 13) as
    :func:`~softgrasp.physics.fingertip.detect.detect_arrays` gives them), evaluated as
    :func:`fingertip_forces` does (``v`` None: at rest, as :func:`fingertip_static_forces`):
    (table (k, 15): f_n [N] 0, friction on the finger [N] 1-3, weight w 4, k_t [N/m] 5, stick
    displacement [m] 6-8, Coulomb cap mu f_n [N] 9, penetration the normal law is evaluated at [m]
    10, the pair it is measured on 11, the unweighted elastic force [N] 12, its derivative [N/m]
    13 and energy [J] 14 there; slipping (k,))."""
    f64, i64 = np.float64, np.int64
    x = np.ascontiguousarray(x, dtype=f64)
    static = v is None
    finger = np.ascontiguousarray(finger, dtype=i64)
    table = np.zeros((finger.shape[0], 15))
    slipping = np.zeros(finger.shape[0], np.bool_)
    centres = np.ascontiguousarray(centres, dtype=f64).reshape(-1, 3)
    _pair_table(
        finger,
        np.ascontiguousarray(facet, dtype=i64),
        np.ascontiguousarray(val, dtype=f64).reshape(-1, 13),
        x,
        x if static else np.ascontiguousarray(v, dtype=f64),
        np.ascontiguousarray(facets, dtype=i64),
        centres,
        np.ascontiguousarray(radii, dtype=f64).ravel(),
        np.ascontiguousarray(velocities, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(omegas, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(law, dtype=f64).reshape(-1, LAW_COLUMNS),
        np.ascontiguousarray(C, dtype=f64).ravel(),
        float(mu),
        float(exponent),
        bool(hunt_crossley),
        bool(patch),
        float(ratio),
        float(min_depth_ratio),
        *_state_args(active, anchor, offset),
        np.ascontiguousarray(memory, dtype=f64),
        static,
        table,
        slipping,
    )
    return table, slipping
