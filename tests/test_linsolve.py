"""The Newton systems' linear solvers: PARDISO with reused analysis, GMRES on the exact
(non-symmetric) Newton matrix, and their agreement with SciPy's sparse LU and with each other on a
static solve with friction."""

from __future__ import annotations

import gc
import math
import os

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from softgrasp.linalg import factored, krylov, pardiso, threads
from softgrasp.linalg import solve as linsolve
from softgrasp.linalg.multigrid import cycle, hierarchy
from softgrasp.linalg.multigrid import krylov as mg_krylov
from softgrasp.linalg.solve import SolverCache, solve_newton_system
from softgrasp.model.material import preset
from softgrasp.model.mesh.generate import box
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.scene import Scene
from softgrasp.sim.static import solve_static

needs_mkl = pytest.mark.skipif(
    not pardiso.available(), reason="MKL PARDISO is not installed (pip install mkl)"
)


def _stiffness(n: int = 4, shift: float = 1e-3) -> sp.csr_matrix:
    """The foam cube's rest stiffness with a small diagonal shift (a free body is singular)."""
    body = build_body(box(0.05, n), preset("foam"), mass=0.0125)
    K = -body.rest_jacobian
    return (K + shift * sp.diags(K.diagonal())).tocsr()


@needs_mkl
def test_factors_with_different_thread_counts_interleave():
    """Each factor keeps the thread count of its analysis (PARDISO crashes if it changes between
    phases): a one-thread and a two-thread factor used alternately both solve exactly; the
    automatic choice is the cores this process may use."""
    K = _stiffness()
    b = np.random.default_rng(2).standard_normal(K.shape[0])
    want = spla.spsolve(K.tocsc(), b)
    try:
        pardiso.set_threads(1)
        one = pardiso.PardisoFactor(K)
        pardiso.set_threads(2)
        two = pardiso.PardisoFactor(K)
        for _ in range(3):
            two.refactor(two.same_pattern(1.5 * K))
            one.refactor(one.same_pattern(1.5 * K))
            for f in (one, two):
                np.testing.assert_allclose(f.solve(1.5 * b), want, rtol=1e-9, atol=0)
    finally:
        pardiso.set_threads(None)
    assert pardiso.choose_threads() == (pardiso.fixed_threads() or len(os.sched_getaffinity(0)))


def test_small_systems_are_factorised_on_one_thread_unless_a_count_is_fixed():
    """Below ``threads.PARALLEL_MIN_UNKNOWNS`` a factor runs on one thread (the automatic count), at and
    above it on the cores this process may use; a fixed count holds for every size."""
    small, large = threads.PARALLEL_MIN_UNKNOWNS - 1, threads.PARALLEL_MIN_UNKNOWNS
    try:
        pardiso.set_threads(None)
        if pardiso.fixed_threads() is None:
            assert pardiso.factor_threads(small) == 1
            assert pardiso.factor_threads(large) == len(os.sched_getaffinity(0))
        pardiso.set_threads(3)
        assert pardiso.factor_threads(small) == pardiso.factor_threads(large) == 3
    finally:
        pardiso.set_threads(None)


@needs_mkl
def test_a_small_factor_on_one_thread_solves_as_on_two():
    """The foam cube's stiffness at 1 473 unknowns (below the limit): its automatic factor runs
    on one thread and its solves agree with a two-thread factor's and SciPy's sparse LU to 1e-12."""
    K = _stiffness(5)
    assert K.shape[0] < threads.PARALLEL_MIN_UNKNOWNS
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    want = spla.spsolve(K.tocsc(), b)
    try:
        pardiso.set_threads(None)
        auto = pardiso.PardisoFactor(K)
        pardiso.set_threads(2)
        two = pardiso.PardisoFactor(K)
    finally:
        pardiso.set_threads(None)
    if pardiso.fixed_threads() is None:
        assert auto._threads == 1 and two._threads == 2
    np.testing.assert_allclose(auto.solve(b), two.solve(b), rtol=1e-12, atol=0)
    np.testing.assert_allclose(auto.solve(b), want, rtol=1e-9, atol=0)


@needs_mkl
def test_factor_uses_cholesky_while_positive_definite_and_ldlt_otherwise():
    """A positive definite matrix is factorised by Cholesky; one with negative eigenvalues falls
    back to LDL^T (which counts them: as many as the dense eigenvalues say) and the next
    ``SPD_RETRY`` factorisations stay there before Cholesky is tried again. Every solve matches
    SciPy's sparse LU to 1e-9. A singular stiffness (a free body) is refused by Cholesky too,
    though PARDISO's Cholesky raises nothing on it: its pivots fall to ~1e-14 of the diagonal."""
    K = _stiffness(shift=0.0)
    b = np.random.default_rng(6).standard_normal(K.shape[0])
    spd = (K + 1e-3 * sp.diags(K.diagonal())).tocsr()
    ind = (K - 1e-2 * sp.diags(K.diagonal())).tocsr()
    negative = int((np.linalg.eigvalsh(ind.toarray()) < 0).sum())
    assert negative > 0
    f = pardiso.PardisoFactor(spd)
    seen = []
    for M in [spd, ind] + [spd] * (pardiso.SPD_RETRY + 1):
        f.refactor(f.same_pattern(M))
        np.testing.assert_allclose(f.solve(b), spla.spsolve(M.tocsc(), b), rtol=1e-9, atol=0)
        seen.append((f.positive_definite, f.negative_pivots))
    assert seen == [(True, 0), (False, negative)] + [(False, 0)] * pardiso.SPD_RETRY + [(True, 0)]
    f.refactor(f.same_pattern(K.tocsr()))  # rigid motions free: singular
    assert not f.positive_definite


@needs_mkl
def test_collected_factor_leaves_the_thread_count_alone():
    """A factor freed by the cycle collector (which runs wherever an allocation starts it: inside
    another factor's call, after that call set its thread count) makes no MKL call then: MKL's
    thread count stays the live factor's (a call with another count than its analysis crashes
    MKL), and the release is made by the next call, which still solves exactly."""
    K = _stiffness()
    b = np.random.default_rng(4).standard_normal(K.shape[0])
    want = spla.spsolve(K.tocsc(), b)
    from softgrasp.linalg import mkl

    gc.collect()  # cycles left by earlier tests queue now; the next call releases them
    gc.disable()
    try:
        pardiso.set_threads(1)
        one = pardiso.PardisoFactor(K)
        assert not mkl._RELEASED
        one.cycle = one  # only the cycle collector frees it
        pardiso.set_threads(2)
        two = pardiso.PardisoFactor(K)
        np.testing.assert_allclose(two.solve(b), want, rtol=1e-9, atol=0)
        assert mkl.max_threads() == 2
        del one
        gc.collect()
        assert mkl.max_threads() == 2
        assert len(mkl._RELEASED) == 1
        np.testing.assert_allclose(two.solve(b), want, rtol=1e-9, atol=0)
        assert not mkl._RELEASED
    finally:
        gc.enable()
        pardiso.set_threads(None)


_COLLECTED_DURING_REFACTORISATION = """
import gc, random, sys
import numpy as np, scipy.sparse as sp
from softgrasp.physics.body import build_body
from softgrasp.model.material import preset
from softgrasp.model.mesh.generate import box
from softgrasp.linalg import pardiso
K = -build_body(box(0.05, 8), preset("foam"), mass=0.0125).rest_jacobian
K = (K + 1e-3 * sp.diags(K.diagonal())).tocsr()
b = np.ones(K.shape[0])
pardiso.set_threads(2)
two = pardiso.PardisoFactor(K)
want = two.solve(b)
rng = random.Random(1)
for k in range(12):
    gc.disable()
    pardiso.set_threads(1)
    one = pardiso.PardisoFactor(K)
    one.cycle = one
    holder = [one]
    del one
    gc.collect(0)
    gc.collect(0)
    holder.clear()  # unreachable now, in an older generation: the next collection frees it
    gc.set_threshold(rng.randint(1, 12), 0, 0)  # ... somewhere inside the next calls
    gc.enable()
    two.refactor(two.same_pattern(K))
    err = float(np.abs(two.solve(b) - want).max() / np.abs(want).max())
    gc.set_threshold(700, 10, 10)
    assert err < 1e-9, err
print("ok")
"""


