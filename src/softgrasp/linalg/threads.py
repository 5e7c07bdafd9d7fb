"""How many threads softgrasp's parallel numerical work runs on: one setting, a fixed rule.

PARDISO's factorisations and solves, the multigrid path's compiled products and sweeps and the
fused explicit stepper take their thread count from here. ``SOFTGRASP_THREADS`` (a positive
number; read at import) or :func:`set_threads` fixes it; otherwise (``auto``, the default) it is
the number of cores this process may run on. The count never depends on how busy the machine is,
so a plan takes the same solver path, and reaches the same numbers, whatever else runs.
"""

from __future__ import annotations

import os

__all__ = ["choose_threads", "cores", "fixed_threads", "set_threads"]

#: The environment variable that fixes the thread count (a positive number, or ``auto``).
THREADS_ENV = "SOFTGRASP_THREADS"


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
