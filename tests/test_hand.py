"""Shadow-like hand: URDF reading, forward kinematics, Jacobian, WDLS, IK and palm placement."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand.ik import follow_line, solve_ik
from softgrasp.hand.kinematics import HandModel
from softgrasp.hand.wdls import LIMIT_EPS, limited_step, wdls_step

MODEL = HandModel.default()
FINGERS = ("thumb", "first", "middle")
KNUCKLE = {"first": np.array([0.033, 0.095, 0.0]), "middle": np.array([0.011, 0.099, 0.0])}
PROXIMAL, MIDDLE, DISTAL = 0.045, 0.025, 0.026
FINGER_LENGTH = PROXIMAL + MIDDLE + DISTAL
THUMB_BASE = np.array([0.034, 0.029, 0.0085])
THUMB_LENGTH = 0.038 + 0.032 + 0.0275
DEG = math.pi / 180.0


def in_limits(finger: str, q: np.ndarray) -> bool:
    lo, hi = MODEL.limits(finger)
    return bool(np.all(q >= lo) and np.all(q <= hi))


# ---------------------------------------------------------------------- model structure


def test_default_model_fingers_joints_and_limits() -> None:
    assert set(MODEL.fingers) == set(FINGERS)
    assert MODEL.joint_names("first") == ("FFJ4", "FFJ3", "FFJ2")
    assert MODEL.joint_names("middle") == ("MFJ4", "MFJ3", "MFJ2")
    assert MODEL.joint_names("thumb") == ("THJ5", "THJ4", "THJ3", "THJ2", "THJ1")
    lo, hi = MODEL.limits("first")
    np.testing.assert_allclose(lo, np.array([-20.0, -15.0, 0.0]) * DEG, atol=1e-6)
    np.testing.assert_allclose(hi, np.array([20.0, 90.0, 90.0]) * DEG, atol=1e-6)
    lo, hi = MODEL.limits("thumb")
    np.testing.assert_allclose(lo, np.array([-60.0, 0.0, -12.0, -30.0, 0.0]) * DEG, atol=1e-6)
    np.testing.assert_allclose(hi, np.array([60.0, 70.0, 12.0, 30.0, 90.0]) * DEG, atol=1e-6)
    for finger in FINGERS:
        assert MODEL.fingertip_radius(finger) == 0.008
    with pytest.raises(ConfigError, match="unknown finger 'ring'"):
        MODEL.forward("ring", [0.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match="3 finite values"):
        MODEL.forward("first", [0.0, 0.0])


# ---------------------------------------------------------------------- forward kinematics


@pytest.mark.parametrize("finger", ["first", "middle"])
def test_fk_straight_and_flexed_finger(finger: str) -> None:
    k = KNUCKLE[finger]
    np.testing.assert_allclose(MODEL.forward(finger, [0, 0, 0]), k + [0, FINGER_LENGTH, 0], atol=1e-12)
    # J3 = 90 deg: the whole straight finger points out of the palm (+z)
    np.testing.assert_allclose(
        MODEL.forward(finger, [0, math.pi / 2, 0]), k + [0, 0, FINGER_LENGTH], atol=1e-6
    )
    # J3 = J2 = 90 deg (J1 = 90 deg by the coupling): proximal +z, middle -y, distal -z
    np.testing.assert_allclose(
        MODEL.forward(finger, [0, math.pi / 2, math.pi / 2]), k + [0, -MIDDLE, PROXIMAL - DISTAL], atol=1e-6
    )
    # abduction J4 = 15 deg of the straight finger: rotation about +z
    t = 15.0 * DEG
    np.testing.assert_allclose(
        MODEL.forward(finger, [t, 0, 0]),
        k + FINGER_LENGTH * np.array([-math.sin(t), math.cos(t), 0]),
        atol=1e-12,
    )


def test_fk_distal_joint_mimics_middle_joint() -> None:
    a = 30.0 * DEG
    tip = MODEL.forward("first", [0.0, 0.0, a])
    # J2 = 30 deg and J1 = 30 deg: middle phalanx at 30 deg, distal phalanx at 60 deg from +y
    expected = KNUCKLE["first"] + np.array(
        [
            0.0,
            PROXIMAL + MIDDLE * math.cos(a) + DISTAL * math.cos(2 * a),
            MIDDLE * math.sin(a) + DISTAL * math.sin(2 * a),
        ]
    )
    np.testing.assert_allclose(tip, expected, atol=1e-12)
    # not the J1 = 0 position
    uncoupled = KNUCKLE["first"] + np.array(
        [0.0, PROXIMAL + (MIDDLE + DISTAL) * math.cos(a), (MIDDLE + DISTAL) * math.sin(a)]
    )
    assert np.linalg.norm(tip - uncoupled) > 5e-3


def test_fk_thumb_straight_and_lifted() -> None:
    along = np.array([math.sqrt(0.5), math.sqrt(0.5), 0.0])  # 45 deg between +y and +x
    np.testing.assert_allclose(
        MODEL.forward("thumb", np.zeros(5)), THUMB_BASE + THUMB_LENGTH * along, atol=1e-6
    )
    # TH4 lifts the straight thumb off the palm towards +z
    t = 60.0 * DEG
    expected = THUMB_BASE + THUMB_LENGTH * (math.cos(t) * along + math.sin(t) * np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(MODEL.forward("thumb", [0, t, 0, 0, 0]), expected, atol=1e-6)
    # TH5 spins the thumb about its own axis: the straight thumb's tip does not move
    np.testing.assert_allclose(
        MODEL.forward("thumb", [0.7, 0, 0, 0, 0]), THUMB_BASE + THUMB_LENGTH * along, atol=1e-6
    )


# ---------------------------------------------------------------------- Jacobian


@pytest.mark.parametrize("finger", FINGERS)
def test_jacobian_matches_central_differences(finger: str) -> None:
    rng = np.random.default_rng(11)
    lo, hi = MODEL.limits(finger)
    h = 1e-6
    for _ in range(5):
        q = rng.uniform(lo, hi)
        J = MODEL.jacobian(finger, q)
        assert J.shape == (3, q.size)
        fd = np.empty_like(J)
        for i in range(q.size):
            e = np.zeros(q.size)
            e[i] = h
            fd[:, i] = (MODEL.forward(finger, q + e) - MODEL.forward(finger, q - e)) / (2 * h)
        np.testing.assert_allclose(J, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


# ---------------------------------------------------------------------- WDLS


def _random_problem(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(3, 5)) * 0.05, rng.normal(size=3) * 1e-3, rng.uniform(0.5, 3.0, size=5)


def test_wdls_tends_to_weighted_pseudo_inverse() -> None:
    J, dx, w = _random_problem(1)
    Winv = np.diag(1.0 / w)
    exact = Winv @ J.T @ np.linalg.solve(J @ Winv @ J.T, dx)
    np.testing.assert_allclose(wdls_step(J, dx, w, damping=0.0), exact, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(wdls_step(J, dx, np.diag(w), damping=1e-9), exact, rtol=1e-6)
    np.testing.assert_allclose(J @ wdls_step(J, dx, w, damping=0.0), dx, rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize("seed", range(6))
def test_wdls_agrees_with_lapack_on_full_and_rank_deficient_jacobians(seed) -> None:
    """The compiled step's own Cholesky and Jacobi-eigenvalue solves give NumPy's (LAPACK's)
    solve and Moore-Penrose pinv: up to four fingers (12 rows), 20 joints, and a Jacobian whose
    rows repeat (rank-deficient: no damping, the pseudo-inverse)."""
    rng = np.random.default_rng(100 + seed)
    m, n = 3 * (1 + seed % 4), 20
    J = rng.normal(size=(m, n)) * 0.05
    if seed % 2:
        J[m - 3 :] = J[:3]  # the last finger's rows those of the first: rank m - 3
    dx, w = rng.normal(size=m) * 1e-3, rng.uniform(0.5, 3.0, size=n)
    Winv = np.diag(1.0 / w)
    A = J @ Winv @ J.T
    for lam in (1e-3, 0.0):
        ref = Winv @ J.T @ (np.linalg.solve(A + lam**2 * np.eye(m), dx) if lam else np.linalg.pinv(A) @ dx)
        np.testing.assert_allclose(wdls_step(J, dx, w, damping=lam), ref, rtol=1e-8, atol=1e-12)


def test_wdls_solves_the_damped_weighted_least_squares_problem() -> None:
    # minimiser of |J dq - dx|^2 + lambda^2 dq^T W dq: (J^T J + lambda^2 W) dq = J^T dx
    J, dx, w = _random_problem(2)
    lam = 0.02
    expected = np.linalg.solve(J.T @ J + lam**2 * np.diag(w), J.T @ dx)
    np.testing.assert_allclose(wdls_step(J, dx, w, damping=lam), expected, rtol=1e-9)


def test_wdls_damping_shortens_the_step() -> None:
    J, dx, w = _random_problem(3)
    undamped = wdls_step(J, dx, damping=0.0)
    for lam in (1e-3, 1e-2, 1e-1):
        assert np.linalg.norm(wdls_step(J, dx, damping=lam)) < np.linalg.norm(undamped)
    # with weights the W-norm shrinks
    w_norm = lambda dq: float(np.sqrt(dq @ (w * dq)))  # noqa: E731
    assert w_norm(wdls_step(J, dx, w, damping=0.05)) < w_norm(wdls_step(J, dx, w, damping=0.0))


def test_wdls_rejects_bad_inputs() -> None:
    J, dx, w = _random_problem(4)
    with pytest.raises(ConfigError, match="diagonal"):
        wdls_step(J, dx, np.ones((5, 5)))
    with pytest.raises(ConfigError, match="> 0"):
        wdls_step(J, dx, -w)
    with pytest.raises(ConfigError, match="shape"):
        wdls_step(J, dx, w[:3])
    with pytest.raises(ConfigError, match="dx must be 3"):
        wdls_step(J, dx[:2])
    with pytest.raises(ConfigError, match="damping"):
        wdls_step(J, dx, damping=-1.0)
    with pytest.raises(ConfigError, match="matrix"):
        wdls_step(dx, dx)


# ---------------------------------------------------------------------- inverse kinematics


@pytest.mark.parametrize("finger", FINGERS)
def test_solve_ik_reaches_random_reachable_targets(finger: str) -> None:
    rng = np.random.default_rng(7)
    lo, hi = MODEL.limits(finger)
    for _ in range(15):
        target = MODEL.forward(finger, rng.uniform(lo, hi))
        q = solve_ik(MODEL, finger, target, rng.uniform(lo, hi))
        assert in_limits(finger, q)
        assert np.linalg.norm(MODEL.forward(finger, q) - target) <= 1e-5


def test_limited_step_freezes_joints_pushed_out_of_their_range() -> None:
    # first finger with J3 at its upper limit (90 deg); the requested motion would need more J3,
    # so J3 is frozen and the step is the WDLS step of the J4 and J2 columns alone
    lo, hi = MODEL.limits("first")
    q = np.array([0.0, hi[1], 0.3])
    J = MODEL.jacobian("first", q)
    dx = np.array([0.0, -2e-3, 1e-3])
    free_step = wdls_step(J, dx, damping=1e-3)
    assert free_step[1] > 0.0  # unconstrained, J3 would leave its range
    dq, rounds = limited_step(J, dx, q, lo, hi, np.ones(3), 1e-3, LIMIT_EPS)
    assert dq[1] == 0.0 and rounds == 1
    np.testing.assert_allclose(dq[[0, 2]], wdls_step(J[:, [0, 2]], dx, damping=1e-3), rtol=1e-12)
    # a step pointing back into the range is left alone
    back, rounds = limited_step(J, -dx, q, lo, hi, np.ones(3), 1e-3, LIMIT_EPS)
    np.testing.assert_allclose(back, -free_step, rtol=1e-12)
    assert rounds == 0


def _limited_step_reference(J, dx, q, lo, hi, w, damping):  # type: ignore[no-untyped-def]
    """The limit-clamped step written plainly on :func:`wdls_step`: drop the columns of joints at a
    limit that the step pushes out, recompute, until none is left."""
    at_lo, at_hi = q <= lo + 1e-12, q >= hi - 1e-12
    free = ~(at_lo & at_hi)
    while free.any():
        dq = np.zeros_like(q)
        dq[free] = wdls_step(J[:, free], dx, w[free], damping)
        blocked = free & ((at_lo & (dq < 0)) | (at_hi & (dq > 0)))
        if not blocked.any():
            return dq
        free &= ~blocked
    return np.zeros_like(q)


def test_limited_steps_equal_the_plain_step_row_by_row() -> None:
    """Many problems, with joints at their limits (some pushed out, some not, one pinned with
    lower == upper): the compiled step of each, and the NumPy oracle's batch of all at once, are the
    plain limit-clamped WDLS step of each problem."""
    from oracles.hand import limited_steps

    rng = np.random.default_rng(5)
    B, m, n = 40, 9, 11
    J = rng.normal(size=(B, m, n)) * 0.05
    dx = rng.normal(size=(B, m)) * 1e-3
    lo, hi = -np.ones(n), np.ones(n)
    lo[4] = hi[4] = 0.2
    q = rng.uniform(-0.5, 0.5, size=(B, n))
    at = rng.random((B, n)) < 0.3
    q[at] = np.where(rng.random(at.sum()) < 0.5, -1.0, 1.0)
    q[:, 4] = 0.2
    w = rng.uniform(0.5, 2.0, size=n)
    for damping in (1e-3, 0.0):
        dq = limited_steps(J, dx, q, lo, hi, 1.0 / w, damping)
        assert dq.shape == (B, n)
        for b in range(B):
            ref = _limited_step_reference(J[b], dx[b], q[b], lo, hi, w, damping)
            np.testing.assert_allclose(dq[b], ref, rtol=1e-9, atol=1e-15)
            one = limited_step(J[b], dx[b], q[b], lo, hi, 1.0 / w, damping, LIMIT_EPS)[0]
            np.testing.assert_allclose(one, ref, rtol=1e-9, atol=1e-15)
            assert one[4] == 0.0
        assert np.all(dq[:, 4] == 0.0)


@pytest.mark.parametrize(
    ("finger", "q_star"),
    [
        ("first", [-20.0, 90.0, 30.0]),  # J4 and J3 at limits
        ("middle", [20.0, 10.0, 90.0]),  # J4 and J2 (so also J1) at their upper limits
        ("thumb", [30.0, 70.0, -12.0, 10.0, 0.0]),  # TH4, TH3 and TH1 at limits
    ],
)
def test_solve_ik_targets_needing_joints_at_limits(finger: str, q_star: list[float]) -> None:
    target = MODEL.forward(finger, np.array(q_star) * DEG)
    lo, hi = MODEL.limits(finger)
    for q0 in (np.zeros(lo.size), 0.5 * (lo + hi), hi):
        q = solve_ik(MODEL, finger, target, q0)
        assert in_limits(finger, q)
        assert np.linalg.norm(MODEL.forward(finger, q) - target) <= 1e-5


def test_solve_ik_clips_start_outside_limits_and_respects_weights() -> None:
    target = MODEL.forward("thumb", np.array([20.0, 40.0, 5.0, 10.0, 45.0]) * DEG)
    q = solve_ik(MODEL, "thumb", target, np.full(5, 3.0), weights=[10.0, 1.0, 1.0, 1.0, 1.0])
    assert in_limits("thumb", q)
    assert np.linalg.norm(MODEL.forward("thumb", q) - target) <= 1e-5


@pytest.mark.parametrize("finger", FINGERS)
def test_solve_ik_unreachable_target_raises(finger: str) -> None:
    q0 = np.zeros(MODEL.fingers[finger].dof)
    target = MODEL.forward(finger, q0) + np.array([0.0, 0.3, 0.4])  # 0.5 m away
    with pytest.raises(InfeasibleGrasp, match=rf"the {finger} fingertip cannot reach .*closest \d+\.\d+ mm"):
        solve_ik(MODEL, finger, target, q0)


# ---------------------------------------------------------------------- Cartesian line following


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = b - a
    t = min(1.0, max(0.0, float((p - a) @ d / (d @ d))))
    return float(np.linalg.norm(p - (a + t * d)))


@pytest.mark.parametrize(
    ("finger", "q0", "move"),
    [
        ("first", [0.0, 1.0, 0.6], [0.0, 0.0, -0.02]),  # towards the palm
        ("first", [0.0, 1.0, 0.6], [0.0, 0.02, 0.0]),  # along the fingers
        ("middle", [0.1, 1.2, 0.5], [0.0, -0.012, -0.016]),
    ],
)
def test_follow_line_stays_on_the_line(finger: str, q0: list[float], move: list[float]) -> None:
    start = MODEL.forward(finger, q0)
    assert start[2] > 0.05  # in front of the palm
    end = start + np.array(move)
    traj = follow_line(MODEL, finger, q0, start, end, 20)
    assert traj.shape == (21, 3)
    np.testing.assert_allclose(traj[0], q0)
    tips = np.array([MODEL.forward(finger, q) for q in traj])
    assert max(_distance_to_segment(p, start, end) for p in tips) <= 5e-4
    assert np.linalg.norm(tips[-1] - end) <= 5e-4
    assert all(in_limits(finger, q) for q in traj)
    # the tip progresses monotonically along the line
    s = (tips - start) @ (end - start) / float((end - start) @ (end - start))
    assert np.all(np.diff(s) > 0.0)


def test_follow_line_out_of_the_workspace_raises() -> None:
    q0 = [0.0, 1.0, 0.6]
    start = MODEL.forward("first", q0)
    with pytest.raises(InfeasibleGrasp, match="the first fingertip cannot follow the line"):
        follow_line(MODEL, "first", q0, start, start + np.array([0.0, 0.0, 0.1]), 20)
    with pytest.raises(ConfigError, match="steps"):
        follow_line(MODEL, "first", q0, start, start, 0)


# ---------------------------------------------------------------------- opposition


@pytest.mark.parametrize(
    ("finger", "point"),
    # 60 mm in front of the palm over the finger's column (the J1 = J2 coupling puts a finger's
    # reach at 60 mm height between ~66 and ~114 mm from the wrist, over its own column)
    [("first", [0.033, 0.085, 0.060]), ("middle", [0.011, 0.090, 0.060])],
)
def test_thumb_opposes_finger(finger: str, point: list[float]) -> None:
    target = np.array(point)
    q_th = solve_ik(MODEL, "thumb", target, np.zeros(5))
    q_f = solve_ik(MODEL, finger, target, np.zeros(3))
    tip_th, tip_f = MODEL.forward("thumb", q_th), MODEL.forward(finger, q_f)
    assert np.linalg.norm(tip_th - target) <= 1e-5
    assert np.linalg.norm(tip_f - target) <= 1e-5
    assert np.linalg.norm(tip_th - tip_f) <= 2e-5
    assert in_limits("thumb", q_th) and in_limits(finger, q_f)
    # an opposed thumb, not one lying in the palm plane
    assert q_th[1] > 0.3  # lifted off the palm (TH4)


# ---------------------------------------------------------------------- batched kinematics


def _check_stack(model: HandModel, fingers: tuple[str, ...], seed: int) -> None:
    """Every finger at several configurations at once, in posed palm frames: the stacked fingertips,
    Jacobians and joint origins are those of each finger alone, moved into the frame, and those of
    the NumPy oracle."""
    from oracles.hand import stack_kinematics as numpy_kinematics
    from softgrasp.hand.kinematics import chain_stack, stack_kinematics
    from softgrasp.hand.placement import transform

    rng = np.random.default_rng(seed)
    chains = tuple(model.chain(f) for f in fingers)
    stack = chain_stack(chains)
    assert chain_stack(chains) is stack  # cached
    B = 6
    q = np.array([np.concatenate([rng.uniform(*model.limits(f)) for f in fingers]) for _ in range(B)])
    poses = [_pose(list(rng.normal(size=3)), list(0.1 * rng.normal(size=3))) for _ in range(B)]
    R = np.array([T[:3, :3] for T in poses])
    p = np.array([T[:3, 3] for T in poses])
    k = stack_kinematics(stack, q, R, p, jacobian=True, origins=True)
    k0 = stack_kinematics(stack, q)  # palm frame, fingertips only
    assert k.jacobian is not None and k.origins is not None
    assert k.tips.shape == (B, len(fingers), 3) and k.jacobian.shape == (B, len(fingers), 3, stack.n)
    ref = numpy_kinematics(stack, q, R, p, jacobian=True, origins=True)
    assert ref.jacobian is not None and ref.origins is not None
    np.testing.assert_allclose(k.tips, ref.tips, atol=1e-14)
    np.testing.assert_allclose(k.jacobian, ref.jacobian, atol=1e-14)
    np.testing.assert_allclose(k.origins, ref.origins, atol=1e-14)
    np.testing.assert_allclose(k0.tips, numpy_kinematics(stack, q).tips, atol=1e-14)
    for b in range(B):
        for c, (f, chain) in enumerate(zip(fingers, chains, strict=True)):
            qf = q[b, stack.starts[c] : stack.starts[c] + chain.dof]
            tip = model.forward(f, qf)
            np.testing.assert_allclose(k0.tips[b, c], tip, atol=1e-14)
            np.testing.assert_allclose(k.tips[b, c], transform(poses[b], tip), atol=1e-14)
            J = np.zeros((3, stack.n))
            J[:, stack.starts[c] : stack.starts[c] + chain.dof] = R[b] @ model.jacobian(f, qf)
            np.testing.assert_allclose(k.jacobian[b, c], J, atol=1e-14)
            L = len(chain.joints)
            pts = transform(poses[b], model.link_points(f, qf))
            np.testing.assert_allclose(k.origins[b, c, :L], pts[:-1], atol=1e-14)
            np.testing.assert_allclose(
                k.origins[b, c, L:], np.broadcast_to(pts[-1], k.origins[b, c, L:].shape)
            )
    # the stacked Jacobian is the derivative of the stacked fingertips
    h = 1e-6
    for i in range(stack.n):
        e = np.zeros(stack.n)
        e[i] = h
        fd = (stack_kinematics(stack, q + e, R, p).tips - stack_kinematics(stack, q - e, R, p).tips) / (2 * h)
        np.testing.assert_allclose(k.jacobian[..., i], fd, atol=1e-8)


def test_stacked_kinematics_of_the_hand_equal_each_finger_alone() -> None:
    """Fingers of different lengths (the thumb has one joint more: the others are padded)."""
    _check_stack(MODEL, FINGERS, 3)
    _check_stack(MODEL, ("middle", "thumb"), 4)


# ---------------------------------------------------------------------- URDF reader

LINK = '<link name="{0}"/>'
TIP = '<link name="{0}"><collision><geometry><sphere radius="0.01"/></geometry></collision></link>'


def _joint(name: str, parent: str, child: str, body: str = "", kind: str = "revolute") -> str:
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>{body}</joint>'
    )


LIM = '<limit lower="-1" upper="1"/>'


def _write(tmp_path: Path, *parts: str) -> Path:
    path = tmp_path / "hand.urdf"
    path.write_text('<?xml version="1.0"?>\n<robot name="t">' + "".join(parts) + "</robot>")
    return path


def test_small_urdf_prismatic_rpy_and_scaled_mimic(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        LINK.format("palm"),
        LINK.format("a"),
        LINK.format("b"),
        LINK.format("c"),
        TIP.format("xx_tip"),
        _joint(
            "S",
            "palm",
            "a",
            '<origin xyz="0.1 0 0" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/>'
            '<limit lower="0" upper="0.05"/>',
            "prismatic",
        ),
        _joint("R1", "a", "b", '<axis xyz="0 0 1"/><limit lower="-1" upper="1"/>'),
        _joint(
            "R2",
            "b",
            "c",
            '<origin xyz="0.02 0 0"/><axis xyz="0 0 1"/><limit lower="0" upper="1"/>'
            '<mimic joint="R1" multiplier="2" offset="0"/>',
        ),
        _joint("T", "c", "xx_tip", '<origin xyz="0.03 0 0"/>', "fixed"),
    )
    model = HandModel.from_urdf(path)
    assert list(model.fingers) == ["xx"]
    assert model.fingertip_radius("xx") == 0.01
    assert model.joint_names("xx") == ("S", "R1")
    lo, hi = model.limits("xx")
    np.testing.assert_allclose(lo, [0.0, 0.0])  # R2 = 2 R1 in [0, 1]  ->  R1 in [0, 0.5]
    np.testing.assert_allclose(hi, [0.05, 0.5])
    # yaw 90 deg: the frame's x is the palm's y; slide 0.04 along it, then R1 = t, R2 = 2 t
    t = 0.3
    tip = model.forward("xx", [0.04, t])
    base = np.array([0.1, 0.04, 0.0])
    expected = (
        base
        + 0.02 * np.array([-math.sin(t), math.cos(t), 0])
        + 0.03 * np.array([-math.sin(3 * t), math.cos(3 * t), 0])
    )
    np.testing.assert_allclose(tip, expected, atol=1e-12)
    J = model.jacobian("xx", [0.04, t])
    np.testing.assert_allclose(J[:, 0], [0.0, 1.0, 0.0], atol=1e-12)
    dt = 1e-6
    fd = (model.forward("xx", [0.04, t + dt]) - model.forward("xx", [0.04, t - dt])) / (2 * dt)
    np.testing.assert_allclose(J[:, 1], fd, atol=1e-8)
    # the same chain twice in a stack (a prismatic joint, a scaled mimic, an rpy origin)
    _check_stack(model, ("xx", "xx"), 6)


@pytest.mark.parametrize(
    ("parts", "message"),
    [
        (None, "does not exist"),
        (("<robot><link name='palm'>",), "not well-formed XML"),
        (
            (LINK.format("palm"), TIP.format("ff_tip"), _joint("J", "palm", "ff_tip", '<axis xyz="1 0 0"/>')),
            "joint 'J' has no <limit",
        ),
        (
            (LINK.format("palm"), LINK.format("ff_distal"), _joint("J", "palm", "ff_distal", LIM)),
            "chain ending at link 'ff_distal' has no fingertip link",
        ),
        (
            (
                LINK.format("palm"),
                LINK.format("a"),
                TIP.format("ff_tip"),
                _joint("J2", "palm", "a", LIM),
                _joint("J1", "a", "ff_tip", LIM + '<mimic joint="J9"/>'),
            ),
            "joint 'J1' mimics unknown joint 'J9'",
        ),
        (
            (LINK.format("palm"), LINK.format("ff_tip"), _joint("J", "palm", "ff_tip", LIM)),
            "has no collision sphere giving the fingertip radius; add a sphere to it or give the radius",
        ),
        (
            (LINK.format("palm"), TIP.format("ff_tip"), _joint("J", "palm", "ff_tip", LIM, "continuous")),
            "type 'continuous'",
        ),
        (
            (LINK.format("palm"), TIP.format("ff_tip"), _joint("J", "palm", "nowhere", LIM)),
            "unknown child link 'nowhere'",
        ),
    ],
)
def test_malformed_urdf_raises_config_error(
    tmp_path: Path, parts: tuple[str, ...] | None, message: str
) -> None:
    if parts is None:
        path = tmp_path / "missing.urdf"
    elif parts[0].startswith("<robot>"):
        path = tmp_path / "bad.urdf"
        path.write_text(parts[0])
    else:
        path = _write(tmp_path, *parts)
    with pytest.raises(ConfigError, match=message):
        HandModel.from_urdf(path)


# ---------------------------------------------------------------------- palm placement


def _pose(rotvec: list[float], origin: list[float]) -> np.ndarray:
    from softgrasp.hand.placement import _rotation

    T = np.eye(4)
    T[:3, :3] = _rotation(np.asarray(rotvec, dtype=float))
    T[:3, 3] = origin
    return T


def _known_targets() -> dict[str, np.ndarray]:
    """Fingertip targets made by forward kinematics from a palm pose and joint angles (a grasp from
    above) that the placement does not see."""
    from softgrasp.hand.placement import transform

    pose = _pose([2.8, 0.3, 0.2], [0.05, -0.02, 0.18])
    q = {
        "thumb": np.array([0.5, 0.7, 0.0, 0.1, 0.4]),
        "first": np.array([0.05, 0.6, 0.5]),
        "middle": np.array([-0.05, 0.6, 0.5]),
    }
    return {f: transform(pose, MODEL.forward(f, q[f])) for f in FINGERS}


def test_link_points_start_at_the_knuckle_and_end_at_the_fingertip() -> None:
    q = np.array([0.1, 0.4, 0.3])
    pts = MODEL.link_points("first", q)
    np.testing.assert_allclose(pts[0], KNUCKLE["first"], atol=1e-12)
    np.testing.assert_allclose(pts[-1], MODEL.forward("first", q), atol=1e-12)
    # Consecutive distinct points are the segment lengths of the finger.
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    np.testing.assert_allclose(np.sort(steps[steps > 1e-12]), sorted([PROXIMAL, MIDDLE, DISTAL]), atol=1e-12)


def test_place_hand_finds_a_posture_for_targets_of_a_known_posture() -> None:
    """Targets made by forward kinematics from a palm pose and joint angles softgrasp does not see:
    the placement reaches every one (to 10 um) within the joint limits. The posture found may
    differ (the problem has 19 unknowns for 9 equations), the fingertips may not."""
    from softgrasp.hand.placement import REACH_TOL, place_hand

    targets = _known_targets()
    pl = place_hand(MODEL, targets)
    for f in FINGERS:
        assert in_limits(f, pl.q[f])
        assert np.linalg.norm(pl.fingertip(MODEL, f) - targets[f]) <= REACH_TOL
    R = pl.palm_pose[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_place_hand_names_the_finger_that_cannot_reach() -> None:
    from softgrasp.hand.placement import place_hand

    targets = {"thumb": [0.0, 0.0, 0.1], "first": [0.05, 0.05, 0.1], "middle": [0.03, 0.6, 0.1]}
    with pytest.raises(
        InfeasibleGrasp,
        match=r"the (middle|first|thumb) fingertip cannot reach its initial contact: [0-9.]+ mm away",
    ):
        place_hand(MODEL, targets)


def test_place_hand_keeps_the_palm_out_of_the_object() -> None:
    """The same targets, once free and once inside a large block that the hand cannot reach into
    without putting its palm or joints inside: the second is refused with that reason."""
    from softgrasp.hand.placement import place_hand

    targets = _known_targets()
    centre = np.mean(list(targets.values()), axis=0)
    block = centre + 0.4 * (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T)
    with pytest.raises(InfeasibleGrasp, match="inside the object"):
        place_hand(MODEL, targets, obstacle=block)


def test_the_obstacle_hull_kept_between_placements_is_the_current_obstacles() -> None:
    """place_hand keeps the last obstacle's hull: two obstacles in turn each get their own (the
    same facet planes as a fresh hull), and the block that refuses a placement still refuses it
    after another obstacle's hull was kept."""
    from scipy.spatial import ConvexHull

    from softgrasp.hand.placement import _hull_equations, place_hand

    rng = np.random.default_rng(3)
    a, b = rng.standard_normal((40, 3)), 2.0 + rng.standard_normal((50, 3))
    for pts in (a, b, a, a.copy(), b):
        assert np.array_equal(_hull_equations(pts), ConvexHull(pts).equations)
    targets = _known_targets()
    centre = np.mean(list(targets.values()), axis=0)
    block = centre + 0.4 * (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T)
    far = block + 10.0
    place_hand(MODEL, targets, obstacle=far)  # clear of the hand
    with pytest.raises(InfeasibleGrasp, match="inside the object"):
        place_hand(MODEL, targets, obstacle=block)
    place_hand(MODEL, targets, obstacle=far)


