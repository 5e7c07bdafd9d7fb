"""The body's internal forces summed in one pass: springs, dashpots and volume term together.

:class:`softgrasp.physics.body.Body` calls these: :func:`internal_forces` and :func:`internal_energy`
(the kernels of :mod:`softgrasp.physics.springs` and :mod:`softgrasp.physics.volume` into one force
array), their partitioned form for large bodies (:func:`partitioned_forces`: the elements in
:func:`assembly_partition`'s order, its first two groups side by side on Numba's threads, the same
sums on any number of threads) and :func:`internal_jacobian_data` (the spring and volume blocks
summed straight into the CSR data of the body's :class:`softgrasp.physics.forces.BlockPattern`).

In a process forked from one whose Numba threads do not survive the fork
(:func:`softgrasp.backend.forked`), the groups run one after another on the calling thread: the
same sums in the same order.
"""

from __future__ import annotations

import numba
import numpy as np

from softgrasp import backend, jitcache
from softgrasp.model.material import StressStrainLaw
from softgrasp.physics.jit import Array, IntArray, f64, i64, jit
from softgrasp.physics.springs import (
    _add_springs,
    _law_tensions,
    _spring_blocks,
    _springs,
    polynomial_coefficients,
)
from softgrasp.physics.volume import (
    _tet_volumes,
    _volume_blocks,
    _volumes,
    count_inverted,
)

__all__ = [
    "internal_forces",
    "internal_energy",
    "internal_jacobian_data",
    "assembly_partition",
    "partitioned_elements",
    "partitioned_forces",
    "PARTITIONED_MIN_NODES",
    "count_inverted",
    "polynomial_coefficients",
]


def internal_forces(
    x: Array,
    v: Array | None,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    damping: Array | None,
    law: StressStrainLaw,
    tets: IntArray,
    rest_volume: Array,
    kappa: float,
    barrier: bool,
) -> Array:
    """Springs + volume term (if kappa != 0) + edge dashpots (if ``v`` and ``damping`` are given)
    [N], (N, 3): the fused :meth:`softgrasp.physics.body.Body.internal_forces`."""
    x = f64(x)
    out = np.zeros_like(x)
    _add_springs(out, x, v, i64(edges), f64(rest_length), f64(stiffness), damping, law, False)
    if kappa != 0.0:
        _tet_volumes(x, tets, rest_volume, kappa, barrier, False, out)
    return out


#: Bodies with at least this many nodes sum their forces in :func:`assembly_partition`'s order, its
#: first two groups side by side on Numba's threads (an evaluation of 2-4 ms at 27 749-33 969 nodes;
#: below, the thread hand-off would cost more than it saves): :func:`partitioned_elements`.
PARTITIONED_MIN_NODES = 10_000


def partitioned_elements(
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    damping: Array,
    tets: IntArray,
    rest_volume: Array,
    partition: tuple,
) -> tuple:
    """The per-element arrays the force kernels read, in :func:`assembly_partition`'s order
    (``partition``), with its group bounds: (edges, L0, 1 / L0, k L0, c, edge bounds (4,), tets,
    1 / (6 V0), V0, tet bounds (4,)). Made once per body."""
    eo, eb, to, tb = partition
    rest = f64(rest_length)[eo]
    v0 = f64(rest_volume)[to]
    return (
        i64(edges)[eo],
        rest,
        1.0 / rest,
        (f64(stiffness)[eo] * rest),
        f64(damping)[eo],
        np.asarray(eb, dtype=np.int64),
        i64(tets)[to],
        1.0 / (6.0 * v0),
        v0,
        np.asarray(tb, dtype=np.int64),
    )


@jitcache.jit(fastmath={"contract"}, error_model="numpy", parallel=True)
def _partitioned_forces(
    x,
    v,
    edges,
    rest,
    inv_rest,
    kl0,
    c,
    eb,
    tets,
    inv6v0,
    v0,
    tb,
    a2,
    a3,
    damped,
    kappa,
    barrier,
    want_energy,
    out,
):  # pragma: no cover - compiled
    """Springs (+ dashpots) and volume term into ``out``: the first two groups (their elements'
    nodes in disjoint halves: no force entry in common) side by side, then the third; the same sums
    on any number of threads. Returns the energy (0 unless ``want_energy``), the groups' in order."""
    energy = np.zeros(2)
    for g in numba.prange(2):
        e = _springs(x, v, edges, rest, inv_rest, kl0, c, a2, a3, damped, want_energy, eb[g], eb[g + 1], out)
        if kappa != 0.0:
            ev = _volumes(x, tets, inv6v0, v0, kappa, barrier, want_energy, False, tb[g], tb[g + 1], out)
            e += ev[0]
        energy[g] = e
    e = _springs(x, v, edges, rest, inv_rest, kl0, c, a2, a3, damped, want_energy, eb[2], eb[3], out)
    if kappa != 0.0:
        e += _volumes(x, tets, inv6v0, v0, kappa, barrier, want_energy, False, tb[2], tb[3], out)[0]
    return (energy[0] + energy[1]) + e


