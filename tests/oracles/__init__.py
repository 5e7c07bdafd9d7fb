"""NumPy reference implementations of softgrasp's physical laws, used only by the tests.

Each module here is an independent, vectorised NumPy twin of compiled kernels in ``src/``
(:mod:`oracles.forces` of the body's forces, :mod:`oracles.contact` of the fingertip contact): the
tests compare the kernels with them to round-off. Nothing in ``src/`` imports them.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest


@contextmanager
def without_parallel_kernels() -> Iterator[None]:
    """Run the block as in a forked child whose Numba threads were lost
    (:func:`softgrasp.backend.compiled` false): the solver and hand-placement code then takes its
    SciPy, pyamg and NumPy routines."""
    from softgrasp import backend

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(backend, "compiled", lambda: False)
        yield
