"""Compilation of the fused stepper's kernels: Numba's on-disk cache, keyed by every source they inline.

The fused kernels call compiled functions of other modules (the spring and volume laws of
:mod:`softgrasp.physics.forces_compiled`, the plane law of :mod:`softgrasp.physics.planes_compiled`,
the fingertip kernels of :mod:`softgrasp.physics.fingertip.compiled`, and one another across the
modules of this package), and Numba compiles those callees into their machine code. Numba's
cache checks only a function's own file for changes, so after an edit of a callee's module a
cached kernel would run the callee's earlier code. Here every cached kernel's index key also
holds :data:`SOURCE_DIGEST`, the SHA-256 of the sources of :data:`INLINED_MODULES` computed at
import (under a millisecond): an edit of any of them compiles the kernels afresh, once (the
cache then holds the new code); a run with the sources unchanged loads them as Numba's own cache
does.
"""

from __future__ import annotations

import hashlib
import importlib.util
from collections.abc import Callable
from typing import Any

import numba
from numba.core.caching import FunctionCache

__all__ = ["INLINED_MODULES", "SOURCE_DIGEST", "jit", "pjit", "source_digest"]

#: Modules whose compiled functions the fused kernels call (their sources key the cache).
INLINED_MODULES = (
    "softgrasp.physics.forces_compiled",
    "softgrasp.physics.planes_compiled",
    "softgrasp.physics.fingertip.compiled",
    "softgrasp.sim.fused.body",
    "softgrasp.sim.fused.contacts",
    "softgrasp.sim.fused.monitor",
    "softgrasp.sim.fused.rk4",
)


def source_digest(modules: tuple[str, ...] = INLINED_MODULES) -> str:
    """SHA-256 over the source files of ``modules`` (found without importing them)."""
    h = hashlib.sha256()
    for name in modules:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            raise ImportError(f"cannot find the source of {name}")
        with open(spec.origin, "rb") as f:
            h.update(name.encode() + b"\0" + f.read() + b"\0")
    return h.hexdigest()


#: :func:`source_digest` of :data:`INLINED_MODULES`, at import.
SOURCE_DIGEST = source_digest()


class SourceKeyedCache(FunctionCache):
    """Numba's cache of one function, its index key extended by :data:`SOURCE_DIGEST`."""

    def __init__(self, py_func: Callable[..., Any], digest: str = SOURCE_DIGEST) -> None:
        super().__init__(py_func)
        self.digest = digest

    def _index_key(self, sig: Any, codegen: Any) -> tuple:
        return (*super()._index_key(sig, codegen), self.digest)


def _keyed(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    def decorate(func: Callable[..., Any]) -> Any:
        dispatcher = numba.njit(cache=False, fastmath=False, error_model="numpy", **options)(func)
        dispatcher._cache = SourceKeyedCache(dispatcher.py_func)
        return dispatcher

    return decorate


#: ``numba.njit`` for the fused kernels (no fast-math: NaN and infinity keep their meaning for the
#: blow-up checks; a division by zero gives inf/nan as in NumPy), cached under the source digest.
jit = _keyed()
#: :data:`jit` with Numba's parallel loops (``prange``).
pjit = _keyed(parallel=True)