@needs_mkl
def test_factor_collected_during_another_factorisation_does_not_crash():
    """The crash itself, in a child process: one-thread factors freed by the cycle collector at
    chance points inside a two-thread factor's refactorisations and solves (a factorisation run
    with another thread count than its analysis was a segmentation fault here). Every solve stays
    exact and the child exits normally."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", _COLLECTED_DURING_REFACTORISATION], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert out.stdout.strip() == "ok"


def test_auto_threads_are_a_fixed_rule_not_the_machine_load(monkeypatch):
    """``auto`` is the cores this process may run on, whatever else runs; a number in
    ``SOFTGRASP_THREADS`` (or :func:`set_threads`) fixes the count; the load is never read."""
    from softgrasp.linalg import threads

    monkeypatch.setattr(threads, "_fixed", None)
    assert threads.choose_threads() == threads.cores() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("SOFTGRASP_THREADS", "3")
    threads.set_threads(None)
    assert threads.choose_threads() == 3 and threads.fixed_threads() == 3
    threads.set_threads(1)
    assert threads.choose_threads() == 1
    monkeypatch.setenv("SOFTGRASP_THREADS", "auto")
    threads.set_threads(None)
    assert threads.fixed_threads() is None
    monkeypatch.undo()
    threads.set_threads(None)


def test_mkl_is_found_where_the_mkl_wheel_installs_it():
    """The library comes from where the ``mkl`` wheel installs it: the distribution's own file
    list names it among the candidates (no path setting), each candidate once."""
    from importlib.metadata import PackageNotFoundError, distribution

    from softgrasp.linalg import mkl

    names = list(mkl._candidates())
    assert len(names) == len(set(names))
    try:
        wheel = [f for f in distribution("mkl").files or [] if f.name.startswith("libmkl_rt.so")]
    except PackageNotFoundError:
        pytest.skip("the mkl wheel is not installed")
    assert wheel and os.path.normpath(wheel[0].locate()) in names
    assert pardiso.available()


@needs_mkl
def test_mkl_runs_on_intel_openmp_even_after_gnu_openmp_was_loaded():
    """gmsh loads GNU OpenMP before MKL; MKL must still take its Intel threading layer (whose
    threads KMP_BLOCKTIME governs), not the GNU one."""
    import gmsh  # noqa: F401 - loads GNU OpenMP first where gmsh links it

    pardiso.PardisoFactor(_stiffness()).solve(np.ones(_stiffness().shape[0]))
    with open("/proc/self/maps", encoding="ascii", errors="replace") as fh:
        maps = fh.read()
    assert "libmkl_intel_thread" in maps
    assert "libmkl_gnu_thread" not in maps


@needs_mkl
def test_pardiso_solves_like_sparse_lu_and_refactorises_new_values():
    K = _stiffness()
    b = np.random.default_rng(1).standard_normal(K.shape[0])
    f = pardiso.PardisoFactor(K)
    x = f.solve(b)
    ref = spla.spsolve(K.tocsc(), b)
    assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max()
    assert f.negative_pivots == 0 and f.perturbed_pivots == 0
    # New values, same pattern: numerical refactorisation only.
    K2 = (1.3 * K + sp.diags(K.diagonal() * np.random.default_rng(2).random(K.shape[0]))).tocsr()
    U = f.same_pattern(K2)
    assert U is not None
    f.refactor(U)
    assert np.abs(K2 @ f.solve(b) - b).max() <= 1e-9 * np.abs(b).max()


@needs_mkl
def test_a_single_precision_factor_solves_to_single_precision_and_the_newton_solve_refines_it():
    """``single=True`` factorises a well-conditioned stiffness in single precision: a solve's
    relative residual is float32's (~1e-6-1e-3 here, against ~1e-13 for the double factor), and
    the Newton solve (mixed precision) refines it against the double matrix to sparse LU's
    solution."""
    K = _stiffness(6)
    b = np.random.default_rng(21).standard_normal(K.shape[0])
    ref = spla.spsolve(K.tocsc(), b)
    single, double = pardiso.PardisoFactor(K, single=True), pardiso.PardisoFactor(K)
    assert single.single_precision and single.positive_definite and not double.single_precision
    assert single.single_factorisations == 1 and double.single_factorisations == 0
    rel = {f: np.linalg.norm(K @ f.solve(b) - b) / np.linalg.norm(b) for f in (single, double)}
    assert 1e-9 < rel[single] < 1e-2 and rel[double] < 1e-11
    cache = SolverCache(method="pardiso", precision="mixed")
    x, _ = solve_newton_system(K, b, None, np.zeros((K.shape[0] // 3, 3)), cache)
    assert cache._factor.single_precision
    assert np.linalg.norm(K @ x - b) <= krylov.STALE_RTOL * np.linalg.norm(b)
    assert np.abs(x - ref).max() <= 1e-6 * np.abs(ref).max()


@needs_mkl
@pytest.mark.parametrize("shift", [1e-7, 0.0])
def test_a_matrix_too_ill_conditioned_for_single_precision_gets_the_double_factor_and_verdict(shift):
    """A stiffness whose rigid motions are held only by a diagonal of 1e-7 of its own (Cholesky
    pivots ~1e-7 of their diagonal: below ``SINGLE_PIVOT_FLOOR``, where float32 cannot resolve
    them) is factorised in double precision and solves as the double factor does; a free body's
    singular stiffness (no shift) gets the same verdict with and without single precision."""
    K = _stiffness(4, shift=shift)
    b = np.random.default_rng(22).standard_normal(K.shape[0])
    single, double = pardiso.PardisoFactor(K, single=True), pardiso.PardisoFactor(K)
    assert not single.single_precision and single.single_factorisations == 0
    assert single.positive_definite == double.positive_definite == (shift > 0)
    assert single.perturbed_pivots == double.perturbed_pivots
    if shift > 0:
        assert np.array_equal(single.solve(b), double.solve(b))


@needs_mkl
def test_pardiso_factorises_indefinite_matrices_and_counts_negative_pivots():
    K = _stiffness()
    n = K.shape[0]
    M = (K - 2.0 * float(np.median(K.diagonal())) * sp.eye(n)).tocsr()  # shifted into indefiniteness
    b = np.random.default_rng(3).standard_normal(n)
    f = pardiso.PardisoFactor(M)
    assert f.negative_pivots > 0
    assert np.abs(M @ f.solve(b) - b).max() <= 1e-8 * np.abs(b).max() * np.abs(M).max()


def test_multigrid_cg_shifts_an_indefinite_stiffness_into_a_descent_step():
    """The foam cube's stiffness with one strongly negative direction (a body about to tip): CG
    meets negative curvature, so the multigrid path solves the diagonally shifted system instead
    (Levenberg-Marquardt) to its tolerance; the step is a descent direction (b . x > 0) and, along
    the stiff directions, close to the unshifted solution."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    K = _stiffness()
    lam, vecs = np.linalg.eigh(K.toarray())
    v = vecs[:, 0]  # the softest mode, turned unstable
    A = (K - sp.csr_matrix(np.outer((lam[0] + lam[6]) * v, v))).tocsr()
    assert float(v @ (A @ v)) < 0  # indefinite
    b = v + 0.1 * (K @ np.random.default_rng(6).standard_normal(K.shape[0])) / lam[-1]
    cache = SolverCache(method="amg")
    x, _ = solve_newton_system(A, b, None, np.asarray(body.mesh.points), cache)
    assert cache.stats.get("shifted", 0) == 1
    assert float(b @ x) > 0
    # it solves (A + tau D) x = b for one of the shifts tried, D = |diag A|
    D = np.abs(A.diagonal())
    taus = [1e-6 * 10.0**k for k in range(7)]
    res = [np.linalg.norm(A @ x + tau * D * x - b) / np.linalg.norm(b) for tau in taus]
    assert min(res) < 1e-8, res


def test_conjugate_gradients_breaking_down_raise_not_converged():
    """A preconditioner that gives ``r^T M r = 0`` for a residual that is not zero makes conjugate
    gradients divide by zero (the hand-written iteration raised ZeroDivisionError): SciPy's
    iteration, watched, raises NotConverged instead."""
    from softgrasp.errors import NotConverged

    A = sp.identity(2, format="csr")
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])  # M r is orthogonal to r
    with pytest.raises(NotConverged, match="broke down"):
        krylov.cg(A, np.array([1.0, 0.0]), turn, 1e-10, 50)
    x, it, curved = krylov.cg(A, np.array([1.0, 2.0]), sp.identity(2), 1e-12, 50)
    assert not curved and it == 1 and np.allclose(x, [1.0, 2.0])