# Placements of a known-posture grasp and of the sphere grasp, rows 0-2 of the palm pose and the
# joint vectors: the placement must find these.
PINNED = {
    "known": (
        [
            [0.9489403410562461, -0.2998529979256229, -0.09798167558820102, 0.13573904447022],
            [-0.2999531164474714, -0.9538503770788324, 0.014056531578559538, -0.019514692306500478],
            [-0.09767475134088852, 0.01605109907719988, -0.9950889433457238, 0.22415585040979052],
        ],
        {
            "thumb": [
                0.3996535786614061,
                0.8295476871924065,
                0.06807477566283729,
                0.16440181954898675,
                1.0560068047275677,
            ],
            "first": [-0.020290779948393525, 0.3595057431030076, 0.6921712592231357],
            "middle": [-0.17408558856709774, 0.4399025359306195, 0.498195207029718],
        },
    ),
    "sphere": (
        [
            [0.5743171991038175, -0.814675604106718, 0.08039536607852707, 0.06749877993721741],
            [0.8137704578062184, 0.557458320853751, -0.16437111216017866, -0.1040267507891533],
            [0.08909206931822826, 0.15982453060863466, 0.9831168407673248, -0.042352214175506234],
        ],
        {
            "thumb": [
                -0.12969365187650642,
                0.6138752651311774,
                0.0012218390811899538,
                -0.09608035035830363,
                0.8053723344621796,
            ],
            "first": [-0.18629546601291544, 0.41590122489606374, 0.19474693290263612],
            "middle": [0.014327701812999133, 0.2703580280816504, 0.7868223007175198],
        },
    ),
}


