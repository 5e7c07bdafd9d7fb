"""The hand-placement solve (:mod:`softgrasp.hand.descent`, compiled) agrees with the NumPy
oracle (:func:`oracles.hand.solve`) to 1e-9 [m, rad], and :func:`place_hand` returns the same
placement with either.

Every iteration agrees to round-off whatever the targets (one iteration at a time along the
oracle's path). Whole solves compound that round-off: a posture reaching its targets along a
well-conditioned path ends within 1e-9 of the oracle, but one wandering near singular postures
short of unreachable targets does not (the oracle itself ends up to 1 rad elsewhere when its
start moves by one ulp). Whole solves of unreachable targets are therefore compared with rules
(stall window, iteration and halving budgets) that retire every posture before the round-off grows;
each comparison also checks that its posture stopped by the rule under test.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from oracles import hand as oracle
from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand import descent as kernel
from softgrasp.hand import placement as reach
from softgrasp.hand.kinematics import ChainStack, HandModel, chain_stack
from softgrasp.hand.wdls import LIMIT_EPS

#: Agreement of the compiled solve and the NumPy oracle: absolute [m, rad] and relative.
TOL = 1e-9

MODEL = HandModel.default()
FINGERS = ("thumb", "first", "middle")
UP = np.array([0.0, 0.0, 1.0])

Problem = tuple[ChainStack, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _pose(rotvec: list[float], origin: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = reach._rotation(np.asarray(rotvec, dtype=float))
    T[:3, 3] = origin
    return T


#: A palm pose of a grasp from above that the placement does not see.
ABOVE = _pose([2.8, 0.3, 0.2], [0.05, -0.02, 0.18])


def _targets_of(q: dict[str, np.ndarray], pose: np.ndarray = ABOVE) -> dict[str, np.ndarray]:
    """World fingertips of the default hand at palm ``pose`` and joints ``q``."""
    return {f: reach.transform(pose, MODEL.forward(f, q[f])) for f in FINGERS}


def _limit(side: int) -> dict[str, np.ndarray]:
    """Every joint at its lower (``side`` 0) or upper (1) limit."""
    return {f: MODEL.limits(f)[side] for f in FINGERS}


KNOWN = {
    "thumb": np.array([0.5, 0.7, 0.0, 0.1, 0.4]),
    "first": np.array([0.05, 0.6, 0.5]),
    "middle": np.array([-0.05, 0.6, 0.5]),
}

TARGETS = {
    # targets of a posture inside the limits
    "known": _targets_of(KNOWN),
    # targets of postures with every joint at a limit: the clamped step freezes joints
    "lower limits": _targets_of(_limit(0)),
    "upper limits": _targets_of(_limit(1)),
    "mixed limits": _targets_of(
        {"thumb": _limit(1)["thumb"], "first": _limit(0)["first"], "middle": _limit(1)["middle"]}
    ),
    # out of reach: the middle fingertip 0.5 m from the others, or the fingers 0.6 m apart
    "far": {"thumb": [0.0, 0.0, 0.1], "first": [0.05, 0.05, 0.1], "middle": [0.03, 0.6, 0.1]},
    "spread": {"thumb": [0.0, 0.0, 0.1], "first": [0.3, 0.05, 0.1], "middle": [-0.3, 0.05, 0.1]},
}


def _problem(targets: dict[str, np.ndarray], model: HandModel = MODEL) -> Problem:
    """The arguments of :func:`reach._solve` for ``targets``, from :func:`reach.place_hand`'s starts."""
    fingers = tuple(targets)
    T = np.array([np.asarray(targets[f], dtype=float) for f in fingers])
    stack = chain_stack(tuple(model.chain(f) for f in fingers))
    seeds = reach._seeds(model, fingers, T, UP)
    poses = np.array([pose for pose, _ in seeds])
    q0 = np.array([np.concatenate([q[f] for f in fingers]) for _, q in seeds])
    return stack, T, poses[:, :3, :3], poses[:, :3, 3], q0


def _compiled(problem: Problem) -> kernel.Solves:
    """:func:`kernel.solve` with the rules of :mod:`softgrasp.hand.placement` (read now: tests patch them)."""
    return kernel.solve(
        *problem,
        reach_tol=reach.REACH_TOL,
        max_iter=reach.MAX_ITER,
        max_step=reach.MAX_STEP,
        damping=reach.DAMPING,
        stall_fraction=reach.STALL_FRACTION,
        stall_window=reach.STALL_WINDOW,
        max_halvings=reach.MAX_HALVINGS,
        limit_eps=LIMIT_EPS,
    )


