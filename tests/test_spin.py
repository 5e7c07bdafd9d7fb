"""The flags two threads of the fused stepper meet on (:mod:`softgrasp.sim.fused.spin`): a value
stored with release ordering carries the writes before it to the thread that loads it with
acquire ordering; a wait ends when the other thread gets there, or when stop is set; the
intrinsics refuse the wrong types."""

from __future__ import annotations

import threading

import numpy as np
import pytest

numba = pytest.importorskip("numba")
from softgrasp.sim.fused import step  # noqa: E402 - needs numba
from softgrasp.sim.fused.spin import STRIDE, load_acquire, relax, store_release  # noqa: E402


@numba.njit(nogil=True)
def _produce(flags, data, n):  # pragma: no cover - compiled
    """Round r: write data[:] = r, then publish r; wait for the consumer to have read it."""
    for r in range(1, n + 1):
        for i in range(data.shape[0]):
            data[i] = r
        store_release(flags, 0, r)
        polls = 0
        while load_acquire(flags, STRIDE) < r:
            relax(polls)
            polls += 1


@numba.njit(nogil=True)
def _consume(flags, data, n, seen):  # pragma: no cover - compiled
    """Wait for round r, count the entries of data that are not r yet, acknowledge."""
    bad = 0
    for r in range(1, n + 1):
        polls = 0
        while load_acquire(flags, 0) < r:
            relax(polls)
            polls += 1
        for i in range(data.shape[0]):
            if data[i] != r:
                bad += 1
        seen[0] = r
        store_release(flags, STRIDE, r)
    return bad


def test_release_and_acquire_pass_the_data_between_threads():
    """On x86 the hardware keeps stores in order by itself: there this catches a compiler that
    hoists the polled load out of its loop (a hang, seen as the timeout) or moves the data's
    stores past the release (stale data); on weaker hardware the ordering itself too."""
    flags = np.zeros(2 * STRIDE, np.int64)
    data = np.zeros(64, np.int64)
    seen = np.zeros(1, np.int64)
    n = 20000
    _produce(flags, data, 0)  # compiled before the threads start
    _consume(flags, data, 0, seen)
    out = []
    # both sides on daemon threads: a broken side fails the test instead of hanging the run
    reader = threading.Thread(target=lambda: out.append(_consume(flags, data, n, seen)), daemon=True)
    writer = threading.Thread(target=_produce, args=(flags, data, n), daemon=True)
    reader.start()
    writer.start()
    writer.join(timeout=60)
    reader.join(timeout=1)
    assert not writer.is_alive() and not reader.is_alive()
    assert out == [0] and seen[0] == n
    assert flags[0] == n and flags[STRIDE] == n


def test_wait_returns_when_the_value_arrives_or_stop_is_set():
    flags = np.zeros(step._S_SIZE, np.int64)
    flags[step._S_NODES1] = 3
    assert step._wait(flags, step._S_NODES1, 3)
    flags[step._S_STOP] = 1
    assert step._wait(flags, step._S_NODES1, 2)  # the value is there: stop does not matter
    assert not step._wait(flags, step._S_NODES1, 4)  # it never comes: stop ends the wait


@numba.njit(nogil=True)
def _wait_without_the_gil(flags, slot, value):  # pragma: no cover - compiled
    return step._wait(flags, slot, value)


def test_a_long_wait_yields_the_core_and_still_ends():
    """Past SPINS polls the waiting thread yields at every poll; it still sees the value."""
    flags = np.zeros(step._S_SIZE, np.int64)
    done = []
    _wait_without_the_gil(np.ones(step._S_SIZE, np.int64), 0, 1)  # compiled before the thread starts
    waiter = threading.Thread(
        target=lambda: done.append(_wait_without_the_gil(flags, step._S_BODY1, 1)), daemon=True
    )
    waiter.start()
    threading.Event().wait(0.05)  # long past SPINS polls of about 25 ns
    assert waiter.is_alive()
    flags[step._S_BODY1] = 1
    waiter.join(timeout=10)
    assert done == [True]


@pytest.mark.parametrize("dtype", [np.float64, np.int32])
def test_the_flags_must_be_int64(dtype):
    @numba.njit
    def load(a):  # pragma: no cover - compiled
        return load_acquire(a, 0)

    with pytest.raises(numba.core.errors.TypingError):
        load(np.zeros(8, dtype))
