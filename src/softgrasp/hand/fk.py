"""Forward kinematics of the finger chains, compiled: the transforms multiplied root to tip
(:func:`forward`), the Jacobian's joint columns (:func:`joint_columns`) and both for a batch of
postures (:func:`batch`). The one implementation that :mod:`softgrasp.hand.kinematics`, the WDLS
descent (:mod:`softgrasp.hand.descent`) and the placement use; imported where first needed, so that
loading the hand model does not load Numba's compiler."""

from __future__ import annotations

import math

import numpy as np

from softgrasp import jitcache

__all__ = ["batch", "forward", "jit", "joint_columns"]

#: The Numba compilation of softgrasp's hand kernels.
jit = jitcache.jit(fastmath=False, error_model="numpy")


@jit
def _compose(A, B, out):  # pragma: no cover - compiled
    """The affine product ``A B`` of 3 x 4 transforms (implicit last row 0 0 0 1) into ``out``."""
    for i in range(3):
        a0 = A[i, 0]
        a1 = A[i, 1]
        a2 = A[i, 2]
        for j in range(3):
            out[i, j] = a0 * B[0, j] + a1 * B[1, j] + a2 * B[2, j]
        out[i, 3] = a0 * B[0, 3] + a1 * B[1, 3] + a2 * B[2, 3] + A[i, 3]


@jit
def forward(basis, column, gain, offset, length, R, p, q, T, M, frames, tips):  # pragma: no cover
    """Frames after every joint ``(C, L, 3, 4)`` (3 x 4) and fingertips ``(C, 3)`` [m] of the
    :class:`ChainStack` arrays' chains with palm rotation ``R`` (3, 3), origin ``p`` (3,) and joints
    ``q`` (n,), root to tip. Joint ``(l, c)`` takes the value ``gain q[column] + offset``; its
    transform is ``cos(value) basis[l, c, 0] + sin(value) basis[l, c, 1] + basis[l, c, 2]
    (+ value basis[l, c, 3])`` (rows 0-2 of the flat 4 x 4). Padding joints past ``length[c]`` are
    identities and skipped. ``T``, ``M``: scratch (3, 4)."""
    K = basis.shape[2]
    for c in range(length.shape[0]):
        for i in range(3):
            for j in range(3):
                T[i, j] = R[i, j]
            T[i, 3] = p[i]
        for l in range(length[c]):
            value = gain[l, c] * q[column[l, c]] + offset[l, c]
            cv = math.cos(value)
            sv = math.sin(value)
            for r in range(12):
                v = cv * basis[l, c, 0, r] + sv * basis[l, c, 1, r] + basis[l, c, 2, r]
                if K == 4:
                    v += value * basis[l, c, 3, r]
                M[r // 4, r % 4] = v
            _compose(T, M, frames[c, l])
            for i in range(3):
                for j in range(4):
                    T[i, j] = frames[c, l, i, j]
        for i in range(3):
            tips[c, i] = T[i, 3]


@jit
def joint_columns(axis, prismatic, column, gain, length, frames, tips, J, first):  # pragma: no cover
    """Add the joints' columns of the fingertips' Jacobian to ``J`` ``(3 C, first + n)`` (column
    ``first + k`` for joint ``k``; rows ``3 c`` to ``3 c + 2`` for chain ``c``), from the
    :func:`forward` frames and tips. A revolute joint's column is ``a x (tip - o)``, a prismatic
    one's ``a`` (``a`` its axis, ``o`` its origin, in the frames' frame), times the joint's gain,
    added to its driving joint's column."""
    for c in range(length.shape[0]):
        r0 = 3 * c
        for l in range(length[c]):
            g = gain[l, c]
            if g == 0.0:
                continue  # a fixed joint (or a mimic joint with multiplier 0): no column
            F = frames[c, l]
            ax = F[0, 0] * axis[l, c, 0, 0] + F[0, 1] * axis[l, c, 1, 0] + F[0, 2] * axis[l, c, 2, 0]
            ay = F[1, 0] * axis[l, c, 0, 0] + F[1, 1] * axis[l, c, 1, 0] + F[1, 2] * axis[l, c, 2, 0]
            az = F[2, 0] * axis[l, c, 0, 0] + F[2, 1] * axis[l, c, 1, 0] + F[2, 2] * axis[l, c, 2, 0]
            if prismatic[l, c]:
                cx = ax
                cy = ay
                cz = az
            else:
                dx = F[0, 3] - tips[c, 0]
                dy = F[1, 3] - tips[c, 1]
                dz = F[2, 3] - tips[c, 2]
                cx = az * dy - ay * dz
                cy = ax * dz - az * dx
                cz = ay * dx - ax * dy
            k = first + column[l, c]
            J[r0, k] += g * cx
            J[r0 + 1, k] += g * cy
            J[r0 + 2, k] += g * cz


@jit
def batch(basis, axis, prismatic, column, gain, offset, length, R, p, q, tips, J_out, origins):  # pragma: no cover
    """:func:`forward` for each row ``b`` of ``R`` ``(B, 3, 3)``, ``p`` ``(B, 3)``, ``q`` ``(B, n)``
    into ``tips`` ``(B, C, 3)``; the Jacobian ``J_out`` ``(B, C, 3, n)`` and the joint origins
    ``(B, C, L, 3)`` too unless ``J_out``, ``origins`` have no rows."""
    B, n = q.shape
    C = length.shape[0]
    L = basis.shape[0]
    T = np.empty((3, 4))
    M = np.empty((3, 4))
    frames = np.empty((C, L, 3, 4))
    tip = np.empty((C, 3))
    J = np.empty((3 * C, n))
    for b in range(B):
        forward(basis, column, gain, offset, length, R[b], p[b], q[b], T, M, frames, tip)
        for c in range(C):
            for i in range(3):
                tips[b, c, i] = tip[c, i]
        if J_out.shape[0] > 0:
            J[:, :] = 0.0
            joint_columns(axis, prismatic, column, gain, length, frames, tip, J, np.int64(0))
            for c in range(C):
                for i in range(3):
                    for k in range(n):
                        J_out[b, c, i, k] = J[3 * c + i, k]
        if origins.shape[0] > 0:
            for c in range(C):
                for l in range(L):
                    if l >= length[c]:
                        for i in range(3):
                            origins[b, c, l, i] = tip[c, i]
                        continue
                    F = frames[c, l]
                    shift = 0.0  # a prismatic joint moves its frame along its axis from its origin
                    if prismatic[l, c]:
                        shift = gain[l, c] * q[b, column[l, c]] + offset[l, c]
                    u = axis[l, c]
                    for i in range(3):
                        a = F[i, 0] * u[0, 0] + F[i, 1] * u[1, 0] + F[i, 2] * u[2, 0]  # world axis
                        origins[b, c, l, i] = F[i, 3] - shift * a