def _assert_same(got: tuple[np.ndarray, ...], ref: tuple[np.ndarray, ...]) -> None:
    """R, p, q within TOL (absolute and relative) and the errors within TOL [m]."""
    for a, b in zip(got[:3], ref[:3], strict=True):
        np.testing.assert_allclose(a, b, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(got[3], ref[3], rtol=0, atol=TOL)


# ---------------------------------------------------------------------- whole solves


@pytest.mark.parametrize("case", ["known", "lower limits"])
def test_compiled_solve_equals_the_oracle(case: str) -> None:
    """Every start reaches its targets; ``_solve`` runs the kernel, which ends where the oracle
    does (the lower-limit targets make the clamped step freeze joints)."""
    problem = _problem(TARGETS[case])
    got = reach._solve(*problem)
    stats = _compiled(problem)
    for a, b in zip(got, stats[:4], strict=True):
        np.testing.assert_array_equal(a, b)  # _solve dispatched to the kernel
    _assert_same(got, oracle.solve(*problem))
    assert np.all(stats.stop == kernel.STOP_REACHED)
    if case == "lower limits":
        assert stats.clamps.sum() > len(stats.clamps)


def test_compiled_solve_of_a_hand_with_prismatic_offset_mimic_and_padded_joints(
    tmp_path: Path
) -> None:
    """A prismatic joint, a mimic joint with gain 2 and an offset, a fixed joint and a shorter chain
    (padded): the kernel supports every kind of joint a :class:`ChainStack` holds."""
    path = tmp_path / "hand.urdf"
    path.write_text(
        '<?xml version="1.0"?><robot name="t">'
        '<link name="palm"/><link name="a"/><link name="b"/><link name="c"/>'
        '<link name="xx_tip"><collision><geometry><sphere radius="0.01"/></geometry></collision></link>'
        '<link name="yy_tip"><collision><geometry><sphere radius="0.01"/></geometry></collision></link>'
        '<joint name="S" type="prismatic"><parent link="palm"/><child link="a"/>'
        '<origin xyz="0.1 0 0" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/>'
        '<limit lower="0" upper="0.05"/></joint>'
        '<joint name="R1" type="revolute"><parent link="a"/><child link="b"/>'
        '<axis xyz="0 0 1"/><limit lower="-1" upper="1"/></joint>'
        '<joint name="R2" type="revolute"><parent link="b"/><child link="c"/>'
        '<origin xyz="0.02 0 0"/><axis xyz="0 1 1"/><limit lower="0" upper="1"/>'
        '<mimic joint="R1" multiplier="2" offset="0.1"/></joint>'
        '<joint name="T" type="fixed"><parent link="c"/><child link="xx_tip"/>'
        '<origin xyz="0.03 0 0"/></joint>'
        '<joint name="Y" type="revolute"><parent link="palm"/><child link="yy_tip"/>'
        '<origin xyz="-0.05 0 0"/><axis xyz="1 0 0"/><limit lower="-1" upper="1"/></joint>'
        "</robot>"
    )
    model = HandModel.from_urdf(path)
    q = {"xx": np.array([0.03, 0.2]), "yy": np.array([0.4])}
    pose = _pose([0.2, -0.1, 0.3], [0.01, 0.02, 0.03])
    T = np.array([reach.transform(pose, model.forward(f, q[f])) for f in ("xx", "yy")])
    stack = chain_stack((model.chain("xx"), model.chain("yy")))
    assert stack.has_prismatic and not stack.plain and stack.length == (4, 1)
    starts = [_pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), _pose([0.1, 0.0, 0.2], [0.0, 0.01, 0.0])]
    R = np.array([s[:3, :3] for s in starts])
    p = np.array([s[:3, 3] for s in starts])
    q0 = np.array([[0.01, 0.0, 0.0], [0.04, 0.3, -0.2]])
    got = reach._solve(stack, T, R, p, q0)
    _assert_same(got, oracle.solve(stack, T, R, p, q0))
    assert np.all(got[3] <= reach.REACH_TOL)


