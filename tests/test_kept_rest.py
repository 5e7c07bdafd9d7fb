"""The object's rest on the table kept across processes (:mod:`softgrasp.grasp.kept_rest`): read
back, it is the rest a settle finds, bit for bit, an equilibrium on the same table, and the plan
from it is the plan from a settle; each object, table and solver has its own entry."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from softgrasp import usercache
from softgrasp.grasp import kept_rest
from softgrasp.grasp.config import PlanConfig
from softgrasp.grasp.planner import plan_grasp
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import Material
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body
from softgrasp.sim.scene import Scene


@pytest.fixture(scope="module")
def body():
    mesh, material, mass = make_object("sphere")
    return build_body(mesh, material, mass=mass)


@pytest.fixture
def rests(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "softgrasp" / kept_rest.KIND


def _entries(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.npz")) if folder.exists() else []


def test_a_kept_rest_is_the_settled_rest_and_balances_the_weight_on_the_same_table(body, rests):
    cfg = PlanConfig()
    cache = SolverCache()
    made, table_made, placed_made = kept_rest.settle(body, cfg, cache, keep=True)
    assert cache.stats["settle_systems"] == cache.stats["systems"] > 0 and "rest_kept" not in cache.stats
    # settled on a solver state of its own: the caller's holds no factor of the settle's, so what
    # follows starts alike whether the rest was found or read back
    assert cache._factor is None and cache._ml is None
    assert len(_entries(rests)) == 1
    again = SolverCache()
    kept, table, placed = kept_rest.settle(body, cfg, again, keep=True)
    assert again.stats["rest_kept"] == 1 and again.stats["settle_systems"] == again.stats["systems"] == 0
    assert np.array_equal(kept.x, made.x) and np.array_equal(kept.v, made.v) and kept.t == made.t
    assert np.array_equal(placed, placed_made)
    (s_made,), (s_kept,) = made.contacts, kept.contacts
    assert np.array_equal(s_kept.active, s_made.active) and np.array_equal(s_kept.anchor, s_made.anchor)
    assert s_kept.cap is None and s_kept.stick is None
    for a, b in ((table, table_made), (table.plane, table_made.plane)):
        assert usercache.value_digest(a) == usercache.value_digest(b)  # every field, exactly
    # The rest read back is an equilibrium on that table: its forces hold the weight, nothing is
    # left unbalanced beyond the settle's tolerance.
    scene = Scene(body, (table,))
    f_table = table.static_forces(body, kept.x, kept.t, s_kept)
    weight = body.total_mass * abs(body.gravity[2])
    assert f_table[:, 2].sum() == pytest.approx(weight, rel=1e-6)
    unbalanced = scene.static_forces(kept.x, kept.t, kept.contacts)
    assert np.abs(unbalanced).max() < 1e-5 * weight


def test_a_plan_from_a_kept_rest_is_the_plan_from_a_settle(body, rests):
    cfg = PlanConfig(hold_time=0.05)
    settled = plan_grasp(body, cfg)
    first = plan_grasp(body, cfg, keep_rest=True)
    kept = plan_grasp(body, cfg, keep_rest=True)
    assert first.solver_stats["settle_systems"] > 0 and kept.solver_stats["settle_systems"] == 0
    assert kept.solver_stats["rest_kept"] == 1
    for plan in (first, kept):
        assert np.array_equal(plan.setpoints, settled.setpoints)
        assert np.array_equal(plan.positions, settled.positions)
        assert plan.margin.checks == settled.margin.checks
    assert kept.solver_stats["closing_systems"] == settled.solver_stats["closing_systems"]


def test_each_table_object_and_solver_has_its_own_rest(body, rests):
    cfg = PlanConfig()
    base, _, _ = kept_rest.settle(body, cfg, SolverCache(), keep=True)
    slippery, _, _ = kept_rest.settle(body, replace(cfg, table_mu=0.2), SolverCache(), keep=True)
    m = body.material
    stiffer_material = Material(E=2.0 * m.E, nu=m.nu, density=m.density, law=m.law, name=m.name)
    stiffer = build_body(body.mesh, stiffer_material, mass=body.total_mass)
    hard, _, _ = kept_rest.settle(stiffer, cfg, SolverCache(), keep=True)
    kept_rest.settle(body, cfg, SolverCache(method="direct"), keep=True)
    assert len(_entries(rests)) == 4
    # the stiffer ball sinks less into the table: its own rest, not the other's read back
    assert hard.x[:, 2].min() > base.x[:, 2].min()
    assert not np.array_equal(slippery.x, base.x)
    again = SolverCache()
    kept_rest.settle(body, cfg, again, keep=True)
    assert again.stats["rest_kept"] == 1 and len(_entries(rests)) == 4


def test_another_processor_keeps_a_rest_of_its_own(body, rests, monkeypatch):
    """MKL and the kernels round differently on another kind of processor: a cache folder shared
    between machines holds a rest per kind, none read back on the other."""
    import llvmlite.binding as llvm

    kept_rest.settle(body, PlanConfig(), SolverCache(), keep=True)
    monkeypatch.setattr(llvm, "get_host_cpu_name", lambda: "another-processor")
    other = SolverCache()
    kept_rest.settle(body, PlanConfig(), other, keep=True)
    assert "rest_kept" not in other.stats and other.stats["settle_systems"] > 0
    assert len(_entries(rests)) == 2


@pytest.mark.parametrize("damage", ["not an npz file", "truncated", "wrong size"])
def test_a_damaged_rest_is_found_again(body, rests, damage):
    cfg = PlanConfig()
    made, _, _ = kept_rest.settle(body, cfg, SolverCache(), keep=True)
    (entry,) = _entries(rests)
    whole = entry.read_bytes()
    if damage == "wrong size":
        arrays = dict(np.load(entry))
        arrays["x"] = arrays["x"][:-1]
        with open(entry, "wb") as f:
            np.savez(f, **arrays)
    else:
        entry.write_bytes(b"not an npz file" if damage == "not an npz file" else whole[: len(whole) // 2])
    again = SolverCache()
    found, _, _ = kept_rest.settle(body, cfg, again, keep=True)
    assert "rest_kept" not in again.stats and again.stats["settle_systems"] > 0
    assert np.array_equal(found.x, made.x)
    with np.load(entry) as kept:  # kept again, whole
        assert np.array_equal(kept["x"], made.x)


@dataclass(frozen=True)
class _Holder:
    value: object


def test_a_value_is_written_down_exactly_or_not_at_all():
    a = np.linspace(0.0, 1.0, 7)
    b = a.copy()
    b[3] = np.nextafter(b[3], 2.0)  # one unit in the last place
    assert usercache.value_digest(_Holder(a)) == usercache.value_digest(_Holder(a.copy()))
    assert usercache.value_digest(_Holder(a)) != usercache.value_digest(_Holder(b))
    assert usercache.value_digest(_Holder(a)) != usercache.value_digest(_Holder(a.astype(np.float32)))
    assert usercache.value_digest(_Holder(a)) != usercache.value_digest(_Holder(a.reshape(7, 1)))
    assert usercache.value_digest(_Holder(1)) != usercache.value_digest(_Holder(1.0))
    assert usercache.value_digest(_Holder((1, "a"))) != usercache.value_digest(_Holder([1, "a"]))
    assert usercache.value_digest(_Holder(object())) is None  # its state is not seen: no key
    assert usercache.value_digest(_Holder(lambda s: s)) is None


def test_no_rest_is_kept_for_a_body_that_cannot_be_written_down(body, rests, monkeypatch):
    monkeypatch.setattr(usercache, "value_digest", lambda value: None)
    cache = SolverCache()
    kept_rest.settle(body, PlanConfig(), cache, keep=True)
    assert cache.stats["settle_systems"] > 0 and not _entries(rests)
