"""The object's rest on the table, kept across processes.

Settling the object on the table (:func:`~softgrasp.grasp.settle.settle_on_table`) depends on the
object and the table only, not on the hand, the fingertips or the grasp: a plan of the same object
again (another hand, other fingertips, another safety factor or hold time) finds the same rest.
:func:`settle` keeps it in softgrasp's cache folder (:mod:`softgrasp.usercache`), keyed by
everything it depends on:

* the body, written down exactly (:func:`~softgrasp.usercache.value_digest`: its mesh, masses,
  springs, volume term, material and gravity);
* the table's friction coefficient and the linear solver's settings (its method, tolerance,
  precision, and the thread counts of the factorisation and of the force sums: a sum over
  threads rounds differently);
* the sources of the modules that settle it, the versions of NumPy, SciPy, Numba and MKL, and
  the processor's name and features (MKL and the compiled kernels take other code paths, which
  round differently, on other processors: a cache folder shared between machines keeps a rest
  per kind of processor).

The settle runs on a solver state of its own (a fresh :class:`~softgrasp.linalg.solve.SolverCache`
of the caller's settings, whose counts are added to the caller's): what follows it then starts
from the same solver state whether the rest was found now or read back, and a plan from a kept rest
is the plan from a settled one, bit for bit.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from softgrasp import usercache
from softgrasp.grasp.config import PlanConfig
from softgrasp.grasp.settle import settle_on_table, table_under
from softgrasp.linalg.solve import SolverCache
from softgrasp.linalg.threads import choose_threads, factor_threads
from softgrasp.physics.body import Body
from softgrasp.physics.planes import PlaneContact, PlaneState
from softgrasp.sim.scene import State

__all__ = ["SETTLE_SOURCES", "settle"]

#: The packages and modules whose sources decide a rest (they key its entry).
SETTLE_SOURCES = (
    "softgrasp.model",
    "softgrasp.physics",
    "softgrasp.linalg",
    "softgrasp.sim",
    "softgrasp.grasp.config",
    "softgrasp.grasp.settle",
    "softgrasp.grasp.kept_rest",
    "softgrasp.jitcache",
    "softgrasp.backend",
)

#: The folder of the kept rests in the cache folder.
KIND = "rests"


def settle(
    body: Body, cfg: PlanConfig, cache: SolverCache, *, keep: bool = False
) -> tuple[State, PlaneContact, NDArray[np.float64]]:
    """:func:`~softgrasp.grasp.settle.settle_on_table` on a solver state of its own (its counts
    added to ``cache``'s, ``settle_systems`` among them); with ``keep``, read from the cache
    folder when this rest was kept there, else found and kept (``rest_kept`` counts a rest read
    back). Returns (the rest state, the table, the unloaded placement the rest was found from)."""
    own = SolverCache(
        method=cache.method, rtol=cache.rtol, precision=cache.precision, exact_body=cache.exact_body
    )
    key = _key(body, cfg, own) if keep else None
    found = _load(key, body, cfg) if key is not None else None
    if found is not None:
        cache.stats["settle_systems"] = 0
        cache.stats["rest_kept"] = cache.stats.get("rest_kept", 0) + 1
        return found
    rest, table, placed = settle_on_table(body, cfg, own)
    for name, count in own.stats.items():
        cache.stats[name] = cache.stats.get(name, 0) + count
    cache.stats["settle_systems"] = own.stats["systems"]
    if key is not None:
        _store(key, rest, placed)
    return rest, table, placed


def _platform() -> tuple[str, ...]:
    """The versions of the libraries a rest depends on, and the processor's name and features."""
    from importlib.metadata import PackageNotFoundError, version

    import llvmlite.binding as llvm
    import numba
    import scipy

    try:
        mkl = version("mkl")
    except PackageNotFoundError:
        mkl = "none"
    cpu = (llvm.get_host_cpu_name(), llvm.get_host_cpu_features().flatten())
    return (np.__version__, scipy.__version__, numba.__version__, mkl, *cpu)


def _key(body: Body, cfg: PlanConfig, cache: SolverCache) -> str | None:
    """The entry's name, or None where the body cannot be written down exactly."""
    digest = usercache.value_digest(body)
    if digest is None:
        return None
    n = 3 * body.n_nodes
    solver = (
        cache.method,
        cache.rtol,
        cache.precision,
        cache.exact_body,
        factor_threads(n),
        choose_threads(),
    )
    return usercache.entry_key(
        "rest", digest, float(cfg.table_mu), solver, _platform(), usercache.package_digest(*SETTLE_SOURCES)
    )


def _store(key: str, rest: State, placed: NDArray[np.float64]) -> None:
    (table,) = rest.contacts  # a finished solve's: no limits or stick stiffnesses left
    usercache.store(
        KIND,
        key,
        {
            "x": rest.x,
            "v": rest.v,
            "t": float(rest.t),
            "active": table.active,
            "anchor": table.anchor,
            "placed": placed,
        },
    )


def _load(key: str, body: Body, cfg: PlanConfig) -> tuple[State, PlaneContact, NDArray[np.float64]] | None:
    """The kept rest, or None when there is none (or a damaged one)."""
    kept = usercache.load(KIND, key)
    names = {"x", "v", "t", "active", "anchor", "placed"}
    if kept is None or not names <= kept.keys():
        return None
    shape = (body.n_nodes, 3)
    arrays = (kept["x"], kept["v"], kept["anchor"], kept["placed"])
    if any(a.shape != shape or a.dtype != np.float64 or not np.isfinite(a).all() for a in arrays):
        return None
    if kept["active"].shape != (body.n_nodes,) or kept["active"].dtype != np.bool_:
        return None
    placed = kept["placed"]
    state = State(kept["x"], kept["v"], float(kept["t"]), (PlaneState(kept["active"], kept["anchor"]),))
    return state, table_under(placed, cfg.table_mu), placed
