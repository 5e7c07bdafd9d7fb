"""Two threads meeting on shared flags: the fused stepper's leader and worker, a few times a step.

The fused explicit stepper (:mod:`softgrasp.sim.fused.step`) runs a step in about 100 us on two
threads. Numba's ``prange`` hands work to its thread pool and waits for it at every parallel
region (about 1.7 us on this project's reference machine, twice a step, plus the serial work
between the regions that the second thread sits out). Instead, two threads each run a whole chunk
of steps in one compiled call, and meet where the data demands it by writing and polling counters
in a shared ``int64`` array: a release store of "I have reached point p of step s" and acquire
loads until the other thread's counter has too. The functions here are those loads and stores
(LLVM atomics through :func:`numba.extending.intrinsic`, inlined) and the wait built on them.

A waiting thread spins with the CPU's pause hint, and after :data:`SPINS` polls also gives its
core away (``sched_yield``) on every poll, so that a thread waiting for one the scheduler has put
aside does not hold the core that one needs. Every wait also watches a stop slot that either side
(or Python, when a thread failed) sets, so a thread never waits for one that is gone.

Slots are spread :data:`STRIDE` apart (64 bytes: one cache line each).
"""

from __future__ import annotations

import os
import platform

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["SPINS", "STRIDE", "load_acquire", "relax", "store_release"]

#: int64 slots between two counters of the shared array (one 64-byte cache line each).
STRIDE = 8
#: Polls with the pause hint (about 25 ns each on the reference machine: 0.1 ms, ten times a normal
#: wait) before a waiting thread starts yielding its core at every poll.
SPINS = 4000

_I64 = ir.IntType(64)
_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686", "x86")
_YIELD = os.name == "posix"


def _int64_array(a) -> bool:  # type: ignore[no-untyped-def]
    return isinstance(a, types.Array) and a.dtype == types.int64 and a.ndim == 1


def _slot_pointer(context, builder, aryty, ary, index):  # type: ignore[no-untyped-def]
    array = context.make_array(aryty)(context, builder, ary)
    return cgutils.get_item_pointer(context, builder, aryty, array, [index])


@intrinsic
def load_acquire(typingctx, flags, slot):  # type: ignore[no-untyped-def]
    """``flags[slot]`` read with acquire ordering: whatever the writer stored before its release
    store of this value is visible after this load (and the load is never hoisted out of a loop).
    ``flags``: 1-D int64 array; ``slot`` in range (not checked)."""
    if not (_int64_array(flags) and isinstance(slot, types.Integer)):
        return None

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        p = _slot_pointer(context, builder, sig.args[0], args[0], args[1])
        return builder.load_atomic(p, "acquire", 8)

    return types.int64(flags, slot), codegen


@intrinsic
def store_release(typingctx, flags, slot, value):  # type: ignore[no-untyped-def]
    """``flags[slot] = value`` with release ordering: everything this thread wrote before is visible
    to a thread whose acquire load reads this value."""
    if not (_int64_array(flags) and isinstance(slot, types.Integer) and isinstance(value, types.Integer)):
        return None

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        p = _slot_pointer(context, builder, sig.args[0], args[0], args[1])
        val = context.cast(builder, args[2], sig.args[2], types.int64)
        builder.store_atomic(val, p, "release", 8)
        return context.get_dummy_value()

    return types.void(flags, slot, value), codegen


@intrinsic
def relax(typingctx, polls):  # type: ignore[no-untyped-def]
    """One poll's pause while spinning: the CPU's spin-wait hint (x86 ``pause``), and from the
    :data:`SPINS`-th poll of a wait on (``polls`` so far) also ``sched_yield`` (POSIX)."""
    if not isinstance(polls, types.Integer):
        return None

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        n = context.cast(builder, args[0], sig.args[0], types.int64)
        if _X86:
            pause = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), []), "llvm.x86.sse2.pause"
            )
            builder.call(pause, [])
        if _YIELD:
            with builder.if_then(builder.icmp_signed(">=", n, ir.Constant(_I64, SPINS)), likely=False):
                sched_yield = cgutils.get_or_insert_function(
                    builder.module, ir.FunctionType(ir.IntType(32), []), "sched_yield"
                )
                builder.call(sched_yield, [])
        return context.get_dummy_value()

    return types.void(polls), codegen