@pytest.mark.parametrize("always", [False, True])
def test_a_multigrid_breakdown_rebuilds_the_hierarchy_then_raises_not_converged(monkeypatch, always):
    """A V-cycle that returns nothing (``r^T M r = 0``): the multigrid path builds the hierarchy
    anew on the same matrix and solves with it; where the new one breaks down too, the solve
    raises NotConverged (a softgrasp error the Newton iteration handles), never ZeroDivisionError."""
    from softgrasp.errors import NotConverged

    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    K = _stiffness()
    b = np.random.default_rng(8).standard_normal(K.shape[0])
    real = cycle.Multigrid.matvec
    built: list[object] = []

    def broken(self, r):
        if not built or built[0] is self or always:
            built.append(self) if not built else None
            return np.zeros_like(r)
        return real(self, r)

    monkeypatch.setattr(cycle.Multigrid, "matvec", broken)
    monkeypatch.setattr(cycle.Multigrid, "__matmul__", broken)
    cache = SolverCache(method="amg")
    if always:
        with pytest.raises(NotConverged, match="broke down"):
            solve_newton_system(K, b, None, np.asarray(body.mesh.points), cache)
        assert cache.stats["multigrid_setups"] == 2
        return
    x, _ = solve_newton_system(K, b, None, np.asarray(body.mesh.points), cache)
    assert cache.stats["multigrid_setups"] == 2
    assert np.linalg.norm(K @ x - b) <= 1e-8 * np.linalg.norm(b)


def _tipping(K: sp.csr_matrix) -> tuple[sp.csr_matrix, NDArray, float]:
    """K (in its own pattern) with its softest modes turned unstable (a body about to tip over on
    its few supports), the softest mode, and the first of the Newton solver's diagonal shifts tau
    (1e-6, 1e-5, ..., relative to |diag|) that makes it positive definite, from its dense
    eigenvalues."""
    lam, vecs = np.linalg.eigh(K.toarray())
    A = (K - 2.0 * lam[0] * sp.eye(K.shape[0])).tocsr()
    dense = A.toarray()
    assert np.linalg.eigvalsh(dense)[0] < 0
    D = np.diag(np.abs(A.diagonal()))
    tau = next(t for t in (1e-6 * 10.0**k for k in range(7)) if np.linalg.eigvalsh(dense + t * D)[0] > 0)
    return A, vecs[:, 0], tau


