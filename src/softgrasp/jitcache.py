"""Compiling softgrasp's kernels: Numba's on-disk cache, keyed by every kernel source.

Kernels call compiled functions of other modules (the fingertip kernels call the contact laws,
the fused stepper calls the spring, volume and plane laws, the placement calls the kinematics),
and Numba compiles those callees into the caller's machine code. Numba's own cache checks only
the caller's file for changes, so after an edit of a callee's module a cached caller would run
the callee's earlier code. Every kernel of softgrasp is therefore compiled with :func:`jit`,
whose cache index key also holds :data:`SOURCE_DIGEST`, the SHA-256 of the sources of all
:data:`KERNEL_MODULES` (computed at import, about a millisecond): an edit of any of them compiles
the kernels afresh, once; unchanged sources load from the cache as Numba's own cache does.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
from numba.core.caching import FunctionCache

from softgrasp import (
    backend,  # noqa: F401 - Intel TBB made loadable for Numba's threads first
    usercache,
)

__all__ = ["KERNEL_MODULES", "SOURCE_DIGEST", "SourceKeyedCache", "cached", "jit", "source_digest"]

#: Every module that defines compiled kernels (with :func:`jit`); their sources key the cache.
KERNEL_MODULES = (
    "softgrasp.linalg.pattern",
    "softgrasp.linalg.smoothers",
    "softgrasp.linalg.sparse",
    "softgrasp.physics.jit",
    "softgrasp.physics.springs",
    "softgrasp.physics.volume",
    "softgrasp.physics.nodal_volume",
    "softgrasp.physics.forces_compiled",
    "softgrasp.physics.planes_compiled",
    "softgrasp.physics.fingertip.laws",
    "softgrasp.physics.fingertip.resolved",
    "softgrasp.physics.fingertip.detect",
    "softgrasp.physics.fingertip.forces",
    "softgrasp.physics.fingertip.friction",
    "softgrasp.physics.fingertip.compiled",
    "softgrasp.hand.fk",
    "softgrasp.hand.wdls",
    "softgrasp.hand.descent",
    "softgrasp.sim.fused.body",
    "softgrasp.sim.fused.contacts",
    "softgrasp.sim.fused.monitor",
    "softgrasp.sim.fused.rk4",
)


def source_digest(modules: tuple[str, ...] = KERNEL_MODULES) -> str:
    """SHA-256 over the source files of ``modules`` (:func:`softgrasp.usercache.source_digest`)."""
    return usercache.source_digest(*modules)


#: :func:`source_digest` of :data:`KERNEL_MODULES`, at import.
SOURCE_DIGEST = source_digest()


class SourceKeyedCache(FunctionCache):
    """Numba's cache of one function, its index key extended by a digest of the kernel sources."""

    def __init__(self, py_func: Callable[..., Any], digest: str = SOURCE_DIGEST) -> None:
        super().__init__(py_func)
        self.digest = digest

    def _index_key(self, sig: Any, codegen: Any) -> tuple:
        return (*super()._index_key(sig, codegen), self.digest)


def jit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(**options)``, cached on disk under :data:`SOURCE_DIGEST`."""

    def decorate(func: Callable[..., Any]) -> Any:
        dispatcher = numba.njit(cache=False, **options)(func)
        dispatcher._cache = SourceKeyedCache(dispatcher.py_func)
        return dispatcher

    return decorate


def cached(dispatcher: Any) -> bool:
    """Whether kernel ``dispatcher`` (compiled with :func:`jit`) has machine code on disk for the
    current kernel sources and this CPU, for some argument types: loading it then takes a fraction
    of a second, where compiling it takes seconds. False when it has none, when its cache index
    cannot be read, or when ``dispatcher`` is not such a kernel."""
    cache = getattr(dispatcher, "_cache", None)
    if not isinstance(cache, SourceKeyedCache):
        return False
    try:
        index = cache._cache_file._load_index()  # {index key: data file}, empty when stale
        magic = dispatcher.targetctx.codegen().magic_tuple()
    except Exception:  # noqa: BLE001 - an unreadable index is a cold cache
        return False
    return any(key[-1] == cache.digest and key[1] == magic for key in index)