@pytest.mark.parametrize("case", sorted(PINNED))
def test_place_hand_finds_the_pinned_placement(case: str, sphere_grasp) -> None:
    from softgrasp.hand.placement import place_hand

    if case == "known":
        pl = place_hand(MODEL, _known_targets())
    else:
        targets, points = sphere_grasp
        pl = place_hand(MODEL, targets, obstacle=points)
    pose, q = PINNED[case]
    np.testing.assert_allclose(pl.palm_pose[:3], pose, atol=1e-9)
    np.testing.assert_array_equal(pl.palm_pose[3], [0.0, 0.0, 0.0, 1.0])
    for f in FINGERS:
        np.testing.assert_allclose(pl.q[f], q[f], atol=1e-9)


def test_each_start_of_the_batched_placement_iterates_on_its_own(sphere_grasp) -> None:
    """The starting postures of the NumPy oracle advance together only to share NumPy calls, and the
    compiled solve takes them one after the other: solving them all at once or one by one gives the
    same end postures (including the ones that stall or get stuck)."""
    from oracles.hand import solve as _solve_numpy
    from softgrasp.hand.kinematics import chain_stack
    from softgrasp.hand.placement import _seeds, _solve

    targets = dict(sphere_grasp[0])
    targets["middle"] = targets["middle"] + np.array([0.0, 0.0, 0.05])  # some starts cannot reach it
    T = np.array([targets[f] for f in FINGERS])
    stack = chain_stack(tuple(MODEL.chain(f) for f in FINGERS))
    seeds = _seeds(MODEL, FINGERS, T, np.array([0.0, 0.0, 1.0]))
    poses = np.array([pose for pose, _ in seeds])
    q0 = np.array([np.concatenate([q[f] for f in FINGERS]) for _, q in seeds])
    for solve in (_solve_numpy, _solve):
        together = solve(stack, T, poses[:, :3, :3], poses[:, :3, 3], q0)
        for s in range(len(seeds)):
            alone = solve(stack, T, poses[s : s + 1, :3, :3], poses[s : s + 1, :3, 3], q0[s : s + 1])
            for a, b in zip(together, alone, strict=True):
                np.testing.assert_allclose(a[s], b[0], rtol=0, atol=1e-12)


def test_closing_paths_move_fingertips_along_their_lines() -> None:
    from softgrasp.hand.placement import closing_paths, place_hand, transform

    targets = _known_targets()
    pl = place_hand(MODEL, targets)
    centroid = np.mean(list(targets.values()), axis=0)
    lines = {
        f: (targets[f], targets[f] + 0.01 * (centroid - targets[f]) / np.linalg.norm(centroid - targets[f]))
        for f in FINGERS
    }
    paths = closing_paths(MODEL, pl, lines, 10)
    for f, (a, b) in lines.items():
        assert paths[f].shape == (11, MODEL.chain(f).dof)
        for k, qk in enumerate(paths[f]):
            assert in_limits(f, qk)
            tip = transform(pl.palm_pose, MODEL.forward(f, qk))
            assert np.linalg.norm(tip - (a + k / 10 * (b - a))) < 1e-6