def partitioned_forces(
    x: Array,
    v: Array | None,
    elements: tuple,
    law: StressStrainLaw,
    kappa: float,
    barrier: bool,
    want_energy: bool = False,
) -> tuple[Array, float] | None:
    """:func:`internal_forces` (and, with ``want_energy``, :func:`internal_energy`) summed in the
    order of ``elements`` (:func:`partitioned_elements`), on the calling thread's Numba threads:
    (forces (N, 3) [N], energy [J] or 0); None for a law that is not a polynomial (the caller then
    takes :func:`internal_forces`)."""
    coef = polynomial_coefficients(law)
    if coef is None:
        return None
    edges, rest, inv_rest, kl0, c, eb, tets, inv6v0, v0, tb = elements
    x = f64(x)
    damped = v is not None
    out = np.zeros_like(x)
    energy = _partitioned_forces(
        x, f64(v) if damped else x, edges, rest, inv_rest, kl0, c, eb, tets, inv6v0, v0, tb,
        coef[0], coef[1], damped, float(kappa), bool(barrier), want_energy, out,
    )  # fmt: skip
    return out, float(energy)


def internal_energy(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    tets: IntArray,
    rest_volume: Array,
    kappa: float,
    barrier: bool,
) -> float:
    """Elastic energy of springs and volume term [J]."""
    x = f64(x)
    scratch = np.zeros_like(x)
    e = _add_springs(scratch, x, None, i64(edges), f64(rest_length), f64(stiffness), None, law, True)
    if kappa != 0.0:
        e += _tet_volumes(x, tets, rest_volume, kappa, barrier, True, scratch)
    return e


def assembly_partition(
    edges: IntArray, tets: IntArray, n_nodes: int
) -> tuple[IntArray, IntArray, IntArray, IntArray]:
    """The edges and tets in the order :func:`internal_jacobian_data` sums them: those whose
    nodes all lie in the first half of the node numbers, then those all in the second half (two
    groups that write no Jacobian block in common: one thread each), then the rest.

    Returns
    -------
    (edge order (E,), its group bounds (4,), tet order (M,), its group bounds (4,)).
    """

    def split(elements: IntArray) -> tuple[IntArray, IntArray]:
        half = n_nodes // 2
        low = (elements < half).all(axis=1)
        high = (elements >= half).all(axis=1)
        groups = [np.flatnonzero(low), np.flatnonzero(high), np.flatnonzero(~(low | high))]
        bounds = np.cumsum([0] + [len(g) for g in groups]).astype(np.int64)
        return np.concatenate(groups).astype(np.int64), bounds

    eo, eb = split(np.asarray(edges))
    to, tb = split(np.asarray(tets))
    return eo, eb, to, tb


@jit
def _jacobian_group(
    x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb, g
):  # pragma: no cover - compiled
    """The spring then volume-term blocks of :func:`assembly_partition`'s group ``g``."""
    _spring_blocks(x, edges, L, T, dT, False, base, stride, True, 0, out, eo, eb[g], eb[g + 1])
    if kappa != 0.0:
        offset = 4 * edges.shape[0]
        _volume_blocks(x, tets, rest, kappa, barrier, base, stride, True, offset, out, to, tb[g], tb[g + 1])


@jitcache.jit(fastmath=False, error_model="numpy", parallel=True)
def _jacobian_groups(
    x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb
):  # pragma: no cover - compiled
    """:func:`assembly_partition`'s first two groups side by side (they write no entry in
    common), then the third; the same sums on any number of threads."""
    for k in numba.prange(2):  # the group as an int64, as from Python: one compiled group kernel
        g = np.int64(k)
        _jacobian_group(x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb, g)
    last = np.int64(2)
    _jacobian_group(x, edges, L, T, dT, tets, rest, kappa, barrier, base, stride, out, eo, eb, to, tb, last)


def internal_jacobian_data(
    x: Array,
    edges: IntArray,
    rest_length: Array,
    stiffness: Array,
    law: StressStrainLaw,
    tets: IntArray,
    rest_volume: Array,
    kappa: float,
    barrier: bool,
    block_base: IntArray,
    block_stride: IntArray,
    nnz: int,
    partition: tuple | None = None,
    threads: int = 1,
) -> Array:
    """CSR data (nnz,) of ``d f_internal / d x``: the spring blocks (then the volume term's, if
    kappa != 0) summed straight into the entries of a :class:`softgrasp.physics.forces.BlockPattern`
    built on :func:`softgrasp.physics.springs.spring_pairs` (then :func:`softgrasp.physics.volume.volume_pairs`)
    (its ``block_base`` and ``block_stride``), without forming the blocks; in the order of
    ``partition`` (:func:`assembly_partition`, computed here when None), its first two groups on
    ``threads`` threads (the result does not depend on it; one after another on the calling
    thread in a process forked from one whose Numba threads did not survive the fork)."""
    from softgrasp.linalg.sparse import _Threads

    x, edges, tets = f64(x), i64(edges), i64(tets)
    block_base, block_stride = i64(block_base), i64(block_stride)
    if partition is None:
        partition = assembly_partition(edges, tets, x.shape[0])
    data = np.zeros(nnz)
    L, T, dT = _law_tensions(x, edges, f64(rest_length), f64(stiffness), law)
    args = (x, edges, L, T, dT, tets, f64(rest_volume), float(kappa), bool(barrier), block_base, block_stride, data)
    if backend.forked():
        for g in range(3):
            _jacobian_group(*args, *partition, g)
        return data
    with _Threads(threads):
        _jacobian_groups(*args, *partition)
    return data
