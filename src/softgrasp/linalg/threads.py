"""How many threads softgrasp's parallel numerical work runs on: one setting, a fixed rule.

PARDISO's factorisations and solves, the multigrid path's compiled products and sweeps and the
fused explicit stepper take their thread count from here. ``SOFTGRASP_THREADS`` (a positive
number; read at import) or :func:`set_threads` fixes it; otherwise (``auto``, the default) it is
the number of cores this process may run on, and one for a factorisation too small to share
(:func:`factor_threads`). The count never depends on how busy the machine is, so a plan takes
the same solver path, and reaches the same numbers, whatever else runs.
"""

from __future__ import annotations

import os

__all__ = [
    "PARALLEL_MIN_UNKNOWNS",
    "choose_threads",
    "cores",
    "factor_threads",
    "fixed_threads",
    "set_threads",
]

#: The environment variable that fixes the thread count (a positive number, or ``auto``).
THREADS_ENV = "SOFTGRASP_THREADS"
#: Sparse factorisations of fewer unknowns run on one thread unless a count is fixed
#: (:func:`factor_threads`).
PARALLEL_MIN_UNKNOWNS = 2000


def _configured() -> int | None:
    """The count ``SOFTGRASP_THREADS`` fixes, or None for ``auto`` (also when it is not a
    number)."""
    value = os.environ.get(THREADS_ENV, "auto").strip().lower()
    if value in ("", "auto"):
        return None
    try:
        return max(1, int(value))
    except ValueError:
        return None


_fixed: int | None = _configured()


def cores() -> int:
    """The cores this process may run on (its CPU affinity)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def set_threads(n: int | None) -> None:
    """Fix the thread count of the work started from now on (>= 1); None: back to what
    ``SOFTGRASP_THREADS`` says."""
    global _fixed
    _fixed = _configured() if n is None else max(1, int(n))


def fixed_threads() -> int | None:
    """The fixed thread count, or None for ``auto``."""
    return _fixed


def choose_threads() -> int:
    """The thread count to use: the fixed one, else (``auto``) :func:`cores`."""
    return _fixed if _fixed is not None else cores()


def factor_threads(n: int) -> int:
    """The thread count of a sparse factorisation of ``n`` unknowns (PARDISO's): the fixed count
    if there is one; otherwise one below :data:`PARALLEL_MIN_UNKNOWNS`, else :func:`cores`. A
    factorisation that small takes about a millisecond: a second thread saves a fraction of it
    where the other core is idle, and makes it several times longer where that core is busy
    (1 164 unknowns, the default sphere's: 0.8 ms on two threads and 1.2 ms on one with the other
    core idle; 7.3 and 1.3 ms with it busy, as it is while ``softgrasp plan``'s figure process
    starts). The count depends on the size only (the set-points of eight plans of 388 to 775
    nodes, spheres and the cube, come out bit-identical on one thread and on two)."""
    if _fixed is not None:
        return _fixed
    return 1 if n < PARALLEL_MIN_UNKNOWNS else cores()
