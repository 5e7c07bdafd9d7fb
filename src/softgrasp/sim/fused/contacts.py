"""The interactions in the fused stepper: planes and fingertips, on the stepper's arrays.

* planes: the law of :mod:`softgrasp.physics.planes_compiled` (forces and friction state update),
  plane by plane, the planes' points moved to the time of the evaluation;
* fingertips: the compiled kernels of :mod:`softgrasp.physics.fingertip.compiled` (detection,
  forces, state update), the fingertips moving with their prescribed velocity. Their broad phase
  gets a margin from the surface's current stretch instead of the worst case and scans a Verlet
  list of the surface nodes near the fingertips (the same pairs: :func:`finger_reach`). The
  friction state is double-buffered: the update after a step writes the other buffer.

Planes come as a tuple of (P, ...) arrays ``(point, normal, velocity, mu, k, c, kt, ct)`` (points,
normals and velocities (P, 3), friction coefficients (P,), per-node coefficients (P, N)); the
fingertips as the tuple :class:`softgrasp.sim.fused.step.FusedStepper` builds from a
:class:`~softgrasp.physics.fingertip.contact.FingertipContact`.
"""

from __future__ import annotations

import math

import numpy as np

from softgrasp.physics.fingertip.compiled import _detect, _fingertip_forces, _pair_forces, _update_pairs
from softgrasp.physics.planes_compiled import plane_forces, plane_update
from softgrasp.sim.fused.cache import jit

__all__ = ["finger_reach", "finger_step", "max_facet_edge", "plane_step"]


@jit
def plane_points(t, point, velocity, p0):  # pragma: no cover - compiled
    """Each plane's point at time t, ``point + t velocity`` (Plane.point_at), into p0 (P, 3)."""
    for p in range(point.shape[0]):
        for d in range(3):
            p0[p, d] = point[p, d] + t * velocity[p, d]


@jit
def plane_step(x, v, t, planes, p0, active, anchor, update, out):  # pragma: no cover - compiled
    """The planes at the state (x, v, t): when ``update``, first their friction states after a step
    (``active`` (P, N), ``anchor`` (P, N, 3), in place); then their forces added to ``out``.
    Returns the forces' power [W]."""
    point, normal, velocity, mu, k, c, kt, ct = planes
    plane_points(t, point, velocity, p0)
    n = x.shape[0]
    power = 0.0
    for p in range(point.shape[0]):
        if update:
            plane_update(x, p0[p], normal[p], mu[p], k[p], kt[p], active[p], anchor[p], 0, n)
        power += plane_forces(
            x, v, p0[p], normal[p], velocity[p], mu[p], k[p], c[p], kt[p], ct[p], anchor[p], 0, n, out
        )
    return power


@jit
def max_facet_edge(x, facets):  # pragma: no cover - compiled
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


@jit
def fingers_at(t, fingers, centres):  # pragma: no cover - compiled
    """Fingertip centres at time t, ``centre + t velocity`` (Fingertip.centre_at), into centres."""
    c0 = fingers[6]
    vel = fingers[7]
    for f in range(c0.shape[0]):
        for d in range(3):
            centres[f, d] = c0[f, d] + t * vel[f, d]


@jit
def finger_reach(x, t, fingers, x_ref, track, near, centres):  # pragma: no cover - compiled
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
    exceeds L_ref / 4."""
    facets = fingers[1]
    boundary = fingers[2]
    reach = fingers[5]
    radii = fingers[9]
    grow = 1.0 + 3.0 * fingers[13]  # inside_tol
    fingers_at(t, fingers, centres)
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
        track[0] = max_facet_edge(x, facets)
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


@jit
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


@jit
def finger_forces(x, v, t, fingers, fstate, cur, x_ref, track, near, centres, out):  # pragma: no cover
    """Fingertip forces at the state (x, v, t) with buffer ``cur`` of the friction state ``fstate``
    added to ``out`` (:func:`softgrasp.physics.fingertip.compiled._fingertip_forces`)."""
    reach, n_near = finger_reach(x, t, fingers, x_ref, track, near, centres)
    active, anchor, _, memory, offset = fstate
    (_, facets, _, indptr, indices, _, _, vel, omega, radii, law, C, closest, inside_tol, mu, n_exp,
     hunt_crossley, patch, ratio, min_depth_ratio, corners) = fingers  # fmt: skip
    _fingertip_forces(
        x, v, facets, corners, near[:n_near], indptr, indices, reach, centres, radii, vel, omega, law, C,
        closest, inside_tol, mu, n_exp, hunt_crossley, patch, ratio, min_depth_ratio, active[cur],
        anchor[cur], offset[cur], memory[cur], out,
    )  # fmt: skip


@jit
def finger_step(
    x, v, t, fingers, fstate, cur, x_ref, track, near, centres, out, want_power
):  # pragma: no cover - compiled
    """The fingertips after a step: friction states updated at (x, t) into the other buffer, then
    their forces at the new state added to ``out`` (one detection for both: the same state, the
    same pairs). Returns the new current buffer and the forces' power (0 unless ``want_power``)."""
    reach, n_near = finger_reach(x, t, fingers, x_ref, track, near, centres)
    (_, facets, _, indptr, indices, _, _, vel, omega, radii, law, C, closest, inside_tol, mu, n_exp,
     hunt_crossley, patch, ratio, min_depth_ratio, corners) = fingers  # fmt: skip
    active, anchor, slip, memory, offset = fstate
    finger, facet, val = _detect(
        x, facets, corners, near[:n_near], indptr, indices, reach, centres, radii, closest, inside_tol
    )
    nxt = 1 - cur
    _clear_finger(active[nxt], anchor[nxt], offset[nxt], slip[nxt], memory[nxt])
    _update_pairs(
        finger, facet, val, x, facets, centres, radii, law, mu, n_exp, patch, ratio, min_depth_ratio,
        active[cur], anchor[cur], offset[cur], slip[cur], memory[cur], active[nxt], anchor[nxt], offset[nxt],
        slip[nxt], memory[nxt],
    )  # fmt: skip
    cur = nxt
    _pair_forces(
        finger, facet, val, x, v, facets, centres, radii, vel, omega, law, C, mu, n_exp, hunt_crossley, patch,
        ratio, min_depth_ratio, active[cur], anchor[cur], offset[cur], memory[cur], False, out,
    )  # fmt: skip
    power = 0.0
    if want_power:  # over the touching facets' nodes, each once: the only ones with a fingertip force
        seen = np.zeros(x.shape[0], np.bool_)
        for p in range(facet.shape[0]):
            for r in range(3):
                i = facets[facet[p], r]
                if not seen[i]:
                    seen[i] = True
                    power += out[i, 0] * v[i, 0] + out[i, 1] * v[i, 1] + out[i, 2] * v[i, 2]
    return cur, power