@needs_mkl
@pytest.mark.parametrize("precision", ["double", "mixed"])
@pytest.mark.parametrize("stale", [True, False])
def test_pardiso_shifts_an_indefinite_held_stiffness_by_cholesky_alone(stale, precision):
    """A held body's stiffness turned indefinite after a positive definite one: the PARDISO path
    solves the diagonally shifted system (A + tau D) x = b for the first shift that is positive
    definite (tau from the dense eigenvalues, x checked against SciPy's LU of that matrix) with
    Cholesky factors only: either the old factor's conjugate gradients prove A indefinite (no
    factorisation of A at all) or A's Cholesky fails (the scene changed: no old factor tried);
    no LDL^T is computed to count negative pivots. The step is a descent direction. With mixed
    precision the same shift is found (a failed single-precision Cholesky is tried again in
    double: two factorisations per failure) and the step refined to the same accuracy."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    K = _stiffness()
    A, v, tau = _tipping(K)
    x_nodes = np.asarray(body.mesh.points)
    b = v + 0.1 * (K @ np.random.default_rng(6).standard_normal(K.shape[0])) / np.abs(K).max()
    cache = SolverCache(method="pardiso", precision=precision)
    solve_newton_system(K, b, None, x_nodes, cache)
    f = cache._factor
    assert f.positive_definite and cache.stats["factorisations"] == 1
    assert f.single_precision == (precision == "mixed")
    if not stale:
        cache.scene_changed()
    x, _ = solve_newton_system(A, b, None, x_nodes, cache)
    want = spla.spsolve((A + tau * sp.diags(np.abs(A.diagonal()))).tocsc(), b)
    assert np.abs(x - want).max() <= 1e-8 * np.abs(want).max()
    assert float(b @ x) > 0
    assert cache.stats["indefinite_factor"] == 1 and cache.stats["shifted"] == 1
    assert all(mtype != pardiso.SYMMETRIC_INDEFINITE for mtype, _ in f._pts)  # never analysed for LDL^T
    shifts = round(math.log10(tau / krylov.INDEFINITE_SHIFT)) + 1  # factorisations of A + tau D
    per_failure = 2 if precision == "mixed" else 1
    failures = shifts - 1 + (0 if stale else 1)  # the failed shifts, and A's own Cholesky
    assert cache.stats["factorisations"] == 1 + 1 + per_failure * failures
    assert f.single_precision == (precision == "mixed")


@needs_mkl
def test_a_cholesky_stopped_at_a_negative_pivot_leaves_no_factor_to_solve_with():
    """``refactor(..., stop_if_indefinite=True)`` on an indefinite matrix returns False and leaves no
    factor in use (a solve says so instead of using a failed one); ``refactor_positive`` takes a
    positive definite matrix (then solves like SciPy's LU) and refuses an indefinite one."""
    K = _stiffness()
    A, _, tau = _tipping(K)
    b = np.random.default_rng(8).standard_normal(K.shape[0])
    f = pardiso.PardisoFactor(K)
    assert not f.refactor(f.same_pattern(A), stop_if_indefinite=True)
    with pytest.raises(pardiso.PardisoError, match="no factorisation in use"):
        f.solve(b)
    assert not f.refactor_positive(f.same_pattern(A))
    S = (A + tau * sp.diags(np.abs(A.diagonal()))).tocsr()
    assert f.refactor_positive(f.same_pattern(S)) and f.positive_definite
    np.testing.assert_allclose(f.solve(b), spla.spsolve(S.tocsc(), b), rtol=1e-9, atol=0)
    assert f.refactor(f.same_pattern(A))  # without the flag: LDL^T, negative pivots counted
    assert f.negative_pivots == int((np.linalg.eigvalsh(A.toarray()) < 0).sum()) > 0


@needs_mkl
def test_a_free_body_singular_stiffness_is_not_shifted():
    """A free body's stiffness (rigid motions free, singular) after a held one: not shifted as an
    indefinite one would be, but factorised by LDL^T as before, and solved (b chosen in its
    range)."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    x_nodes = np.asarray(body.mesh.points)
    K0 = _stiffness(shift=0.0)
    b = K0 @ np.random.default_rng(9).standard_normal(K0.shape[0])
    cache = SolverCache(method="pardiso")
    solve_newton_system(_stiffness(), b, None, x_nodes, cache)
    cache.scene_changed()
    x, _ = solve_newton_system(K0, b, None, x_nodes, cache)
    assert cache.stats.get("shifted", 0) == 0 and not cache._factor.positive_definite
    assert np.linalg.norm(K0 @ x - b) <= 1e-8 * np.linalg.norm(b)


def test_a_load_along_a_translation_nothing_resists_is_found():
    """A free body's stiffness K (nothing holds it) under its weight: K t = 0 for the vertical
    translation t, so t . (K x - b) = -t . b for every x and K x = b has no solution; the check
    the singular path runs before multigrid names that axis. A load in K's range (K r), or the
    weight on a body that something holds (K shifted), has none."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    x_nodes = np.asarray(body.mesh.points)
    K0 = _stiffness(shift=0.0)
    weight = (body.mass[:, None] * np.array([0.0, 0.0, -9.81])).ravel()
    assert factored._load_along_free_translation(K0, weight, x_nodes) == "z"
    sideways = np.roll(weight.reshape(-1, 3), -2, axis=1).ravel()  # the weight turned along x
    assert factored._load_along_free_translation(K0, sideways, x_nodes) == "x"
    in_range = K0 @ np.random.default_rng(9).standard_normal(K0.shape[0])
    assert factored._load_along_free_translation(K0, in_range, x_nodes) == ""
    assert factored._load_along_free_translation(_stiffness(), weight, x_nodes) == ""


@needs_mkl
@pytest.mark.parametrize("precision", ["double", "mixed"])
@pytest.mark.parametrize("case", ["tau beyond 1", "a node nothing holds"])
def test_every_numerical_factorisation_is_counted_and_none_is_repeated(monkeypatch, case, precision):
    """The factorisations the PARDISO path makes (PARDISO's numerical phase, spied on) are the
    ones it counts, and no values are factorised twice in a row by the same method: a held
    stiffness shifted by 3 |diag| into indefiniteness (no shift up to tau = 1 is positive
    definite: Cholesky for each, then LDL^T of the last, not Cholesky again), and one with a node
    that nothing holds (a zero row: singular, not indefinite, so not shifted but factorised by
    LDL^T after Cholesky's failure, solved by multigrid where its pivots were perturbed). With
    mixed precision every Cholesky is tried in single precision first and, failing, in double
    (whose verdict counts); LDL^T is always double."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    x_nodes = np.asarray(body.mesh.points)
    K = _stiffness()
    n = K.shape[0]
    rng = np.random.default_rng(11)
    if case == "tau beyond 1":
        A = (K - 3.0 * sp.diags(K.diagonal())).tocsr()
        b = rng.standard_normal(n)
    else:
        keep = sp.diags(np.r_[np.zeros(3), np.ones(n - 3)])
        A = (keep @ K @ keep).tocsr()
        b = keep @ rng.standard_normal(n)
    made: list[tuple[tuple[int, bool], bytes]] = []
    real = pardiso.PardisoFactor._call

    def spy(self, phase, b=None, key=None, perm=None):
        if phase == 22:
            made.append((self._key if key is None else key, self._data.tobytes()))
        return real(self, phase, b=b, key=key, perm=perm)

    monkeypatch.setattr(pardiso.PardisoFactor, "_call", spy)
    cache = SolverCache(method="pardiso", precision=precision)
    solve_newton_system(K, b, None, x_nodes, cache)
    cache.scene_changed()
    before, first = cache.stats["factorisations"], len(made)
    x, _ = solve_newton_system(A, b, None, x_nodes, cache)
    assert cache.stats["factorisations"] - before == len(made) - first
    assert all(made[i] != made[i + 1] for i in range(first, len(made) - 1))  # (method, values)
    cholesky = [(2, True), (2, False)] if precision == "mixed" else [(2, False)]
    if case == "tau beyond 1":
        assert [k for k, _ in made[first:]] == cholesky * 8 + [(-2, False)] and cache.stats["shifted"] == 1
    else:
        assert cache.stats.get("shifted", 0) == 0 and cache.stats.get("indefinite_factor", 0) == 0
        assert [k for k, _ in made[first:]] == cholesky + [(-2, False)]
        assert np.linalg.norm(A @ x - b) <= 1e-8 * np.linalg.norm(b)


def test_gmres_on_a_singular_operator_returns_a_least_squares_step_not_a_blown_up_one():
    """GMRES that breaks down on a singular operator with b partly outside its range (a diagonal
    with three zeros) returns a least-squares step: its residual is NumPy's lstsq residual for the
    whole operator, and the step stays of the size of lstsq's minimum-norm solution (its Krylov
    space holds b, so some of b's null-space part stays in it), not blown up along the null space
    by dividing by a zero pivot (it was 5e15 times larger)."""
    n = 60
    A = np.diag(np.r_[np.zeros(3), np.linspace(1.0, 2.0, n - 3)])
    b = np.random.default_rng(1).standard_normal(n)
    x = krylov.gmres(lambda v: A @ v, b, lambda v: v, 80, 1e-8)
    want = np.linalg.lstsq(A, b, rcond=None)[0]
    assert x is not None
    assert np.linalg.norm(A @ x - b) == pytest.approx(np.linalg.norm(A @ want - b), rel=1e-8)
    assert np.abs(x).max() <= 2.0 * np.abs(want).max()


@needs_mkl
def test_a_pattern_analysed_before_takes_its_kept_ordering_and_factorises_to_the_same_bits(monkeypatch):
    """A second factor of a pattern seen before takes the nested-dissection ordering kept from the
    first analysis (METIS does not run again) and solves to the same bits, in both matrix types;
    another pattern gets an ordering of its own, and only the latest ``ORDERINGS_KEPT`` are kept.
    On one thread: on two, MKL's parallel factorisation differs in its last bits from run to run
    whatever the ordering's origin."""
    monkeypatch.setattr(pardiso, "_ORDERINGS", {})
    pardiso.set_threads(1)
    try:
        _kept_ordering_cases(monkeypatch)
    finally:
        pardiso.set_threads(None)


def _kept_ordering_cases(monkeypatch) -> None:
    K = _stiffness(6)  # 2 325 unknowns: supernodes large enough for the ordering to matter
    b = np.random.default_rng(8).standard_normal(K.shape[0])
    ind = (K - 2.0 * float(np.median(K.diagonal())) * sp.eye(K.shape[0])).tocsr()
    first = pardiso.PardisoFactor(K)
    x1 = first.solve(b)
    first.refactor(first.same_pattern(ind))  # the indefinite type's analysis takes the ordering
    y1 = first.solve(b)
    assert len(pardiso._ORDERINGS) == 1
    kept = next(iter(pardiso._ORDERINGS.values()))
    assert sorted(kept.tolist()) == list(range(K.shape[0]))  # a permutation
    second = pardiso.PardisoFactor(K)
    assert second._perm is kept and second._iparms[(pardiso.SYMMETRIC_POSITIVE_DEFINITE, False)][4] == 1
    assert np.array_equal(second.solve(b), x1)
    second.refactor(second.same_pattern(ind))
    assert np.array_equal(second.solve(b), y1) and second.negative_pivots == first.negative_pivots
    D = sp.diags(K.diagonal()).tocsr()  # another pattern
    other = pardiso.PardisoFactor(D)
    assert len(pardiso._ORDERINGS) == 2 and other._perm is not kept
    assert np.allclose(other.solve(b), b / K.diagonal(), rtol=1e-12)
    monkeypatch.setattr(pardiso, "ORDERINGS_KEPT", 1)
    pardiso.PardisoFactor(K)
    # only the latest is kept
    assert len(pardiso._ORDERINGS) == 1 and next(iter(pardiso._ORDERINGS.values())) is kept


@needs_mkl
def test_pattern_subsets_reuse_the_analysis_and_unions_take_both():
    K = _stiffness()
    n = K.shape[0]
    f = pardiso.PardisoFactor(K)
    # A matrix with fewer entries fits the pattern (missing ones stored as zeros).
    D = sp.diags(K.diagonal()).tocsr()
    U = f.same_pattern(D)
    assert U is not None and U.nnz == f.matrix().nnz
    f.refactor(U)
    b = np.arange(1.0, n + 1.0)
    assert np.allclose(f.solve(b), b / K.diagonal(), rtol=1e-12)
    # An entry outside the pattern does not fit; the union pattern takes both.
    E = K.tolil()
    E[0, n - 1] = E[n - 1, 0] = 1e-3 * K[0, 0]
    E = E.tocsr()
    assert K[0, n - 1] == 0 and f.same_pattern(E) is None
    g = pardiso.PardisoFactor(pardiso.PardisoFactor.union(E, f.matrix()))
    for M in (E, K):
        U = g.same_pattern(M)
        assert U is not None
        # The second time a pattern comes, its values are gathered by the positions kept from
        # the first (every entry of the factor's pattern for E, a subset for K): the same matrix.
        again = g.same_pattern(M.copy())
        assert again is not None and np.array_equal(again.indptr, U.indptr)
        assert np.array_equal(again.indices, U.indices) and np.array_equal(again.data, U.data)
        g.refactor(U)
        assert np.abs(M @ g.solve(b) - b).max() <= 1e-9 * np.abs(b).max()


@needs_mkl
def test_a_pattern_seen_before_is_gathered_to_the_same_upper_triangle():
    """Matrices of the pattern a factor last took (the Newton matrices of one solve) are mapped
    into its upper triangle by a kept gather: the same values in the same places as the
    extraction from scratch, for the factor's own pattern, a subset of it, after a change of
    pattern and back; and a non-canonical matrix (duplicates) still goes the long way, summed."""
    K = _stiffness()
    f = pardiso.PardisoFactor(pardiso.PardisoFactor.union(K, sp.eye(K.shape[0], k=5, format="csr")))
    D = sp.diags(K.diagonal()).tocsr()
    rng = np.random.default_rng(3)
    for M in (K, 1.7 * K, D, 2.0 * D, K + sp.diags(rng.random(K.shape[0])), K):
        M = M.tocsr()
        got = f.same_pattern(M)
        want = f._same_pattern(M)
        assert got is not None and want is not None
        assert np.array_equal(got.indptr, want.indptr) and np.array_equal(got.indices, want.indices)
        assert np.array_equal(got.data, want.data)
    C = sp.coo_matrix(K)
    dup = sp.csr_matrix(
        (np.concatenate([C.data, C.data]), (np.concatenate([C.row, C.row]), np.concatenate([C.col, C.col]))),
        shape=K.shape,
    )
    dup.has_canonical_format = False  # as built from triplets before summing
    got = f.same_pattern(dup)
    assert got is not None
    assert np.allclose(got.data, f.same_pattern((2.0 * K).tocsr()).data, rtol=1e-15, atol=0)


@needs_mkl
def test_gmres_on_the_exact_product_solves_the_non_symmetric_system():
    """With ``matvec`` the solver answers the non-symmetric system it is the product of,
    preconditioned by the factorisation of the symmetric approximation it is given."""
    K = _stiffness()
    n = K.shape[0]
    rng = np.random.default_rng(4)
    u, w = rng.standard_normal((2, n, 3))
    N = K + 0.05 * float(K.diagonal().mean()) * sp.csr_matrix(u @ w.T / n)  # rank-3, not symmetric
    b = rng.standard_normal(n)
    cache = SolverCache(method="pardiso")
    x, _ = solve_newton_system(K, b, None, np.zeros((n // 3, 3)), cache, matvec=lambda v: N @ v)
    assert np.abs(N @ x - b).max() <= 1e-7 * np.abs(b).max()
    # Without it, the symmetric system.
    x2, _ = solve_newton_system(K, b, None, np.zeros((n // 3, 3)), cache)
    assert np.abs(K @ x2 - b).max() <= 1e-7 * np.abs(b).max()
    assert np.abs(N @ x2 - b).max() > 1e-4 * np.abs(b).max()


def _pressed(method: str, precision: str = "mixed", stats: dict | None = None):
    """The foam cube on a rough table, a rough fingertip pressed 1 mm and dragged 0.3 mm sideways
    in static increments, with the given linear solver (and factor precision; the solver's
    counts copied into ``stats``)."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=1.0, name="table")
    params = ContactParams(mu=0.8)
    cache = SolverCache(method=method, precision=precision)
    fc = FingertipContact(
        (Fingertip(0.008, centre=[0.003, 0.002, 0.058], velocity=[0.3, 0.0, -1.0]),), params
    )
    scene = Scene(body, (table, fc))
    state = scene.initial_state()
    iterations = 0
    for t in (0.5e-3, 1e-3):
        state, info = solve_static(scene, state, t=t, cache=cache)
        iterations += info.newton_iterations
    rep = fc.report(body, state.x, None, state.t, state.contacts[1], static=True)
    if stats is not None:
        stats.update(cache.stats, single=cache._factor.single_factorisations if cache._factor else 0)
    return state.x, rep.force[0], iterations


@needs_mkl
def test_fast_and_reference_solvers_reach_the_same_rest_with_friction():
    """PARDISO with the exact Newton product (the fast path) and SciPy's LU of the symmetrised
    Newton matrix (the reference) bring the same frictional contact to the same equilibrium; the
    exact product converges in fewer Newton iterations."""
    x_fast, f_fast, it_fast = _pressed("pardiso")
    x_ref, f_ref, it_ref = _pressed("direct")
    assert np.abs(f_fast - f_ref).max() <= 1e-8 * np.linalg.norm(f_ref)
    assert np.abs(x_fast - x_ref).max() <= 1e-9
    assert it_fast < it_ref


@needs_mkl
def test_mixed_and_double_precision_factors_reach_the_same_rest_with_friction():
    """The pressed and dragged fingertip on the foam cube with single-precision factors refined in
    double (mixed) and with double factors: the same rest and contact force to the Newton
    tolerance, the mixed path's factors single."""
    stats: dict = {}
    x_mixed, f_mixed, _ = _pressed("pardiso", "mixed", stats)
    x_double, f_double, _ = _pressed("pardiso", "double")
    assert stats["single"] > 0
    assert np.abs(f_mixed - f_double).max() <= 1e-8 * np.linalg.norm(f_double)
    assert np.abs(x_mixed - x_double).max() <= 1e-9


def test_multigrid_newton_reaches_the_direct_rest_with_its_solves_stopped_at_the_forcing_term(monkeypatch):
    """The foam cube settling on a rough table under its weight (a symmetric Newton matrix: the
    multigrid path solves it by conjugate gradients, stopped at each Newton step's forcing term,
    not at the cache's 1e-10) rests where sparse LU's exact Newton steps bring it; and the
    pressed and dragged fingertip (multigrid GMRES on the exact product) as well."""
    body = build_body(box(0.05, 4), preset("foam"), mass=0.0125)
    scene = Scene(body, (PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=1.0, name="table"),))
    asked: list[float] = []
    cg = mg_krylov.cg

    def spy(A, b, M, rtol, max_it):
        asked.append(rtol)
        return cg(A, b, M, rtol, max_it)

    monkeypatch.setattr(mg_krylov, "cg", spy)
    rests = {}
    for method in ("amg", "direct"):
        cache = SolverCache(method=method)
        rests[method] = solve_static(scene, scene.initial_state(), cache=cache)[0].x
        if method == "amg":
            assert cache.stats["amg_solves"] > 0 and min(cache.iterations) > 0
            # each CG solve to its Newton step's forcing term: looser than the cache's at first
            assert len(asked) == cache.stats["amg_solves"] and min(asked) >= cache.rtol
            assert asked[0] > 1e3 * cache.rtol
    sag = np.abs(rests["direct"] - body.mesh.points).max()
    assert sag > 1e-8  # it did settle (0.24 um)
    assert np.abs(rests["amg"] - rests["direct"]).max() <= 1e-6 * sag
    x_amg, f_amg, _ = _pressed("amg")
    x_ref, f_ref, _ = _pressed("direct")
    assert np.abs(f_amg - f_ref).max() <= 1e-8 * np.linalg.norm(f_ref)
    assert np.abs(x_amg - x_ref).max() <= 1e-9


# ------------------------------------------------------------------ the corrected old factor


def _table_blocks(K: sp.csr_matrix, nodes, scale: float) -> sp.csr_matrix:
    """A table's penalty on ``nodes``: ``scale`` times each node's own diagonal, normal and
    tangential (3x3 diagonal blocks)."""
    d = np.zeros(K.shape[0])
    for i in nodes:
        d[3 * i : 3 * i + 3] = scale * K.diagonal()[3 * i : 3 * i + 3]
    return sp.diags(d).tocsr()


@needs_mkl
def test_the_old_factor_corrected_for_new_contacts_is_the_new_matrix_inverse():
    """A0 factorised, then six nodes touch a table (a penalty 50 times their stiffness): the
    Woodbury-corrected old factor applied to b is A^-1 b, as fresh LU gives it, for A the new
    matrix (the difference lies on those nodes only). The plain old factor is far from it."""
    from softgrasp.linalg.factored import _Corrected

    K = _stiffness()
    f = pardiso.PardisoFactor(K)
    A = (K + _table_blocks(K, [0, 3, 7, 11, 20, 31], 50.0)).tocsr()
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    cache = SolverCache()
    pre = _Corrected(f, f.same_pattern(A), cache)
    assert pre.nodes == 6 and cache.stats["correction_columns"] == 18
    exact = spla.spsolve(A.tocsc(), b)
    assert np.abs(pre.solve(b) - exact).max() <= 1e-9 * np.abs(exact).max()
    assert np.abs(f.solve(b) - exact).max() > 0.1 * np.abs(exact).max()
    # Two more nodes touch: only their columns are new; after a refactorisation all are.
    A2 = (A + _table_blocks(K, [40, 41], 50.0)).tocsr()
    pre2 = _Corrected(f, f.same_pattern(A2), cache)
    assert pre2.nodes == 8 and cache.stats["correction_columns"] == 24
    exact2 = spla.spsolve(A2.tocsc(), b)
    assert np.abs(pre2.solve(b) - exact2).max() <= 1e-9 * np.abs(exact2).max()
    f.refactor(f.same_pattern(A))
    cache.stats["factorisations"] += 1
    pre3 = _Corrected(f, f.same_pattern(A2), cache)
    assert pre3.nodes == 2 and cache.stats["correction_columns"] == 30
    assert np.abs(pre3.solve(b) - exact2).max() <= 1e-9 * np.abs(exact2).max()


@needs_mkl
def test_the_old_factor_is_not_corrected_where_stiffness_was_taken_away():
    """The table removed (the hold check's release): the factor of the matrix with the table is
    used as it is (correcting it could give a nearly singular matrix)."""
    from softgrasp.linalg.factored import _Corrected

    K = _stiffness()
    A0 = (K + _table_blocks(K, [0, 3, 7], 50.0)).tocsr()
    f = pardiso.PardisoFactor(A0)
    pre = _Corrected(f, f.same_pattern(K), SolverCache())
    b = np.random.default_rng(4).standard_normal(K.shape[0])
    assert pre.nodes == 0
    assert np.array_equal(pre.solve(b), f.solve(b))


@needs_mkl
@pytest.mark.parametrize("used", ["few", "many"])
def test_an_old_factor_that_needed_many_iterations_is_renewed_before_the_next_system(monkeypatch, used):
    """A system solved on the old factor with more than half the iteration cap (a quarter of a
    refactorisation's cost) has the next system refactorise first; one solved in fewer keeps the
    factor. (The iterations are stood in for: each 'iteration' one solve with the factor.)"""
    import softgrasp.linalg.factored as ls

    K = _stiffness()
    b = np.random.default_rng(5).standard_normal(K.shape[0])
    cache = SolverCache(method="pardiso")
    solve_newton_system(K, b, None, np.zeros((K.shape[0] // 3, 3)), cache)  # analyse + factorise
    cap = int(np.clip(0.5 * ls.SOLVE_SPEED_RATIO * cache._factor.solves_per_factorisation, 4, 40))
    n = int(ls.STALE_REFRESH * cap) + (1 if used == "many" else 0)

    def stand_in(A, rhs, pre, max_it, rtol, keep_last=False):
        for _ in range(n):
            pre.solve(rhs)
        return spla.spsolve(A.tocsc(), rhs), False

    monkeypatch.setattr(ls, "stale_pcg", stand_in)
    K2 = (1.01 * K).tocsr()
    before = cache.stats["factorisations"]
    solve_newton_system(K2, b, None, np.zeros((K.shape[0] // 3, 3)), cache)
    assert cache.stats["factorisations"] == before  # solved on the old factor
    solve_newton_system(K2, b, None, np.zeros((K.shape[0] // 3, 3)), cache)
    assert cache.stats["factorisations"] == before + (1 if used == "many" else 0)


@needs_mkl
def test_an_old_factor_is_renewed_once_its_extra_solves_add_up_to_a_refactorisation(monkeypatch):
    """Systems each solved on the old factor in fewer than half the iteration cap keep it, until
    the solves they took beyond what the factor's own system took add up to a refactorisation's
    time (``SOLVE_SPEED_RATIO`` x its operation count in solves): then the next system
    refactorises. (The iterations are stood in for: each 'iteration' one solve with the factor.)"""
    import softgrasp.linalg.factored as ls

    K = _stiffness()
    b = np.random.default_rng(12).standard_normal(K.shape[0])
    x_nodes = np.zeros((K.shape[0] // 3, 3))
    cache = SolverCache(method="pardiso", precision="double")
    solve_newton_system(K, b, None, x_nodes, cache)  # analyse + factorise: its own system
    f = cache._factor
    fresh = cache._fresh
    assert fresh == f.solves >= 1
    cap = int(np.clip(0.5 * ls.SOLVE_SPEED_RATIO * f.solves_per_factorisation, 4, 40))
    n = int(ls.STALE_REFRESH * cap)  # the most a stale system may take and keep the factor
    budget = ls.SOLVE_SPEED_RATIO * f.solves_per_factorisation
    kept = int(budget // (n - fresh))  # stale systems whose extra solves stay within it

    def stand_in(A, rhs, pre, max_it, rtol, keep_last=False):
        for _ in range(n):
            pre.solve(rhs)
        return spla.spsolve(A.tocsc(), rhs), False

    monkeypatch.setattr(ls, "stale_pcg", stand_in)
    before = cache.stats["factorisations"]
    K2 = (1.01 * K).tocsr()
    for _ in range(kept + 1):
        solve_newton_system(K2, b, None, x_nodes, cache)
        assert cache.stats["factorisations"] == before  # solved on the old factor
    assert cache._excess == (kept + 1) * (n - fresh) > budget
    solve_newton_system(K2, b, None, x_nodes, cache)
    assert cache.stats["factorisations"] == before + 1 and cache._excess == 0


@needs_mkl
@pytest.mark.parametrize("precision", ["double", "mixed"])
@pytest.mark.parametrize("told", [True, False])
def test_a_changed_scene_refactorises_at_once(monkeypatch, told, precision):
    """After ``scene_changed`` (the hold check takes the table away) the next system is
    factorised at once and solved with one or two solves of the new factor (a single-precision
    one: two more, refining float32's ~1e-4 residual to 1e-11); untold, it is first iterated on
    the old factor (at least four solves, in vain here). Either way it is solved exactly."""
    K = _stiffness()
    b = np.random.default_rng(9).standard_normal(K.shape[0])
    x_nodes = np.zeros((K.shape[0] // 3, 3))
    cache = SolverCache(method="pardiso", precision=precision)
    with_table = (K + _table_blocks(K, [0, 3, 7], 5e3)).tocsr()
    solve_newton_system(with_table, b, None, x_nodes, cache)
    solves = []
    real = pardiso.PardisoFactor.solve
    monkeypatch.setattr(pardiso.PardisoFactor, "solve", lambda f, rhs: solves.append(1) or real(f, rhs))
    factorised = cache.stats["factorisations"]
    if told:
        cache.scene_changed()
    x, _ = solve_newton_system(K, b, None, x_nodes, cache)
    np.testing.assert_allclose(K @ x, b, rtol=0, atol=1e-8 * np.abs(b).max())
    assert cache.stats["factorisations"] == factorised + 1
    assert cache._factor.single_precision == (precision == "mixed")
    assert (len(solves) <= (2 if precision == "double" else 4)) if told else (len(solves) >= 4)


@needs_mkl
def test_the_kept_correction_columns_stay_bounded_as_contacts_move():
    """Contacts that move over the surface on one factor (new nodes each system) do not pile up
    columns: past six times the most corrected nodes' worth, only the current nodes' are kept."""
    import softgrasp.linalg.factored as ls

    K = _stiffness()
    f = pardiso.PardisoFactor(K)
    cache = SolverCache()
    n_nodes = K.shape[0] // 3
    m = ls.CORRECT_MAX_NODES
    for k in range(8):
        nodes = [(k * m + i) % n_nodes for i in range(m)]
        ls._Corrected(f, f.same_pattern((K + _table_blocks(K, nodes, 50.0)).tocsr()), cache)
        # columns are kept per unknown: at most the threshold's plus the current nodes' three each
        assert len(cache._correction[2]) <= 6 * m + 3 * m


@needs_mkl
def test_numpy_blas_runs_on_one_thread_while_pardiso_may_run_on_two():
    """Inside ``blas_one_thread`` NumPy's and SciPy's OpenBLAS libraries are limited to one thread
    (their idle threads and PARDISO's spin against each other on two cores) and MKL's count, which
    PARDISO's phases must keep, is left alone; holders overlapping from two threads (the CLI's
    warm-up solving while the plan starts) keep the limit until the last one leaves, then the
    counts found first come back; where PARDISO runs on one thread nothing changes."""
    threadpoolctl = pytest.importorskip("threadpoolctl")

    def counts() -> dict[str, int]:
        return {i["filepath"]: i["num_threads"] for i in threadpoolctl.threadpool_info()}

    def apis() -> dict[str, str]:
        return {i["filepath"]: i["internal_api"] for i in threadpoolctl.threadpool_info()}

    from softgrasp.linalg import mkl as mkl_library
    from softgrasp.linalg.threads import cores

    if mkl_library._openblas() is None or cores() < 2:
        pytest.skip("needs NumPy on OpenBLAS and two cores")
    K = _stiffness()
    pardiso.set_threads(2)
    try:
        f = pardiso.PardisoFactor(K)  # loads MKL and sets its thread count
        before = counts()
        blas = [p for p, api in apis().items() if api in ("openblas", "blis")]
        mkl = [p for p, api in apis().items() if api == "mkl"]
        if max(before[p] for p in blas) < 2:
            pytest.skip("OpenBLAS already runs on one thread here")
        with pardiso.blas_one_thread():
            inside = counts()
            x = f.solve(np.ones(K.shape[0]))
        assert all(inside[p] == 1 for p in blas) and all(inside[p] == before[p] for p in mkl)
        assert counts() == before
        np.testing.assert_allclose(K @ x, np.ones(K.shape[0]), rtol=0, atol=1e-9)
        first, second = pardiso.blas_one_thread(), pardiso.blas_one_thread()
        first.__enter__()
        second.__enter__()
        first.__exit__(None, None, None)
        assert all(counts()[p] == 1 for p in blas)  # the second holder still holds it
        second.__exit__(None, None, None)
        assert counts() == before
        pardiso.set_threads(1)
        with pardiso.blas_one_thread():
            assert counts() == before
    finally:
        pardiso.set_threads(None)


@needs_mkl
def test_a_single_precision_solve_of_a_tiny_right_hand_side_is_not_flushed_to_zero():
    """float32 holds nothing below ~1e-45: a right-hand side of 1e-40 N would vanish, and its
    refined solve would stop at the raw single solve. Scaled by a power of two before the float32
    solve, it solves like any other (and the same bits as unscaled where float32 holds it)."""
    K = _stiffness()
    b = np.random.default_rng(31).standard_normal(K.shape[0])
    f = pardiso.PardisoFactor(K, single=True)
    assert f.single_precision
    x = f.solve(b)
    assert np.array_equal(f.solve(b * 2.0**-20) * 2.0**20, x)
    for tiny in (1e-30, 1e-40):
        xt = f.solve(b * tiny)
        assert np.linalg.norm(K @ xt - b * tiny) <= 1e-2 * tiny * np.linalg.norm(b)
    cache = SolverCache(method="pardiso", precision="mixed")
    x, _ = solve_newton_system(K, b * 1e-40, None, np.zeros((K.shape[0] // 3, 3)), cache)
    assert np.linalg.norm(K @ x - b * 1e-40) <= krylov.STALE_RTOL * 1e-40 * np.linalg.norm(b)


@needs_mkl
def test_a_failed_first_solve_of_a_new_factor_leaves_no_stale_renewal_count(monkeypatch):
    """The count of solves an old factor's age has cost is reset when a factor is made, before its
    own system is solved: a solve that raises there (multigrid on a singular stiffness) leaves no
    count of the previous factor behind."""
    from softgrasp.errors import NotConverged

    K = _stiffness()
    b = np.random.default_rng(13).standard_normal(K.shape[0])
    x_nodes = np.zeros((K.shape[0] // 3, 3))
    cache = SolverCache(method="pardiso")
    solve_newton_system(K, b, None, x_nodes, cache)
    cache._excess, cache._fresh = 57, 3  # as if the old factor had aged

    def fail(*args, **kwargs):
        raise NotConverged("stand-in")

    monkeypatch.setattr(factored, "_fresh_solve", fail)
    cache.scene_changed()  # the next system refactorises
    with pytest.raises(NotConverged):
        solve_newton_system((1.1 * K).tocsr(), b, None, x_nodes, cache)
    assert cache._excess == 0 and cache._fresh == -1


def _table_then_plate(n: int):
    """The foam cube's rest stiffness (``box(0.05, n)``) resting on a table (its bottom nodes
    held by half their own stiffness, a 1e-6 diagonal shift), then with its top face pressed by a
    stiff plate (a penalty 50 times the nodes' own stiffness): the two Newton matrices and the
    node positions."""
    body = build_body(box(0.05, n), preset("foam"), mass=0.0125)
    K = (-body.rest_jacobian).tocsr()
    x = np.asarray(body.mesh.points)
    bottom = np.flatnonzero(x[:, 2] < x[:, 2].min() + 1e-9)
    top = np.flatnonzero(x[:, 2] > x[:, 2].max() - 1e-9)
    A0 = (K + 1e-6 * sp.diags(K.diagonal()) + _table_blocks(K, bottom, 0.5)).tocsr()
    A1 = (A0 + _table_blocks(K, top, 50.0)).tocsr()
    return A0, A1, x


def _both_on_one_hierarchy(n: int, rtol: float, seed: int):
    """:func:`_table_then_plate`'s two systems solved in turn on the multigrid path to ``rtol``,
    one right-hand side: (the cache, the second matrix, b, the node positions, its solution),
    the hierarchy built for the first kept for the second."""
    A0, A1, x = _table_then_plate(n)
    b = np.random.default_rng(seed).standard_normal(A0.shape[0])
    cache = SolverCache(method="amg", rtol=rtol)
    solve_newton_system(A0, b, None, x, cache)
    hierarchy = cache._ml
    dx, _ = solve_newton_system(A1, b, None, x, cache)
    assert cache._ml is hierarchy  # kept, not rebuilt
    return cache, A1, b, x, dx


def test_hierarchies_built_by_threads_at_once_are_those_built_alone():
    """The multigrid hierarchy is built from NumPy's seeded global generator (pyamg's spectral
    radius estimate): threads building at once (a script planning on a thread pool) get the
    same prolongators, to the bit, as one built alone; without softgrasp holding the generator
    for each build they drew from each other's sequence."""
    from concurrent.futures import ThreadPoolExecutor

    A0, A1, x = _table_then_plate(5)
    alone = [hierarchy.hierarchy(A, x) for A in (A0, A1)]
    with ThreadPoolExecutor(4) as pool:
        built = list(pool.map(lambda k: hierarchy.hierarchy((A0, A1)[k % 2], x), range(16)))
    for k, ml in enumerate(built):
        want = alone[k % 2]
        for a, b in zip(ml.levels[:-1], want.levels[:-1], strict=True):
            assert np.array_equal(a.P.toarray(), b.P.toarray())


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_child_forked_while_a_thread_builds_a_hierarchy_builds_its_own(finished_ok):
    """A process forked while another thread holds the generator's lock (a sweep forking workers
    while a plan runs) builds hierarchies in the child: the child has a lock of its own (the
    parent's, held at the fork, would never be released there: the build would wait forever)."""
    import multiprocessing

    A0, _, x = _table_then_plate(3)
    ctx = multiprocessing.get_context("fork")
    with hierarchy._GLOBAL_RNG:  # held, as by another thread building, when the child is forked
        child = ctx.Process(target=hierarchy.hierarchy, args=(A0, x))
        child.start()
    assert finished_ok(child)


def _solve_in_child(A, b, x) -> None:
    cache = SolverCache(method="amg", rtol=1e-8)
    dx, _ = solve_newton_system(A, b, None, x, cache)
    if cache.stats["amg_solves"] != 1 or not np.linalg.norm(A @ dx - b) <= 1e-8 * np.linalg.norm(b):
        raise SystemExit(3)


def _multigrid_solve_then_fork(finished_ok) -> None:
    """Solve on the multigrid path (its V-cycles on Numba's threads), fork, and check that the
    child's own multigrid solve converges."""
    import multiprocessing

    A0, A1, x = _table_then_plate(6)
    b = np.ones(A0.shape[0])
    solve_newton_system(A0, b, None, x, SolverCache(method="amg"))  # the parallel kernels, here
    child = multiprocessing.get_context("fork").Process(target=_solve_in_child, args=(A1, b, x))
    child.start()
    assert finished_ok(child)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_child_forked_after_multigrid_solves_runs_its_own(finished_ok):
    """A script that solves on the multigrid path and then forks workers: a worker's multigrid
    solve converges (under GNU OpenMP, Numba's layer before softgrasp made TBB loadable, the child
    was terminated at its first parallel V-cycle; the same under OpenMP now:
    ``test_kernels.test_under_openmp_a_forked_child_...``)."""
    _multigrid_solve_then_fork(finished_ok)


def test_a_kept_multigrid_hierarchy_smooths_with_the_current_matrix():
    """The foam cube resting on a table (its bottom nodes held), then its top face pressed by a
    stiff plate (a penalty 50 times the nodes' own stiffness): the multigrid hierarchy kept from
    the first matrix, its finest level the new matrix, solves the second system to the
    tolerance within three times the iterations a fresh hierarchy needs (16 against 15 here with
    the coarse levels brought up to date, 41 without; a hierarchy kept whole, smoothing with the
    first matrix, needed 175 against a fresh one's 11 with pyamg's symmetric sweeps)."""
    kept, A1, b, x, dx = _both_on_one_hierarchy(8, 1e-8, seed=1)
    fresh = SolverCache(method="amg", rtol=1e-8)
    solve_newton_system(A1, b, None, x, fresh)
    assert kept.stats["amg_solves"] == 2 and len(kept.iterations) == 2
    assert np.linalg.norm(A1 @ dx - b) <= 1e-8 * np.linalg.norm(b)
    assert kept.iterations[1] <= 3 * fresh.iterations[0], (kept.iterations, fresh.iterations)


@pytest.mark.parametrize("n", [6, 10, 14])
def test_a_kept_hierarchy_updated_for_a_pressing_plate_converges_as_a_fresh_one(n):
    """The same two systems: with the hierarchy kept from the first and its coarse levels brought
    up to date (the plate's nodes out of the coarse space:
    :mod:`softgrasp.linalg.multigrid.coarse`), CG on the second takes at most two iterations more
    than with a hierarchy built on it (16 against 15 here); with the coarse levels as built it
    took more than twice as many (36 and 46). At n = 14
    the hierarchy has three levels: the change reaches the third by the second's Galerkin
    product, and the second level's sweeps are updated in place."""
    kept, A1, b, x, dx = _both_on_one_hierarchy(n, 1e-8, seed=1)
    assert len(kept._ml.ml.levels) == (3 if n == 14 else 2)
    fresh = SolverCache(method="amg", rtol=1e-8)
    solve_newton_system(A1, b, None, x, fresh)
    assert np.linalg.norm(A1 @ dx - b) <= 1e-8 * np.linalg.norm(b)
    assert kept._ml._pinned is not None and kept._ml._pinned.size > 0  # the plate's nodes
    assert kept.iterations[1] <= fresh.iterations[0] + 2, (kept.iterations, fresh.iterations)
    stale = SolverCache(method="amg", rtol=1e-8)
    solve_newton_system(kept._ml._A0, b, None, x, stale)
    stale._ml._levels = []  # the coarse levels as built
    solve_newton_system(A1, b, None, x, stale)
    assert stale.iterations[1] > 2 * kept.iterations[1], (stale.iterations, kept.iterations)


def test_a_matrix_stiffened_throughout_keeps_the_coarse_levels_as_built():
    """The cube on the table's matrix scaled by two everywhere (no contact stands out): no node
    leaves the coarse space and the coarse levels stay as built; CG takes 23 iterations against
    17 on the first matrix (the coarse correction off by the factor), where pinning every node
    whose stiffness doubled took 87."""
    A0, _, x = _table_then_plate(8)
    b = np.random.default_rng(4).standard_normal(A0.shape[0])
    cache = SolverCache(method="amg", rtol=1e-8)
    solve_newton_system(A0, b, None, x, cache)
    solve_newton_system((2.0 * A0).tocsr(), b, None, x, cache)
    ml = cache._ml
    assert ml._pinned is None and not any(level.changed for level in ml._levels)
    assert cache.iterations[1] <= 2 * cache.iterations[0], cache.iterations


def test_the_cache_counts_systems_set_ups_and_v_cycles_as_conjugate_gradients_apply_them(monkeypatch):
    """``SolverCache.stats`` (what ``GraspPlan.solver_stats`` reports): two systems on one kept
    hierarchy are two systems and one set-up, and the V-cycles counted are the preconditioner
    applications conjugate gradients made, one per iteration (the first before the loop, none
    after the last), counted independently by a wrapper around the V-cycle."""
    applied = []
    real = cycle.Multigrid._cycle

    def counted(self, lvl, b):
        if lvl == 0:
            applied.append(1)
        return real(self, lvl, b)

    monkeypatch.setattr(cycle.Multigrid, "_cycle", counted)
    cache, *_ = _both_on_one_hierarchy(8, 1e-8, seed=3)
    assert cache.stats["systems"] == 2 and cache.stats["multigrid_setups"] == 1
    assert cache.stats["multigrid_cycles"] == len(applied) == sum(cache.iterations) > 2


def test_a_kept_single_level_hierarchy_solves_each_new_matrix_exactly():
    """A system no larger than the multigrid's coarsest level (the coarsest foam cube, 59 nodes,
    177 unknowns) is its own coarsest level: the kept hierarchy's direct solve must be the new
    matrix's, so that conjugate gradients stop after one iteration on the second matrix too."""
    cache, A1, b, x, dx = _both_on_one_hierarchy(2, 1e-10, seed=2)
    assert len(cache._ml.ml.levels) == 1
    assert cache.iterations == [1, 1]
    assert np.linalg.norm(A1 @ dx - b) <= 1e-10 * np.linalg.norm(b)


def test_multigrid_gmres_applies_the_exact_product_with_the_compiled_matrix_product(monkeypatch):
    """The pressed and dragged fingertip on the multigrid path: GMRES's exact Newton product is
    the multigrid's product of the assembled matrix plus the exact product's finite-difference
    correction, equal to the exact product itself to rounding, at every application."""
    calls = []
    fast = mg_krylov._fast_exact

    def checked(fine, correction, v):
        got = fast(fine, correction, v)
        want = correction.__self__(v)  # the static solver's own exact product
        calls.append(float(np.abs(got - want).max() / np.abs(want).max()))
        return got

    monkeypatch.setattr(mg_krylov, "_fast_exact", checked)
    _pressed("amg")
    assert len(calls) > 5
    assert max(calls) <= 1e-12, max(calls)


@pytest.mark.parametrize("mkl", [True, False])
@pytest.mark.parametrize("method", ["auto", "amg", "direct", "reference", "pardiso"])
@pytest.mark.parametrize("shape", [(3, 3, 3), (9, 9, 9)])
def test_by_multigrid_says_where_a_newton_system_goes(monkeypatch, mkl, method, shape):
    """``by_multigrid`` (the planner's settle asks it) agrees with where ``solve_newton_system``
    sends an unconstrained system: the multigrid solves counted, or none; with MKL (PARDISO's
    limit lowered so that the larger box goes past it) and without; an unknown method is refused
    by both."""
    if (mkl or method == "pardiso") and not pardiso.available():
        pytest.skip("MKL not installed")
    if not mkl:
        if method == "pardiso":
            pytest.skip("PARDISO needs MKL")
        monkeypatch.setattr(pardiso, "available", lambda: False)
    monkeypatch.setattr(linsolve, "PARDISO_MAX_DOF", 3000)
    body = build_body(box((0.03, 0.03, 0.03), shape), preset("rubber"))
    table = PlaneContact(Plane(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])), mu=0.5)
    x = np.asarray(body.mesh.points)
    scene = Scene(body, (table,))
    A = (-scene.jacobian(x - [0.0, 0.0, 1e-4], 0.0, scene.initial_state().contacts)).tocsr()  # held
    cache = SolverCache(method=method)
    solve_newton_system(A, np.ones(A.shape[0]), None, x, cache)
    assert linsolve.by_multigrid(A.shape[0], cache) == (cache.stats["amg_solves"] > 0)
    unknown = SolverCache(method="cholmod")
    with pytest.raises(ValueError, match="cholmod"):
        linsolve.by_multigrid(A.shape[0], unknown)
    with pytest.raises(ValueError, match="cholmod"):
        solve_newton_system(A, np.ones(A.shape[0]), None, x, unknown)


def test_by_multigrid_covers_each_route():
    """The boxes above reach every route: the sizes straddle the limits."""
    small = 3 * build_body(box((0.03, 0.03, 0.03), (3, 3, 3)), preset("rubber")).n_nodes
    large = 3 * build_body(box((0.03, 0.03, 0.03), (9, 9, 9)), preset("rubber")).n_nodes
    assert small <= linsolve.DIRECT_MAX_DOF < 3000 < large
