"""The fused stepper's body forces eight elements at a time, in LLVM's vector instructions.

Numba compiles the per-element loops of :mod:`softgrasp.sim.fused.step` to scalar code, and its
auto-vectoriser either leaves them scalar (the scattered read-modify-write of the forces) or uses
hardware gathers, which cost about three cycles an element on this project's reference machine
(AMD Zen 4): slower than the scalar loop. The intrinsics here (:data:`spring_block` and its
variants for the springs, :data:`volume_block` and its variants for the tets) are written in LLVM
IR through :func:`numba.extending.intrinsic` and inlined into the Numba loops that call them
(:data:`tet_spring_block` and its variants take the tets with the spring each carries: one
kernel, one set of loads and one read-modify-write a node for both terms). Each takes one block of
eight springs or eight tets:

* the nodes' positions (and velocities) are loaded as 4-vectors ``(x, y, z, 0)`` from arrays laid
  out (N, 4) ("AoS4"), one aligned load a node, and transposed by shuffles into 8-lane vectors of
  x, y and z;
* the element arithmetic is the scalar kernels' (:func:`softgrasp.sim.fused.step._edge_pass`,
  ``_tet_pass``) on 8-lane vectors, without fused multiply-adds (the same results to round-off);
* the element forces are transposed back to 4-vectors and added to the nodes, one 4-wide
  read-modify-write a node, in the elements' order (a node met twice in a block is updated twice,
  in order, as in the scalar loop).

:data:`node_step` (and :data:`node_step_two`) does one node's semi-implicit step on its (N, 4)
rows, the scalar loop's arithmetic four columns at a time (the same bits); :data:`node_pair_step`
two neighbouring nodes' in 8-lane vectors.

LLVM lowers the 8-lane vectors to whatever the CPU has (two AVX2 registers, one AVX-512 register).
Measured on the reference machine, 2 196-node sphere, one thread, inside the stepper's force
evaluation: springs and dashpots 89 -> 54 us, volume term 93 -> 61 us (``benchmarks/README.md``).

The callers in :mod:`softgrasp.sim.fused.step` are cached by Numba, which checks only their own
file for changes: the inlined IR of this module would stay stale after an edit here, so step.py
records this file's hash (``_INLINED_SOURCES_SHA256``, compared by a test): an edit here fails that
test until step.py is updated, which renews its cache.

Parameters come in blocks (:func:`block_params`): for springs, eight 1 / L0, eight k L0, eight c
and eight L0 side by side; for tets, eight 1 / (6 V0) and eight V0. Variants return the block's
energy (and, for tets, a mask of the inverted ones) for the blow-up monitor's checks.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import NDArray

__all__ = [
    "BLOCK",
    "SPRING_COLUMNS",
    "TET_COLUMNS",
    "TET_SPRING_COLUMNS",
    "block_params",
    "node_step",
    "node_step_two",
    "node_pair_step",
    "node_pair_step_two",
    "spring_block",
    "spring_block_energy",
    "spring_block_undamped",
    "spring_block_undamped_energy",
    "tet_spring_block",
    "tet_spring_block_full",
    "tet_spring_block_quadratic",
    "tet_spring_block_quadratic_full",
    "tet_spring_block_quadratic_undamped",
    "tet_spring_block_quadratic_undamped_full",
    "tet_spring_block_undamped",
    "tet_spring_block_undamped_full",
    "volume_block",
    "volume_block_full",
    "volume_block_quadratic",
    "volume_block_quadratic_full",
]

#: Elements a block.
BLOCK = 8

_F64 = ir.DoubleType()
_V4 = ir.VectorType(_F64, 4)
_V8 = ir.VectorType(_F64, 8)
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)


def block_params(columns: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """Per-element parameters ``columns`` (each (E,)) of the first ``BLOCK * (E // BLOCK)`` elements
    laid out a block at a time: block b holds ``BLOCK`` values of each column in turn, (B * C * 8,)."""
    n = columns[0].shape[0] // BLOCK
    out = np.empty((n, len(columns), BLOCK))
    for c, col in enumerate(columns):
        out[:, c, :] = np.asarray(col, dtype=np.float64)[: n * BLOCK].reshape(n, BLOCK)
    return out.reshape(-1)


def _mask(values: list[int] | range) -> ir.Constant:
    vals = list(values)
    return ir.Constant(ir.VectorType(_I32, len(vals)), vals)


def _splat(b: ir.IRBuilder, s: ir.Value, lanes: int = BLOCK) -> ir.Value:
    """The scalar ``s`` in every lane of a vector of ``lanes`` doubles."""
    ty = ir.VectorType(_F64, lanes)
    v = b.insert_element(ir.Constant(ty, ir.Undefined), s, ir.Constant(_I32, 0))
    return b.shuffle_vector(v, v, _mask([0] * lanes))


def _const(value: float) -> ir.Constant:
    return ir.Constant(_V8, [value] * BLOCK)


def _to_lanes(b: ir.IRBuilder, rows: list[ir.Value]) -> tuple[ir.Value, ir.Value, ir.Value]:
    """Eight 4-vectors (x, y, z, w) -> 8-lane vectors of x, y and z."""
    s = [b.shuffle_vector(rows[2 * k], rows[2 * k + 1], _mask(range(8))) for k in range(4)]
    lo_xy = b.shuffle_vector(s[0], s[1], _mask([0, 4, 8, 12, 1, 5, 9, 13]))
    hi_xy = b.shuffle_vector(s[2], s[3], _mask([0, 4, 8, 12, 1, 5, 9, 13]))
    lo_z = b.shuffle_vector(s[0], s[1], _mask([2, 6, 10, 14, 2, 6, 10, 14]))
    hi_z = b.shuffle_vector(s[2], s[3], _mask([2, 6, 10, 14, 2, 6, 10, 14]))
    x = b.shuffle_vector(lo_xy, hi_xy, _mask([0, 1, 2, 3, 8, 9, 10, 11]))
    y = b.shuffle_vector(lo_xy, hi_xy, _mask([4, 5, 6, 7, 12, 13, 14, 15]))
    z = b.shuffle_vector(lo_z, hi_z, _mask([0, 1, 2, 3, 8, 9, 10, 11]))
    return x, y, z


def _to_rows(b: ir.IRBuilder, fx: ir.Value, fy: ir.Value, fz: ir.Value) -> list[ir.Value]:
    """8-lane vectors of x, y and z -> eight 4-vectors (x, y, z, 0)."""
    zero = _const(0.0)
    xy_lo = b.shuffle_vector(fx, fy, _mask([0, 8, 1, 9, 2, 10, 3, 11]))
    xy_hi = b.shuffle_vector(fx, fy, _mask([4, 12, 5, 13, 6, 14, 7, 15]))
    z_lo = b.shuffle_vector(fz, zero, _mask([0, 8, 1, 9, 2, 10, 3, 11]))
    z_hi = b.shuffle_vector(fz, zero, _mask([4, 12, 5, 13, 6, 14, 7, 15]))
    rows = []
    for xy, z in ((xy_lo, z_lo), (xy_hi, z_hi)):
        for h in (0, 4):
            w = b.shuffle_vector(xy, z, _mask([h, h + 1, h + 8, h + 9, h + 2, h + 3, h + 10, h + 11]))
            rows.append(b.shuffle_vector(w, w, _mask([0, 1, 2, 3])))
            rows.append(b.shuffle_vector(w, w, _mask([4, 5, 6, 7])))
    return rows


def _data(context, b: ir.IRBuilder, ty, value) -> ir.Value:  # type: ignore[no-untyped-def]
    return context.make_array(ty)(context, b, value).data


def _row_ptr(b: ir.IRBuilder, base: ir.Value, index: ir.Value) -> ir.Value:
    return b.bitcast(b.gep(base, [index]), _V4.as_pointer())


def _load_row(b: ir.IRBuilder, base: ir.Value, index: ir.Value) -> ir.Value:
    return b.load(_row_ptr(b, base, index), align=8)


def _add_row(b: ir.IRBuilder, base: ir.Value, index: ir.Value, value: ir.Value, subtract: bool) -> None:
    p = _row_ptr(b, base, index)
    old = b.load(p, align=8)
    b.store(b.fsub(old, value) if subtract else b.fadd(old, value), p, align=8)


def _indices(b: ir.IRBuilder, base: ir.Value, start: ir.Value, count: int) -> list[ir.Value]:
    out = []
    for k in range(count):
        e = b.load(b.gep(base, [b.add(start, ir.Constant(_I64, k))]))
        out.append(b.zext(e, _I64) if e.type.width < 64 else e)
    return out


def _as_i64(b: ir.IRBuilder, v: ir.Value) -> ir.Value:
    return b.sext(v, _I64) if v.type.width < 64 else v


def _load_v8(b: ir.IRBuilder, base: ir.Value, start: ir.Value) -> ir.Value:
    return b.load(b.bitcast(b.gep(base, [start]), _V8.as_pointer()), align=8)


def _lane_sum(b: ir.IRBuilder, v: ir.Value) -> ir.Value:
    """The eight lanes added in order, as the scalar loop adds its elements."""
    acc = b.extract_element(v, ir.Constant(_I32, 0))
    for k in range(1, BLOCK):
        acc = b.fadd(acc, b.extract_element(v, ir.Constant(_I32, k)))
    return acc


def _call_v8(b: ir.IRBuilder, name: str, v: ir.Value) -> ir.Value:
    fn = cgutils.get_or_insert_function(b.module, ir.FunctionType(_V8, [_V8]), name)
    return b.call(fn, [v])


_V8I = ir.VectorType(_I64, BLOCK)


def _log_v8(b: ir.IRBuilder, x: ir.Value) -> ir.Value:
    """The natural log of eight positive doubles, to about an ulp, in vector instructions (libm's
    scalar log, one call a lane, cost the monitor's check steps 44 us at 2 196 nodes).

    x = 2^e m with m in [sqrt(1/2), sqrt(2)); log m = 2 atanh(s), s = (m - 1) / (m + 1), |s| <= 0.1716,
    by its series to s^21 (the next term below 1e-18 of the sum); log x = e ln2_hi + (log m + e ln2_lo)
    with fdlibm's split of ln 2 (e ln2_hi exact). +inf gives +inf; zero, negative and NaN inputs are
    not handled (the callers pass J floored at a positive value)."""
    bits = b.bitcast(x, _V8I)
    e = b.sub(b.lshr(bits, ir.Constant(_V8I, [52] * BLOCK)), ir.Constant(_V8I, [1023] * BLOCK))
    mant = b.or_(
        b.and_(bits, ir.Constant(_V8I, [0x000FFFFFFFFFFFFF] * BLOCK)),
        ir.Constant(_V8I, [0x3FF0000000000000] * BLOCK),
    )
    m = b.bitcast(mant, _V8)
    big = b.fcmp_ordered(">", m, _const(1.4142135623730951))
    m = b.select(big, b.fmul(m, _const(0.5)), m)
    e = b.select(big, b.add(e, ir.Constant(_V8I, [1] * BLOCK)), e)
    ef = b.sitofp(e, _V8)
    s = b.fdiv(b.fsub(m, _const(1.0)), b.fadd(m, _const(1.0)))
    z = b.fmul(s, s)
    poly = _const(1.0 / 21.0)
    for k in range(9, 0, -1):  # 1/3 + z/5 + ... + z^9/21
        poly = b.fadd(_const(1.0 / (2 * k + 1)), b.fmul(z, poly))
    s2 = b.fadd(s, s)
    log_m = b.fadd(s2, b.fmul(b.fmul(s2, z), poly))
    ln2_hi = 6.93147180369123816490e-01
    ln2_lo = 1.90821492927058770002e-10
    out = b.fadd(b.fmul(ef, _const(ln2_hi)), b.fadd(log_m, b.fmul(ef, _const(ln2_lo))))
    return b.select(b.fcmp_ordered("==", x, _const(float("inf"))), x, out)


def _spring_codegen(energy: bool, damped: bool):  # type: ignore[no-untyped-def]
    def codegen(context, b, signature, args):  # type: ignore[no-untyped-def]
        xa, va, eqa, epa, a2v, a3v, bv, oa = args
        t = signature.args
        X, V, EQ, EP, O = (
            _data(context, b, t[k], a) for k, a in ((0, xa), (1, va), (2, eqa), (3, epa), (7, oa))
        )
        bi = _as_i64(b, bv)
        idx = _indices(b, EQ, b.mul(bi, ir.Constant(_I64, 2 * BLOCK)), 2 * BLOCK)
        xi, yi, zi = _to_lanes(b, [_load_row(b, X, idx[2 * k]) for k in range(BLOCK)])
        xj, yj, zj = _to_lanes(b, [_load_row(b, X, idx[2 * k + 1]) for k in range(BLOCK)])
        pb = b.mul(bi, ir.Constant(_I64, SPRING_COLUMNS * BLOCK))
        inv_l0, kl0, c, l0 = (_load_v8(b, EP, b.add(pb, ir.Constant(_I64, BLOCK * r))) for r in range(4))
        dx, dy, dz = b.fsub(xj, xi), b.fsub(yj, yi), b.fsub(zj, zi)
        a2s, a3s = _splat(b, a2v), _splat(b, a3v)
        dv = None
        if damped:
            ui, vi, wi = _to_lanes(b, [_load_row(b, V, idx[2 * k]) for k in range(BLOCK)])
            uj, vj, wj = _to_lanes(b, [_load_row(b, V, idx[2 * k + 1]) for k in range(BLOCK)])
            dv = _rate(b, (ui, vi, wi), (uj, vj, wj), (dx, dy, dz))
        s, eps, e2 = _tension(b, dx, dy, dz, inv_l0, kl0, c, a2s, a3s, dv)
        rows = _to_rows(b, b.fmul(s, dx), b.fmul(s, dy), b.fmul(s, dz))
        for k in range(BLOCK):
            _add_row(b, O, idx[2 * k], rows[k], False)
            _add_row(b, O, idx[2 * k + 1], rows[k], True)
        if not energy:
            return context.get_dummy_value()
        return _lane_sum(b, _spring_energy(b, kl0, l0, eps, e2, a2s, a3s))

    return codegen


def _rate(b: ir.IRBuilder, vi: tuple, vj: tuple, d: tuple) -> ir.Value:
    """(v_j - v_i) . d of eight springs, d = x_j - x_i (the dashpot's rate of extension times L)."""
    return b.fadd(
        b.fadd(b.fmul(b.fsub(vj[0], vi[0]), d[0]), b.fmul(b.fsub(vj[1], vi[1]), d[1])),
        b.fmul(b.fsub(vj[2], vi[2]), d[2]),
    )


def _tension(b, dx, dy, dz, inv_l0, kl0, c, a2s, a3s, dv):  # type: ignore[no-untyped-def]
    """Eight springs' T / L (their force on node i is (T / L) d, on node j minus that, d = x_j - x_i)
    with T the law's tension k L0 (eps + a2 eps^2 + a3 eps^3) plus, when ``dv`` is given, the
    dashpot's c dv / L; returns (T / L, eps, eps^2). :func:`softgrasp.sim.fused.step._edge_pass`."""
    L = _call_v8(b, "llvm.sqrt.v8f64", b.fadd(b.fadd(b.fmul(dx, dx), b.fmul(dy, dy)), b.fmul(dz, dz)))
    one = _const(1.0)
    inv = b.fdiv(one, L)
    eps = b.fsub(b.fmul(L, inv_l0), one)
    e2 = b.fmul(eps, eps)
    T = b.fmul(kl0, b.fadd(b.fadd(eps, b.fmul(a2s, e2)), b.fmul(b.fmul(a3s, e2), eps)))
    if dv is not None:  # the dashpot: c times the rate of extension
        T = b.fadd(T, b.fmul(c, b.fmul(dv, inv)))
    return b.fmul(T, inv), eps, e2


def _spring_energy(b, kl0, l0, eps, e2, a2s, a3s):  # type: ignore[no-untyped-def]
    """Eight springs' energy, k L0 L0 (e^2 / 2 + a2 e^3 / 3 + a3 e^4 / 4), as _edge_pass."""
    a2_3 = b.fdiv(a2s, _const(3.0))
    a3_4 = b.fmul(_const(0.25), a3s)
    cubic = b.fadd(b.fmul(_const(0.5), e2), b.fmul(b.fmul(a2_3, e2), eps))
    return b.fmul(b.fmul(kl0, l0), b.fadd(cubic, b.fmul(b.fmul(a3_4, e2), e2)))


def _f64_arrays(*arrays) -> bool:  # type: ignore[no-untyped-def]
    return all(isinstance(a, types.Array) and a.dtype == types.float64 and a.ndim == 1 for a in arrays)


def _index_array(a) -> bool:  # type: ignore[no-untyped-def]
    return isinstance(a, types.Array) and a.dtype in (types.uint32, types.uint64) and a.ndim == 1


def _spring_intrinsic(energy: bool, damped: bool):  # type: ignore[no-untyped-def]
    def typer(typingctx, x, v, eq, ep, a2, a3, blk, out):  # type: ignore[no-untyped-def]
        if not (_f64_arrays(x, v, ep, out) and _index_array(eq) and isinstance(blk, types.Integer)):
            return None  # a typing error: flat float64 arrays, unsigned indices, an integer block
        ret = types.float64 if energy else types.void
        return ret(x, v, eq, ep, a2, a3, blk, out), _spring_codegen(energy, damped)

    return intrinsic(typer)


#: Columns of the springs' :func:`block_params`: 1 / L0, k L0, c, L0.
SPRING_COLUMNS = 4
#: Columns of the tets' :func:`block_params`: 1 / (6 V0), V0.
TET_COLUMNS = 2

#: Springs and dashpots ``8 blk .. 8 blk + 7`` added to ``out``:
#: ``spring_block(x, v, eq, ep, a2, a3, blk, out)`` with x, v, out flat views of (N, 4) arrays;
#: ``eq`` the edges' nodes times 4, two an edge; ``ep`` :func:`block_params` of (1 / L0, k L0, c,
#: L0); ``a2``, ``a3`` the law's coefficients. The arithmetic of
#: :func:`softgrasp.sim.fused.step._edge_pass` with dashpots, eight edges a time.
spring_block = _spring_intrinsic(False, True)
#: The same, returning the eight springs' energy [J] summed.
spring_block_energy = _spring_intrinsic(True, True)
#: :data:`spring_block` without dashpots (``v`` and c not read).
spring_block_undamped = _spring_intrinsic(False, False)
#: :data:`spring_block_energy` without dashpots.
spring_block_undamped_energy = _spring_intrinsic(True, False)


def _volume_codegen(barrier: bool, full: bool):  # type: ignore[no-untyped-def]
    def codegen(context, b, signature, args):  # type: ignore[no-untyped-def]
        xa, tqa, tpa, kv, floor_v, bv, oa = args
        t = signature.args
        X, TQ, TP, O = (_data(context, b, t[k], a) for k, a in ((0, xa), (1, tqa), (2, tpa), (6, oa)))
        bi = _as_i64(b, bv)
        idx = _indices(b, TQ, b.mul(bi, ir.Constant(_I64, 4 * BLOCK)), 4 * BLOCK)
        n = [_to_lanes(b, [_load_row(b, X, idx[4 * k + r]) for k in range(BLOCK)]) for r in range(4)]
        pb = b.mul(bi, ir.Constant(_I64, TET_COLUMNS * BLOCK))
        vol = _volume(b, n, _load_v8(b, TP, pb), _splat(b, kv), floor_v, barrier)
        s = vol["s"]
        f1 = _to_rows(b, *(b.fmul(s, w) for w in vol["c1"]))
        f2 = _to_rows(b, *(b.fmul(s, w) for w in vol["c2"]))
        f3 = _to_rows(b, *(b.fmul(s, w) for w in vol["c3"]))
        for k in range(BLOCK):
            _add_row(b, O, idx[4 * k + 1], f1[k], False)
            _add_row(b, O, idx[4 * k + 2], f2[k], False)
            _add_row(b, O, idx[4 * k + 3], f3[k], False)
            _add_row(b, O, idx[4 * k], b.fadd(b.fadd(f1[k], f2[k]), f3[k]), True)
        if not full:
            return context.get_dummy_value()
        v0 = _load_v8(b, TP, b.add(pb, ir.Constant(_I64, BLOCK)))
        energy = _lane_sum(b, _volume_energy(b, vol, v0, barrier))
        return context.make_tuple(b, signature.return_type, [energy, _inverted_mask(b, vol["det"])])

    return codegen


def _volume(b, n, inv_6v0, kappa, floor_v, barrier: bool) -> dict:  # type: ignore[no-untyped-def]
    """The volume term of eight tets with vertices ``n`` (four (x, y, z) lane triples): the
    cross products c1 = b x c, c2 = c x a, c3 = a x b of the edge vectors a, b, c from vertex 0
    (the gradients of 6 V), det = a . c1, J = det / (6 V0), the barrier's floored J (Jc),
    psi'(J) (dw) and s = -kappa dw / 6: the force on vertex k = 1..3 is s c_k, on vertex 0 minus
    their sum. :func:`softgrasp.sim.fused.step._tet_pass`."""
    (x0, y0, z0), (x1, y1, z1), (x2, y2, z2), (x3, y3, z3) = n
    ax, ay, az = b.fsub(x1, x0), b.fsub(y1, y0), b.fsub(z1, z0)
    bx, by, bz = b.fsub(x2, x0), b.fsub(y2, y0), b.fsub(z2, z0)
    cx, cy, cz = b.fsub(x3, x0), b.fsub(y3, y0), b.fsub(z3, z0)

    def cross(p, q, r, s):  # type: ignore[no-untyped-def]
        return b.fsub(b.fmul(p, q), b.fmul(r, s))

    c1 = (cross(by, cz, bz, cy), cross(bz, cx, bx, cz), cross(bx, cy, by, cx))
    c2 = (cross(cy, az, cz, ay), cross(cz, ax, cx, az), cross(cx, ay, cy, ax))
    c3 = (cross(ay, bz, az, by), cross(az, bx, ax, bz), cross(ax, by, ay, bx))
    det = b.fadd(b.fadd(b.fmul(ax, c1[0]), b.fmul(ay, c1[1])), b.fmul(az, c1[2]))
    J = b.fmul(det, inv_6v0)
    one = _const(1.0)
    Jc = J
    if barrier:
        floor = _splat(b, floor_v)
        Jc = b.select(b.fcmp_ordered(">", J, floor), J, floor)
        dw = b.fsub(one, b.fdiv(one, Jc))
    else:
        dw = b.fsub(J, one)
    s = b.fmul(b.fdiv(b.fsub(_const(0.0), kappa), _const(6.0)), dw)
    return {"c1": c1, "c2": c2, "c3": c3, "det": det, "J": J, "Jc": Jc, "dw": dw, "s": s, "kappa": kappa}


def _volume_energy(b, vol: dict, v0, barrier: bool):  # type: ignore[no-untyped-def]
    """Eight tets' volume energy, kappa V0 (J - 1 - log Jc) or kappa V0 dw^2 / 2, as _tet_pass."""
    kv0 = b.fmul(vol["kappa"], v0)
    if barrier:
        psi = b.fsub(b.fsub(vol["J"], _const(1.0)), _log_v8(b, vol["Jc"]))
    else:
        psi = b.fmul(_const(0.5), b.fmul(vol["dw"], vol["dw"]))
    return b.fmul(kv0, psi)


def _inverted_mask(b: ir.IRBuilder, det: ir.Value) -> ir.Value:
    """Bit k set where tet k's signed volume det / 6 is not > 0 (an i64)."""
    ok = b.fcmp_ordered(">", b.fdiv(det, _const(6.0)), _const(0.0))
    bad = b.xor(ok, ir.Constant(ir.VectorType(ir.IntType(1), BLOCK), [1] * BLOCK))
    return b.zext(b.bitcast(bad, ir.IntType(BLOCK)), _I64)


def _volume_intrinsic(barrier: bool, full: bool):  # type: ignore[no-untyped-def]
    def typer(typingctx, x, tq, tp, kappa, floor, blk, out):  # type: ignore[no-untyped-def]
        if not (_f64_arrays(x, tp, out) and _index_array(tq) and isinstance(blk, types.Integer)):
            return None  # a typing error: flat float64 arrays, unsigned indices, an integer block
        ret = types.Tuple((types.float64, types.int64)) if full else types.void
        return ret(x, tq, tp, kappa, floor, blk, out), _volume_codegen(barrier, full)

    return intrinsic(typer)


#: Volume-term forces of tets ``8 blk .. 8 blk + 7`` added to ``out``:
#: ``volume_block(x, tq, tp, kappa, floor, blk, out)`` with x, out flat views of (N, 4) arrays,
#: ``tq`` the tets' nodes times 4, four a tet, ``tp`` :func:`block_params` of (1 / (6 V0), V0): the
#: barrier law with J floored at ``floor``. The arithmetic of :func:`softgrasp.sim.fused.step._tet_pass`,
#: eight tets a time.
volume_block = _volume_intrinsic(True, False)
#: The same for the quadratic volume law (``floor`` unused).
volume_block_quadratic = _volume_intrinsic(False, False)
#: :data:`volume_block`, returning (the eight tets' energy [J] summed, a mask of the inverted ones:
#: bit k set where tet ``8 blk + k`` has a signed volume not > 0).
volume_block_full = _volume_intrinsic(True, True)
#: The same for the quadratic volume law.
volume_block_quadratic_full = _volume_intrinsic(False, True)


#: Columns of the tets-with-a-spring kernels' :func:`block_params`: 1 / (6 V0), V0, then for the
#: spring between vertices 0 and 1: 1 / L0, k L0, c, L0.
TET_SPRING_COLUMNS = TET_COLUMNS + SPRING_COLUMNS


def _tet_spring_codegen(barrier: bool, full: bool, damped: bool):  # type: ignore[no-untyped-def]
    def codegen(context, b, signature, args):  # type: ignore[no-untyped-def]
        xa, va, tqa, tpa, kv, floor_v, a2v, a3v, bv, oa = args
        t = signature.args
        X, V, TQ, TP, O = (
            _data(context, b, t[k], a) for k, a in ((0, xa), (1, va), (2, tqa), (3, tpa), (9, oa))
        )
        bi = _as_i64(b, bv)
        idx = _indices(b, TQ, b.mul(bi, ir.Constant(_I64, 4 * BLOCK)), 4 * BLOCK)
        n = [_to_lanes(b, [_load_row(b, X, idx[4 * k + r]) for k in range(BLOCK)]) for r in range(4)]
        pb = b.mul(bi, ir.Constant(_I64, TET_SPRING_COLUMNS * BLOCK))
        col = [_load_v8(b, TP, b.add(pb, ir.Constant(_I64, BLOCK * r))) for r in range(TET_SPRING_COLUMNS)]
        vol = _volume(b, n, col[0], _splat(b, kv), floor_v, barrier)
        s = vol["s"]
        f1 = [b.fmul(s, w) for w in vol["c1"]]
        f2 = [b.fmul(s, w) for w in vol["c2"]]
        f3 = [b.fmul(s, w) for w in vol["c3"]]
        f0 = [b.fsub(_const(0.0), b.fadd(b.fadd(f1[d], f2[d]), f3[d])) for d in range(3)]
        # the spring from vertex 0 to vertex 1: + (T / L) d on vertex 0, - on vertex 1
        inv_l0, kl0, c, l0 = col[TET_COLUMNS:]
        a2s, a3s = _splat(b, a2v), _splat(b, a3v)
        d = [b.fsub(n[1][k], n[0][k]) for k in range(3)]
        dv = None
        if damped:
            v0 = _to_lanes(b, [_load_row(b, V, idx[4 * k]) for k in range(BLOCK)])
            v1 = _to_lanes(b, [_load_row(b, V, idx[4 * k + 1]) for k in range(BLOCK)])
            dv = _rate(b, v0, v1, d)
        ts, eps, e2 = _tension(b, *d, inv_l0, kl0, c, a2s, a3s, dv)
        g = [b.fmul(ts, d[k]) for k in range(3)]
        forces = ([b.fadd(f0[k], g[k]) for k in range(3)], [b.fsub(f1[k], g[k]) for k in range(3)], f2, f3)
        for r, f in enumerate(forces):
            rows = _to_rows(b, *f)
            for k in range(BLOCK):
                _add_row(b, O, idx[4 * k + r], rows[k], False)
        if not full:
            return context.get_dummy_value()
        energy = b.fadd(
            _volume_energy(b, vol, col[1], barrier), _spring_energy(b, kl0, l0, eps, e2, a2s, a3s)
        )
        mask = _inverted_mask(b, vol["det"])
        return context.make_tuple(b, signature.return_type, [_lane_sum(b, energy), mask])

    return codegen


def _tet_spring_intrinsic(barrier: bool, full: bool, damped: bool):  # type: ignore[no-untyped-def]
    def typer(typingctx, x, v, tq, tp, kappa, floor, a2, a3, blk, out):  # type: ignore[no-untyped-def]
        if not (_f64_arrays(x, v, tp, out) and _index_array(tq) and isinstance(blk, types.Integer)):
            return None  # a typing error: flat float64 arrays, unsigned indices, an integer block
        ret = types.Tuple((types.float64, types.int64)) if full else types.void
        return ret(x, v, tq, tp, kappa, floor, a2, a3, blk, out), _tet_spring_codegen(barrier, full, damped)

    return intrinsic(typer)


#: The volume term of tets ``8 blk .. 8 blk + 7`` and the spring (+ dashpot) each carries between
#: its vertices 0 and 1 (none: k L0 = c = 0, 1 / L0 = L0 = 1), added to ``out``:
#: ``tet_spring_block(x, v, tq, tp, kappa, floor, a2, a3, blk, out)`` with ``tp``
#: :func:`block_params` of the :data:`TET_SPRING_COLUMNS`. A tet's four force rows take both terms
#: to the nodes at once (the springs' own kernel updates two rows a spring). Variants: the
#: quadratic volume law, undamped springs, and ``_full`` returning (energy [J], inverted mask) as
#: :data:`volume_block_full`, the spring's energy included.
tet_spring_block = _tet_spring_intrinsic(True, False, True)
tet_spring_block_full = _tet_spring_intrinsic(True, True, True)
tet_spring_block_quadratic = _tet_spring_intrinsic(False, False, True)
tet_spring_block_quadratic_full = _tet_spring_intrinsic(False, True, True)
tet_spring_block_undamped = _tet_spring_intrinsic(True, False, False)
tet_spring_block_undamped_full = _tet_spring_intrinsic(True, True, False)
tet_spring_block_quadratic_undamped = _tet_spring_intrinsic(False, False, False)
tet_spring_block_quadratic_undamped_full = _tet_spring_intrinsic(False, True, False)


def _node_codegen(two_parts: bool, nodes: int):  # type: ignore[no-untyped-def]
    lanes = 4 * nodes
    vec = ir.VectorType(_F64, lanes)

    def codegen(context, b, signature, args):  # type: ignore[no-untyped-def]
        xa, va, ra, fa, ga, pa, qa, rv, wv = args[:9]
        masses, dtv = args[9 : 9 + nodes], args[9 + nodes]
        t = signature.args
        X, V, R, F, G, Pp, Q = (
            _data(context, b, t[k], a) for k, a in enumerate((xa, va, ra, fa, ga, pa, qa))
        )
        r = _as_i64(b, rv)

        def ptr(base, at=r):  # type: ignore[no-untyped-def]  # the node's row (rows) from ``at``
            return b.bitcast(b.gep(base, [at]), vec.as_pointer())

        def load(base, at=r):  # type: ignore[no-untyped-def]
            return b.load(ptr(base, at), align=8)

        f = load(F)
        if two_parts:
            f = b.fadd(f, load(F, b.add(_as_i64(b, wv), r)))
        m = _splat(b, masses[0], 4)
        if nodes == 2:
            m = b.shuffle_vector(m, _splat(b, masses[1], 4), _mask(range(8)))
        dt = _splat(b, dtv, lanes)
        a = b.fdiv(b.fadd(b.fadd(b.fadd(f, load(G)), load(Pp)), load(Q)), m)
        zero = ir.Constant(vec, [0.0] * lanes)
        b.store(zero, ptr(Pp), align=8)
        b.store(zero, ptr(Q), align=8)
        v_new = b.fadd(load(V), b.fmul(dt, a))
        x_new = b.fadd(load(X), b.fmul(dt, v_new))
        b.store(v_new, ptr(V), align=8)
        b.store(x_new, ptr(X), align=8)
        fabs = cgutils.get_or_insert_function(b.module, ir.FunctionType(vec, [vec]), f"llvm.fabs.v{lanes}f64")
        inf = ir.Constant(vec, [float("inf")] * lanes)
        finite = b.and_(
            b.fcmp_ordered("<", b.call(fabs, [v_new]), inf), b.fcmp_ordered("<", b.call(fabs, [x_new]), inf)
        )
        bits = b.bitcast(finite, ir.IntType(lanes))
        bad = b.zext(b.icmp_unsigned("!=", bits, ir.Constant(ir.IntType(lanes), 2**lanes - 1)), _I64)
        du = b.fsub(x_new, load(R))
        out = []
        for h in range(0, lanes, 4):  # each node's |x - x_ref|^2
            du2 = ir.Constant(_F64, 0.0)
            for k in range(3):
                e = b.extract_element(du, ir.Constant(_I32, h + k))
                du2 = b.fadd(du2, b.fmul(e, e))
            out.append(du2)
        return context.make_tuple(b, signature.return_type, [*out, bad])

    return codegen


def _node_intrinsic(two_parts: bool):  # type: ignore[no-untyped-def]
    def typer(typingctx, x, v, ref, f, g, p, q, row, width, m, dt):  # type: ignore[no-untyped-def]
        scalars = (
            isinstance(width, types.Integer) and isinstance(m, types.Float) and isinstance(dt, types.Float)
        )
        if not (_f64_arrays(x, v, ref, f, g, p, q) and isinstance(row, types.Integer) and scalars):
            return None
        ret = types.Tuple((types.float64, types.int64))
        return ret(x, v, ref, f, g, p, q, row, width, m, dt), _node_codegen(two_parts, 1)

    return intrinsic(typer)


def _pair_intrinsic(two_parts: bool):  # type: ignore[no-untyped-def]
    def typer(typingctx, x, v, ref, f, g, p, q, row, width, ma, mb, dt):  # type: ignore[no-untyped-def]
        scalars = all(isinstance(s, types.Float) for s in (ma, mb, dt)) and isinstance(width, types.Integer)
        if not (_f64_arrays(x, v, ref, f, g, p, q) and isinstance(row, types.Integer) and scalars):
            return None
        ret = types.Tuple((types.float64, types.float64, types.int64))
        return ret(x, v, ref, f, g, p, q, row, width, ma, mb, dt), _node_codegen(two_parts, 2)

    return intrinsic(typer)


#: One node's semi-implicit step on (N, 4) rows, ``node_step(x, v, x_ref, fint, grav, fplane, ffinger,
#: r, part, m, dt)`` (flat views; ``r`` the node's row start, 4 i; ``part`` the length of one part
#: of ``fint``): a = (((fint + m g) + f_planes) + f_fingers) / m with the force buffers' parts
#: summed first (one here, two in :data:`node_step_two`), v += dt a, x += dt v, the contact rows
#: zeroed; returns (|x - x_ref|^2, 1 if a value of v or x is not finite). The arithmetic of
#: :func:`softgrasp.sim.fused.step._node_part`'s loop, four columns at a time (the same bits).
node_step = _node_intrinsic(False)
#: :data:`node_step` with two parts of the force buffer.
node_step_two = _node_intrinsic(True)
#: :data:`node_step` for two neighbouring nodes at once (rows ``r`` and ``r + 4``, masses ``ma``,
#: ``mb``): ``node_pair_step(x, v, x_ref, fint, grav, fplane, ffinger, r, part, ma, mb, dt)``
#: returns (|x - x_ref|^2 of each, 1 if a value of v or x is not finite). The same bits.
node_pair_step = _pair_intrinsic(False)
#: :data:`node_pair_step` with two parts of the force buffer.
node_pair_step_two = _pair_intrinsic(True)
