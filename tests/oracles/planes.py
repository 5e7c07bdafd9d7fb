"""NumPy reference of the plane contact law (:class:`softgrasp.physics.planes.PlaneContact`, whose
implementation is the compiled law of :mod:`softgrasp.physics.planes_compiled`), used only by the
tests: penalty normal force, elastic-slider friction capped at ``mu f_n`` (Eq. 15-16, Algorithm 1)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.physics.planes import PlaneContact, PlaneState


def _geometry(contact: PlaneContact, x: NDArray[np.float64], t: float):
    p0 = contact.plane.point_at(t)
    n = contact.plane.normal
    pen = -(x - p0) @ n
    return p0, n, pen


def _tangential_stretch(x, p0, n, state: PlaneState, touching) -> NDArray[np.float64]:
    s = np.where(touching[:, None], x - (p0 + state.anchor), 0.0)
    return s - (s @ n)[:, None] * n


def plane_forces(contact: PlaneContact, body, x, v, t: float, state: PlaneState) -> NDArray[np.float64]:
    """Contact forces on the nodes [N], (N, 3)."""
    k, c, kt, ct = contact._coeffs(body)
    p0, n, pen = _geometry(contact, x, t)
    touching = pen > 0
    vrel = v - contact.plane.velocity
    vn = vrel @ n
    fn = np.where(touching, np.maximum(k * pen - c * vn, 0.0), 0.0)
    f = fn[:, None] * n
    if contact.mu > 0:
        s = _tangential_stretch(x, p0, n, state, touching)
        vt = vrel - vn[:, None] * n
        ft = -kt[:, None] * s - ct[:, None] * vt
        ft[~touching] = 0.0
        mag = np.linalg.norm(ft, axis=1)
        cap = contact.mu * fn
        over = mag > cap
        ft[over] *= (cap[over] / np.maximum(mag[over], 1e-300))[:, None]
        f += ft
    return f


def plane_update(contact: PlaneContact, body, x, v, t: float, state: PlaneState) -> PlaneState:
    """The friction state after a step (Algorithm 1)."""
    k, _, kt, _ = contact._coeffs(body)
    p0, n, pen = _geometry(contact, x, t)
    touching = pen > 0
    rel = x - p0
    rel_t = rel - (rel @ n)[:, None] * n
    anchor = np.where(touching[:, None], state.anchor, rel_t)
    if contact.mu > 0:
        s = rel_t - anchor
        s_norm = np.linalg.norm(s, axis=1)
        limit = contact.mu * k * np.maximum(pen, 0.0) / np.maximum(kt, 1e-300)
        slip = touching & (s_norm > limit)
        if slip.any():
            anchor[slip] = rel_t[slip] - s[slip] * (limit[slip] / s_norm[slip])[:, None]
    else:
        anchor = rel_t
    return replace(state, active=touching.copy(), anchor=anchor)


class OraclePlaneContact(PlaneContact):
    """A :class:`PlaneContact` whose forces and friction update are this module's NumPy law."""

    def forces(self, body, x, v, t, state):
        return plane_forces(self, body, x, v, t, state)

    def update(self, body, x, v, t, state):
        return plane_update(self, body, x, v, t, state)
