"""The body's internal forces in the fused stepper: springs, edge dashpots and volume term in parts.

The laws are those of :mod:`softgrasp.physics.forces_compiled`, called here on each part's
elements: ``_springs`` (springs and dashpots), ``_volumes`` (volume term) and, for the blow-up
checks, ``_inverted`` (the inverted-tet test of
:func:`~softgrasp.physics.forces_compiled.count_inverted`). :func:`pack_body` lays a body's
elements out for them once (the reciprocals of the rest lengths and volumes precomputed);
:func:`body_forces` computes them in parts (even shares of the edges and of the tets,
:data:`softgrasp.sim.fused.step.PARTS` in the stepper), each into its own buffer, on as many of
Numba's threads when asked and one after the other otherwise (the same sums either way).
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import numba
import numpy as np

from softgrasp.physics.forces_compiled import polynomial_coefficients
from softgrasp.physics.springs import _springs
from softgrasp.physics.volume import _inverted, _volumes
from softgrasp.sim.fused.cache import jit, pjit

__all__ = ["body_forces", "pack_body", "packed"]


def pack_body(body: Any) -> tuple:
    """The body's static data for :func:`body_forces`.

    Returns
    -------
    tuple
        ``(edges, L0, 1 / L0, k L0, c, tets, 1 / (6 V0), V0, a2, a3, damped, kappa, barrier, n)``:
        the edges (E, 2); their rest lengths [m], reciprocals [1/m], k L0 [N] and dashpot
        coefficients [N s/m] (E,) (c = 0 undamped); the tets (M, 4); their 1 / (6 V0) [1/m^3] and
        V0 [m^3] (M,); the law's ``a2``, ``a3``
        (:func:`softgrasp.physics.forces_compiled.polynomial_coefficients`: polynomial laws only);
        whether the dashpots act; ``kappa`` [Pa]; whether the volume term is the barrier; the node
        count.
    """
    coef = polynomial_coefficients(body.material.law)
    if coef is None:
        raise ValueError(f"stress-strain law {type(body.material.law).__name__} is not a polynomial")
    damped = body.damping_time > 0
    rest = np.ascontiguousarray(body.rest_length, dtype=np.float64)
    c = np.ascontiguousarray(body.damping, dtype=np.float64) if damped else np.zeros_like(rest)
    v0 = np.ascontiguousarray(body.mesh.volumes, dtype=np.float64)
    return (
        np.ascontiguousarray(body.edges, dtype=np.int64),
        rest,
        1.0 / rest,
        np.ascontiguousarray(body.stiffness, dtype=np.float64) * rest,
        c,
        np.ascontiguousarray(body.mesh.tets, dtype=np.int64),
        1.0 / (6.0 * v0),
        v0,
        float(coef[0]),
        float(coef[1]),
        bool(damped),
        float(body.kappa),
        bool(body.barrier),
        int(body.n_nodes),
    )


#: pack_body's tuples by body: packed once and shared by the body's steppers, whose kernels only
#: read it; held weakly (gone with the body).
_PACKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_PACKED_LOCK = threading.Lock()


def packed(body: Any) -> tuple:
    """:func:`pack_body` of ``body``, computed once a body."""
    with _PACKED_LOCK:
        if body not in _PACKED:
            _PACKED[body] = pack_body(body)
        return _PACKED[body]


@jit
def _lower(first, index):  # pragma: no cover - compiled
    """The lower of a tet index ``first`` found so far (-1: none yet) and ``index``."""
    i = np.int64(index)
    return i if first < 0 or i < first else first


@jit
def _body_part(part, parts, x, v, body, want_energy, check, out, info):  # pragma: no cover - compiled
    """Part ``part`` of ``parts`` of the internal forces (an even share of the edges and of the
    tets) into its own buffer ``out`` (N, 3), zeroed here; its energy (0 unless ``want_energy``),
    inverted count and lowest inverted tet (0 and -1 unless ``check``) into ``info``."""
    edges, rest, inv_rest, kl0, c, tets, inv6v0, v0, a2, a3, damped, kappa, barrier, _ = body
    out[:] = 0.0
    E = edges.shape[0]
    M = tets.shape[0]
    e = _springs(
        x, v, edges, rest, inv_rest, kl0, c, a2, a3, damped, want_energy, part * E // parts,
        (part + 1) * E // parts, out,
    )  # fmt: skip
    lo = part * M // parts
    hi = (part + 1) * M // parts
    count = 0
    first = -1
    if kappa != 0.0:
        e += _volumes(x, tets, inv6v0, v0, kappa, barrier, want_energy, False, lo, hi, out)[0]
    if check:  # the monitor's own count (count_inverted's triple product, to the bit)
        count, first = _inverted(x, tets, lo, hi)
    info[0] = e
    info[1] = count
    info[2] = first


@pjit
def _body_forces_parallel(x, v, body, want_energy, check, fint, info):  # pragma: no cover - compiled
    """:func:`_body_part` for every part, one of Numba's threads each."""
    parts = fint.shape[0]
    for p in numba.prange(parts):
        _body_part(p, parts, x, v, body, want_energy, check, fint[p], info[p])


@jit
def body_totals(info):  # pragma: no cover - compiled
    """The parts' ``info`` rows together: (energy, inverted count, lowest inverted tet or -1)."""
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


@jit
def body_forces(parallel, x, v, body, want_energy, check, fint, info):  # pragma: no cover - compiled
    """Internal forces at positions ``x`` and velocities ``v`` (N, 3) in ``fint.shape[0]`` parts
    ``fint`` (parts, N, 3) (summed by the caller), on as many threads when ``parallel``; ``info``
    (parts, 3) the parts' energy, inverted count and lowest inverted tet. Returns their totals
    (:func:`body_totals`): the same whatever the threads."""
    n = body[13]
    if x.shape != (n, 3) or v.shape != (n, 3) or fint.shape[1] != n or fint.shape[2] != 3:
        raise ValueError("body forces: x and v must be (N, 3) and fint (parts, N, 3), N the body's nodes")
    if parallel:
        _body_forces_parallel(x, v, body, want_energy, check, fint, info)
    else:
        for p in range(fint.shape[0]):
            _body_part(p, fint.shape[0], x, v, body, want_energy, check, fint[p], info[p])
    return body_totals(info)
