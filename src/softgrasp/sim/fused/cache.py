"""The fused stepper's compile options (:func:`softgrasp.jitcache.jit`, cached under the digest of
every kernel source): no fast-math, so NaN and infinity keep their meaning for the blow-up checks,
and a division by zero gives inf/nan as in NumPy."""

from __future__ import annotations

from softgrasp import jitcache

__all__ = ["jit", "pjit"]

#: ``numba.njit`` for the fused kernels.
jit = jitcache.jit(fastmath=False, error_model="numpy")
#: :data:`jit` with Numba's parallel loops (``prange``).
pjit = jitcache.jit(fastmath=False, error_model="numpy", parallel=True)