@pytest.mark.parametrize(
    ("rules", "stop"),
    [
        ({"STALL_WINDOW": 3, "STALL_FRACTION": 0.2}, kernel.STOP_STALLED),
        ({"MAX_ITER": 6}, kernel.STOP_MAX_ITER),
        ({"MAX_HALVINGS": 2}, kernel.STOP_NO_DECREASE),
        ({"MAX_HALVINGS": 3, "MAX_ITER": 10}, kernel.STOP_NO_DECREASE),
    ],
)
@pytest.mark.parametrize("case", ["far", "spread", "mixed limits"])
def test_unreachable_targets_retire_as_in_the_oracle(
    case: str, rules: dict[str, float], stop: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each retirement rule, with budgets that retire every start before round-off grows: the same
    end postures and errors, and the rule under test stopped some starts short of the targets."""
    for name, value in rules.items():
        monkeypatch.setattr(reach, name, value)
    problem = _problem(TARGETS[case])
    got = reach._solve(*problem)
    _assert_same(got, oracle.solve(*problem))
    stats = _compiled(problem)
    assert np.any((stats.stop == stop) & (stats.error > reach.REACH_TOL))


# ---------------------------------------------------------------------- one iteration at a time


@pytest.mark.parametrize("case", sorted(TARGETS))
def test_every_iteration_equals_the_oracle_along_its_path(
    case: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """From each state of the oracle's first 40 iterations (all starts), one compiled iteration
    ends where one oracle iteration does, and moves the same starts (the others are retired:
    no shortened step decreased the error, or the targets are reached)."""
    monkeypatch.setattr(reach, "MAX_ITER", 1)
    stack, T, R, p, q = _problem(TARGETS[case])
    clamped = 0
    for _ in range(40):
        ref = oracle.solve(stack, T, R, p, q)
        got = _compiled((stack, T, R, p, q))
        _assert_same(got, ref)
        moved = np.any(ref[2] != q, axis=1) | np.any(ref[1] != p, axis=1)
        np.testing.assert_array_equal(got.stop == kernel.STOP_MAX_ITER, moved)
        clamped += int(got.clamps.sum())
        R, p, q = ref[:3]
    assert clamped > 0  # every case freezes joints at their limits on the way


# ---------------------------------------------------------------------- place_hand


def _placements(targets, monkeypatch: pytest.MonkeyPatch, **kw):  # type: ignore[no-untyped-def]
    """:func:`reach.place_hand` of ``targets`` with the compiled solve, then with the oracle's (the
    placement or the refusal's message of each)."""
    out = []
    for solve in (reach._solve, oracle.solve):
        with monkeypatch.context() as m:
            m.setattr(reach, "_solve", solve)
            try:
                out.append(reach.place_hand(MODEL, targets, **kw))
            except InfeasibleGrasp as exc:
                out.append(str(exc))
    return out


@pytest.mark.parametrize("case", ["known", "lower limits", "sphere"])
def test_place_hand_places_the_hand_alike_with_the_oracle(
    case: str, sphere_grasp, monkeypatch: pytest.MonkeyPatch
) -> None:
    if case == "sphere":
        targets, obstacle = sphere_grasp
    else:
        targets, obstacle = TARGETS[case], None
    b, a = _placements(targets, monkeypatch, obstacle=obstacle)
    np.testing.assert_allclose(b.palm_pose, a.palm_pose, rtol=TOL, atol=TOL)
    assert list(b.q) == list(a.q) == list(FINGERS)
    for f in FINGERS:
        np.testing.assert_allclose(b.q[f], a.q[f], rtol=TOL, atol=TOL)
    assert b.limit_room == pytest.approx(a.limit_room, rel=TOL, abs=TOL)
    assert b.error == pytest.approx(a.error, rel=0, abs=TOL)


@pytest.mark.parametrize("case", ["far", "spread"])
def test_place_hand_refuses_unreachable_targets_alike_with_the_oracle(
    case: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same message: the same finger, the same closest distance to 0.1 mm."""
    messages = _placements(TARGETS[case], monkeypatch)
    assert all(isinstance(m, str) and "cannot reach" in m for m in messages)
    assert messages[0] == messages[1]


def test_undamped_solves_equal_the_oracle(monkeypatch: pytest.MonkeyPatch) -> None:
    """With DAMPING = 0 the step is the weighted pseudo-inverse one (the Moore-Penrose inverse of
    ``J W^-1 J^T``), in the kernel as in the oracle."""
    problem = _problem(TARGETS["known"])
    monkeypatch.setattr(reach, "DAMPING", 0.0)
    monkeypatch.setattr(reach, "MAX_ITER", 3)
    _assert_same(reach._solve(*problem), oracle.solve(*problem))


def test_solve_rejects_mismatched_shapes() -> None:
    stack, T, R, p, q = _problem(TARGETS["known"])
    with pytest.raises(ConfigError, match="solve needs R"):
        _compiled((stack, T, R, p, q[:, :-1]))
    with pytest.raises(ConfigError, match="solve needs targets"):
        _compiled((stack, T[:2], R, p, q))
