"""Every compiled kernel is cached under the digest of all kernel sources (softgrasp.jitcache), so
an edit of a callee's module can never leave a caller's cached machine code stale."""

from __future__ import annotations

import importlib
import pathlib
import pkgutil
import re

import softgrasp
from softgrasp import jitcache

SRC = pathlib.Path(softgrasp.__file__).parent


def _dispatchers() -> list:
    """Every Numba dispatcher reachable as a module attribute of the package's modules."""
    found = []
    for info in pkgutil.walk_packages(softgrasp.__path__, "softgrasp."):
        if info.name.startswith(("softgrasp.cli", "softgrasp.api")) or info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for value in vars(module).values():
            if hasattr(value, "py_func") and hasattr(value, "_cache"):
                found.append(value)
    return found


def test_every_kernel_is_keyed_by_the_kernel_sources() -> None:
    kernels = _dispatchers()
    assert len(kernels) > 50  # the laws, the fused stepper, the placement, the sparse kernels
    for kernel in kernels:
        assert isinstance(kernel._cache, jitcache.SourceKeyedCache), kernel.py_func.__qualname__
        assert kernel._cache.digest == jitcache.SOURCE_DIGEST
        assert kernel.py_func.__module__ in jitcache.KERNEL_MODULES, kernel.py_func.__module__


def test_kernel_modules_are_the_modules_that_define_kernels() -> None:
    """No module listed without kernels of its own; no kernel module compiled past the cache."""
    defining = {k.py_func.__module__ for k in _dispatchers()}
    assert set(jitcache.KERNEL_MODULES) - defining <= {"softgrasp.physics.jit"}  # the decorators
    for path in SRC.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert not re.search(r"numba\.(njit|jit)\(cache=True", text), f"{path}: use softgrasp.jitcache.jit"


def test_the_key_changes_with_the_sources() -> None:
    from softgrasp.sim.fused import rk4

    assert jitcache.SOURCE_DIGEST == jitcache.source_digest()
    keyed = jitcache.SourceKeyedCache(rk4.advance.py_func)
    other = jitcache.SourceKeyedCache(rk4.advance.py_func, digest="0" * 64)
    sig, codegen = ("a signature",), rk4.advance.targetctx.codegen()
    assert keyed._index_key(sig, codegen) != other._index_key(sig, codegen)
    assert keyed._index_key(sig, codegen)[:-1] == other._index_key(sig, codegen)[:-1]
    assert jitcache.source_digest(jitcache.KERNEL_MODULES[:-1]) != jitcache.SOURCE_DIGEST
