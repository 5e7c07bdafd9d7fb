"""The fingertip contact's stiffness: ``d f / d x`` at rest for the Newton solvers (paper Eq. 9-20).

The normal forces' per-pair derivative by central differences of the 9 facet coordinates (the
facet's rotation and the moving contact point included), the friction springs' ``w k_t H^T P_t H``
(or the slip tangent), symmetrised: :func:`contact_jacobian`, which
:meth:`softgrasp.physics.fingertip.contact.FingertipContact.jacobian` returns.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.geometry import pair_geometry
from softgrasp.physics.fingertip.state import FingerState
from softgrasp.physics.forces import assemble_blocks

__all__ = ["contact_jacobian"]


def _pair_normal_forces(
    tri: NDArray[np.float64],
    centre: NDArray[np.float64],
    radius: NDArray[np.float64],
    coef: NDArray[np.float64],
    n_exp: NDArray[np.float64],
    closest: bool,
    corners: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """Static normal forces on the three nodes of each facet, (k, 3, 3): ``-coef delta^n b_l n``
    for triangles ``tri`` (k, 3, 3) and fingertip centres (k, 3), with each pair's contact point
    (b), normal and penetration as :func:`~softgrasp.physics.fingertip.geometry.pair_geometry` follows them
    (``closest`` as in :func:`~softgrasp.physics.fingertip.geometry.detect`; ``corners`` (k, 3, 3)
    each triangle's corner normals, or None)."""
    k = tri.shape[0]
    ids = np.arange(k)
    own = np.arange(3 * k).reshape(k, 3)  # each pair its own triangle
    pr = pair_geometry(tri.reshape(-1, 3), own, centre, radius, ids, ids, closest=closest, corners=corners)
    mag = coef * np.where(pr.depth > 0, np.abs(pr.depth) ** n_exp, 0.0)
    return -(mag[:, None, None] * pr.bary[:, :, None]) * pr.normal[:, None, :]


def _normal_jacobian_blocks(
    tri: NDArray[np.float64],
    centre: NDArray[np.float64],
    radius: NDArray[np.float64],
    coef: NDArray[np.float64],
    n_exp: NDArray[np.float64],
    closest: bool,
    corners: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """d(nodal normal forces)/d(node positions) per pair by central differences, symmetrised,
    (k, 3, 3, 3, 3) indexed [pair, node_l, node_m, axis_l, axis_m]; the magnitude
    ``coef delta^n`` per pair (exponent ``n_exp`` (k,)); ``corners`` each pair's facet's corner
    normals (k, 3, 3), or None for the facets' normals."""
    k = tri.shape[0]
    h = 1e-7 * np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1)  # (k,)
    # All 18 perturbed copies (+-h on each node's axis) in one evaluation: (2, 3, 3, k, 3, 3)
    # indexed [sign, node m, axis, pair, node, axis].
    moved = np.broadcast_to(tri, (2, 3, 3, k, 3, 3)).copy()
    for m in range(3):
        for ax in range(3):
            moved[0, m, ax, :, m, ax] += h
            moved[1, m, ax, :, m, ax] -= h
    reps = 18
    F = _pair_normal_forces(
        moved.reshape(-1, 3, 3),
        np.tile(centre, (reps, 1)),
        np.tile(radius, reps),
        np.tile(coef, reps),
        np.tile(n_exp, reps),
        closest,
        None if corners is None else np.tile(corners, (reps, 1, 1)),
    ).reshape(2, 3, 3, k, 3, 3)
    dF = (F[0] - F[1]) / (2 * h)[None, None, :, None, None]  # [m, ax, pair, node l, axis l]
    J = np.ascontiguousarray(dF.transpose(2, 3, 0, 4, 1))  # [pair, l, m, axis l, axis m]
    return 0.5 * (J + J.transpose(0, 2, 1, 4, 3))


def contact_jacobian(
    contact: Any, body: Body, x: NDArray[np.float64], t: float, state: FingerState
) -> sp.csr_matrix:
    """``d f / d x`` at rest, symmetrised: the normal forces' per-pair derivative (central
    differences of the 9 facet coordinates, so the facet's rotation and the moving contact
    point are included; exact for the literal rule with the facets' normals; for the patch rule
    with the weights w_j held fixed, plus the magnitude's slope carried by each pair as if its own
    facet were the deepest: positive semi-definite, where the exact coupling symmetrised is not) and
    the friction springs' ``w k_t H^T P_t H`` (or the slip tangent). With the smooth surface's
    normals the force is no longer the gradient of the contact's energy (the penetration stays
    the facet's): the true derivative is slightly unsymmetric (3 % on a sphere's pair) and this
    symmetrised one preconditions the Newton solves' exact products
    (:mod:`softgrasp.sim.newton_matrix`)."""
    ev = contact._evaluate(body, x, None, t, state, static=True)
    N = body.n_nodes
    if not len(ev.pairs):
        return sp.csr_matrix((3 * N, 3 * N))
    pr = ev.pairs
    fac = body.mesh.facets[pr.facet]
    centres = contact.centres(t)[pr.finger]
    radii = contact._radii()[pr.finger]
    patch = contact.params.rule == "patch"
    corners = contact.corners(body)
    corners = None if corners is None else corners[pr.facet]
    if patch:
        # Pair force w_j F(delta_max) along its normal at its contact point: its motion with
        # the facet at fixed magnitude (central differences, exponent 0); the magnitude's slope
        # is added below, the weights are lagged.
        zero = np.zeros(len(pr))
        Jn = _normal_jacobian_blocks(x[fac], centres, radii, ev.w * ev.elastic, zero, True, corners)
    else:
        # Exact per-pair blocks (facet rotation and the moving contact point included), the
        # normal law written locally as the power law with its value and slope at the pair's
        # penetration (the same first derivative).
        d = np.maximum(ev.depth, 1e-300)
        m = np.where(ev.elastic > 0, ev.slope * d / np.maximum(ev.elastic, 1e-300), 1.0)
        Jn = _normal_jacobian_blocks(x[fac], centres, radii, ev.w * ev.elastic / d**m, m, False, corners)
    blk_t = np.zeros((len(pr), 3, 3))
    if contact.params.mu > 0:
        nn = pr.normal[:, :, None] * pr.normal[:, None, :]
        Pt = np.eye(3)[None] - nn
        s = np.linalg.norm(ev.stick, axis=1)
        ktan = np.where(ev.slipping, ev.cap / np.maximum(s, 1e-300), ev.w * ev.kt)
        blk_t = ktan[:, None, None] * Pt
    bb = pr.bary[:, :, None] * pr.bary[:, None, :]  # (k, 3, 3)
    blocks = Jn - bb[:, :, :, None, None] * blk_t[:, None, None, :, :]
    rows = np.repeat(fac, 3, axis=1).ravel()
    cols = np.tile(fac, (1, 3)).ravel()
    blocks = blocks.reshape(-1, 3, 3)
    if patch:
        # The magnitude's dependence on the deepest facet, exactly the rank-one coupling
        # (sum_j g_j b_j n_j) (b_deep gdir)^T, enters the exact products (it is unsymmetric, and
        # symmetrised it is indefinite once the patch spans many facets). Here each pair carries it
        # as if its own facet set the magnitude: g_j (b_j n_j)(b_j n_j)^T, positive semi-definite,
        # equal to the coupling on a single facet, and about as stiff against the patch pressed
        # as a whole (the weights sum to one).
        g = ev.w * ev.slope
        bn = pr.bary[:, :, None] * pr.normal[:, None, :]  # (k, node, 3)
        own = g[:, None, None, None, None] * bn[:, :, None, :, None] * bn[:, None, :, None, :]
        blocks = blocks - own.reshape(-1, 3, 3)
    return assemble_blocks(N, rows, cols, blocks)
