"""How the body's force kernels are compiled, and the arrays they take.

Kernels are compiled with ``cache=True`` (on-disk cache: only the first run compiles) and
``error_model="numpy"`` (a division by zero gives inf/nan, which the blow-up monitor detects,
rather than raising). :data:`jit` keeps IEEE arithmetic exactly as written; :data:`fjit` may
fuse ``a * b + c`` into one FMA instruction ("contract": one rounding instead of two). It removes
a third of the force kernels' floating-point instructions but only ~5 % of their time: their
scattered loads and read-modify-write stores bound them more. No other fast-math flag: NaN and
infinity keep their meaning (the blow-up checks rely on them).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from softgrasp import jitcache

__all__ = ["Array", "IntArray", "jit", "fjit", "f64", "i64", "NO_POS", "NO_ORDER"]

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

jit = jitcache.jit(fastmath=False, error_model="numpy")
fjit = jitcache.jit(fastmath={"contract"}, error_model="numpy")

#: Placeholder block positions for kernels that write blocks one after another (``use_pos`` false).
NO_POS = np.zeros(1, dtype=np.int64)
#: An empty element order: the elements in their own order.
NO_ORDER = np.zeros(0, dtype=np.int64)


def f64(a: Array) -> Array:
    """``a`` as a writable contiguous float64 array (no copy when it already is one). Kernels are
    compiled once per argument type, and Numba types a read-only array apart from a writable one:
    a read-only input (a frozen mesh's points, say) is copied so that each kernel compiles once."""
    out = np.ascontiguousarray(a, dtype=np.float64)
    return out if out.flags.writeable else out.copy()


def i64(a: IntArray) -> IntArray:
    """``a`` as a contiguous int64 array (no copy when it already is one)."""
    return np.ascontiguousarray(a, dtype=np.int64)
