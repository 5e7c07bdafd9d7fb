"""Other hands: any URDF with a fingertip mapping (read through yourdfpy), MJCF hands (through
MuJoCo's parser), the fingertip radius from the links' spheres, layout limits from the hand or a
config file, and the packaged parallel-jaw gripper planned with two opposed soft-finger contacts."""

from __future__ import annotations

import json
import math
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

import softgrasp as sg
from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.grasp.closure import ferrari_canny_bounds, primitive_wrenches_many, wrench_epsilon
from softgrasp.grasp.equilibrium import squeeze_utilisation
from softgrasp.grasp.initial import HandLayout, ranked_grasps
from softgrasp.hand.kinematics import HandModel
from softgrasp.io.options import hand_model

DATA = Path(__file__).parent / "data"
MJCF = DATA / "three_finger_hand.xml"
MJCF_TIPS = {"thumb": "th_distal", "first": "ff_distal", "middle": "mf_distal"}
DEFAULT = HandModel.default()
FINGERS = ("thumb", "first", "middle")


def _renamed_urdf(tmp_path: Path, radius: str | None = "0.008", offset: str = "0 0 0") -> Path:
    """The packaged Shadow-like URDF with its fingertip links renamed (``thumb_end``, ...) and
    their spheres of ``radius`` (None: no sphere) centred at ``offset`` in the link frame."""
    text = resources.files("softgrasp.hand").joinpath("shadow_like.urdf").read_text(encoding="utf-8")
    for old, new in (("th_tip", "thumb_end"), ("ff_tip", "index_end"), ("mf_tip", "middle_end")):
        text = text.replace(f'"{old}"', f'"{new}"')
    sphere = '<origin xyz="0 0 0" rpy="0 0 0"/>\n      <geometry><sphere radius="0.008"/></geometry>'
    assert text.count(sphere) == 3
    if radius is None:
        text = text.replace(sphere, "").replace("<collision>\n      \n    </collision>", "")
    else:
        text = text.replace(
            sphere,
            f'<origin xyz="{offset}" rpy="0 0 0"/>\n      <geometry><sphere radius="{radius}"/></geometry>',
        )
    path = tmp_path / "renamed.urdf"
    path.write_text(text, encoding="utf-8")
    return path


TIPS = {"thumb": "thumb_end", "first": "index_end", "middle": "middle_end"}


def _same_kinematics(a: HandModel, b: HandModel, offset: np.ndarray | None = None) -> None:
    rng = np.random.default_rng(1)
    for f in FINGERS:
        assert a.joint_names(f) == b.joint_names(f)
        lo, hi = a.limits(f)
        np.testing.assert_allclose(b.limits(f), (lo, hi))
        for _ in range(4):
            q = lo + rng.random(lo.size) * (hi - lo)
            np.testing.assert_allclose(a.forward(f, q), b.forward(f, q), atol=1e-12)


# ---------------------------------------------------------------------- URDF with a mapping


def test_a_urdf_with_other_tip_names_loads_with_the_fingertip_mapping(tmp_path: Path) -> None:
    path = _renamed_urdf(tmp_path)
    with pytest.raises(ConfigError, match=r"has no fingertip link; .*map the fingertips \(--fingertips"):
        sg.load_hand(path)
    hand = sg.load_hand(path, fingertips=TIPS)
    assert hand is not None and hand.grasp_fingers == FINGERS
    assert dict(hand.fingertips) == TIPS and hand.fingertip_radius("thumb") == 0.008
    _same_kinematics(DEFAULT, hand)
    # the same mapping as command-line text
    text = sg.load_hand(path, fingertips="thumb=thumb_end, first=index_end,middle=middle_end")
    assert text is not None and dict(text.fingertips) == TIPS


def test_the_fingertip_radius_is_the_links_sphere_and_the_given_radius_overrides_it(tmp_path: Path) -> None:
    hand = sg.load_hand(_renamed_urdf(tmp_path, radius="0.011"), fingertips=TIPS)
    assert hand is not None and {hand.fingertip_radius(f) for f in FINGERS} == {0.011}
    over = sg.load_hand(_renamed_urdf(tmp_path, radius="0.011"), fingertips=TIPS, fingertip_radius_m=0.006)
    assert over is not None and {over.fingertip_radius(f) for f in FINGERS} == {0.006}


def test_a_fingertip_link_without_a_sphere_needs_the_radius(tmp_path: Path) -> None:
    path = _renamed_urdf(tmp_path, radius=None)
    with pytest.raises(
        ConfigError, match=r"fingertip link '\w+' \(\w+\) has no collision sphere.*--fingertip-radius"
    ):
        sg.load_hand(path, fingertips=TIPS)
    hand = sg.load_hand(path, fingertips=TIPS, fingertip_radius_m=0.009)
    assert hand is not None and hand.fingertip_radius("middle") == 0.009
    _same_kinematics(DEFAULT, hand)  # the link origin is then the fingertip centre


def test_a_sphere_off_the_link_origin_moves_the_fingertip_centre(tmp_path: Path) -> None:
    hand = sg.load_hand(_renamed_urdf(tmp_path, offset="0 0.002 0"), fingertips=TIPS)
    assert hand is not None
    q = 0.5 * np.add(*DEFAULT.limits("first"))
    d = hand.forward("first", q) - DEFAULT.forward("first", q)
    assert math.isclose(float(np.linalg.norm(d)), 0.002, rel_tol=1e-9)


@pytest.mark.parametrize(
    ("fingertips", "message"),
    [
        ("thumb=nowhere,first=index_end,middle=middle_end", r"--fingertips thumb=nowhere: .* has no link"),
        ("thumb", r"--fingertips entry 'thumb' is not FINGER=LINK"),
        ("thumb=thumb_end,thumb=index_end", "names finger 'thumb' twice"),
        ("ring=thumb_end,first=index_end", r"softgrasp plans with thumb, first and middle"),
    ],
)
def test_bad_fingertip_mappings_are_refused_with_the_fix(
    tmp_path: Path, fingertips: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        hand = hand_model(str(_renamed_urdf(tmp_path)), fingertips)
        hand.grasp_fingers  # noqa: B018 - the planner's fingers are asked for


def test_the_packaged_hand_takes_no_mapping() -> None:
    with pytest.raises(ConfigError, match="the packaged shadow_like has its own"):
        hand_model("shadow_like", "thumb=th_tip")


# ---------------------------------------------------------------------- MJCF


def test_an_mjcf_hand_has_the_kinematics_of_the_urdf_it_was_written_from() -> None:
    pytest.importorskip("mujoco")
    hand = sg.load_hand(MJCF, fingertips=MJCF_TIPS)
    assert hand is not None and hand.grasp_fingers == FINGERS
    assert {hand.fingertip_radius(f) for f in FINGERS} == {0.008}
    _same_kinematics(DEFAULT, hand)  # two joints a body, joint equalities, euler, offset spheres
    np.testing.assert_allclose(hand.jacobian("thumb", [0.1, 0.5, 0.0, 0.2, 0.4]),
                               DEFAULT.jacobian("thumb", [0.1, 0.5, 0.0, 0.2, 0.4]), atol=1e-12)


def test_a_malformed_mjcf_hand_is_a_config_error(tmp_path: Path) -> None:
    pytest.importorskip("mujoco")
    bad = tmp_path / "bad.xml"
    bad.write_text('<mujoco><worldbody><body name="palm"><joint name="j" type="hinge"/>'
                   '<geom type="sphere" size="0.01"/></body></worldbody></mujoco>')
    with pytest.raises(ConfigError, match=r"MJCF .*bad.xml: joint 'j' has no range"):
        sg.load_hand(bad, fingertips={"left": "palm", "right": "palm"})
    broken = tmp_path / "broken.xml"
    broken.write_text(
        '<mujoco><worldbody><body name="palm"><geom type="nosuch"/></body></worldbody></mujoco>'
    )
    with pytest.raises(ConfigError, match="MuJoCo cannot load it"):
        sg.load_hand(broken, fingertips=MJCF_TIPS)


@pytest.mark.slow
def test_an_mjcf_hand_plans_the_sphere_like_the_urdf_it_was_written_from(tmp_path: Path) -> None:
    pytest.importorskip("mujoco")
    from softgrasp.cli import main

    out = tmp_path / "plan"
    tips = ",".join(f"{k}={v}" for k, v in MJCF_TIPS.items())
    assert main(["plan", "--hand", str(MJCF), "--fingertips", tips, "--out", str(out)]) == 0
    doc = json.loads((out / "plan.json").read_text())
    assert doc["hand"]["fingertips"] == MJCF_TIPS
    assert sorted(doc["hand"]["fingers"]) == sorted(FINGERS)
    # the same kinematics and fingertips: the default plan's set-points
    ref = sg.plan("sphere").document["setpoints_N"]
    for f in FINGERS:
        assert math.isclose(doc["setpoints_N"][f], ref[f], rel_tol=1e-6)


# ---------------------------------------------------------------------- layout limits


def test_layout_limits_come_from_the_hand_and_a_config_file(tmp_path: Path) -> None:
    from softgrasp.grasp.config import PlanConfig
    from softgrasp.io.options import PLAN_DEFAULTS, plan_config
    from softgrasp.physics.fingertip.params import ContactParams

    assert PlanConfig().layout == HandLayout()  # the Shadow-like hand's: today's limits
    jaw = HandLayout.for_hand(HandModel.packaged("parallel_jaw"))
    assert (jaw.fingers, jaw.max_aperture) == (2, 0.085) and jaw.patch_radius == 0.25 * 0.008
    cfg = plan_config({**PLAN_DEFAULTS, "max_aperture": 0.12, "max_spread": 0.07}, ContactParams())
    assert (cfg.layout.max_aperture, cfg.layout.max_spread, cfg.layout.min_spread) == (0.12, 0.07, 0.02)
    with pytest.raises(ConfigError, match="min_spread < max_spread"):
        plan_config({**PLAN_DEFAULTS, "min_spread": 0.08, "max_spread": 0.05}, ContactParams())
    conf = tmp_path / "c.toml"
    conf.write_text("max_aperture = 0.9\n")
    from softgrasp.api.planning import plan_options

    with pytest.raises(ConfigError, match=r"max_aperture must be a number in \[0.001, 0.5\] m"):
        plan_options({}, conf)


# ---------------------------------------------------------------------- two fingers


def test_two_antipodal_point_contacts_are_force_closure_only_with_torsional_friction() -> None:
    p = np.array([[[0.0, -0.03, 0.0], [0.0, 0.03, 0.0]]])
    n = np.array([[[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]])  # inward
    assert wrench_epsilon(primitive_wrenches_many(p, n, 0.8, np.zeros(3))[0]) == 0.0
    w = primitive_wrenches_many(p, n, 0.8, np.zeros(3), torsion=0.002)
    assert w.shape == (1, 2 * 8 + 4, 6)
    eps = wrench_epsilon(w[0])
    assert eps > 0.0
    assert ferrari_canny_bounds(p, n, 0.8, np.zeros(3), torsion=0.002)[0] >= eps  # still an upper bound


def test_the_holding_lp_of_two_contacts_needs_their_patches_when_the_weight_twists_them() -> None:
    pts = np.array([[0.0, -0.03, 0.0], [0.0, 0.03, 0.0]])
    push = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    com = np.array([0.002, 0.0, 0.0])  # 2 mm beside the line through the contacts
    assert squeeze_utilisation(pts, push, [1.0, 1.0], 0.8, com, 0.01) == math.inf
    s = squeeze_utilisation(pts, push, [1.0, 1.0], 0.8, com, 0.01, torsion=[0.002, 0.002])
    assert 0.0 < s < 1.0
    # on the line the weight does not twist: point contacts suffice, and the patch changes nothing
    on = squeeze_utilisation(pts, push, [1.0, 1.0], 0.8, np.zeros(3), 0.01)
    assert math.isclose(on, 0.01 * 9.81 / (2 * 0.8), rel_tol=1e-6)


def test_two_finger_grasps_are_opposed_pairs_within_the_opening() -> None:
    obj = sg.load_object("cube")
    x, facets = obj.body.mesh.points, obj.body.mesh.facets
    com = x.mean(axis=0)
    layout = HandLayout.for_hand(HandModel.packaged("parallel_jaw"))
    g = next(ranked_grasps(x, facets, com, 0.8, layout))
    assert g.points.shape == (2, 3) and g.epsilon > 0
    assert float(g.normals[0] @ g.normals[1]) < -0.99  # opposite faces of the cube
    assert np.linalg.norm(g.points[0] - g.points[1]) <= 0.085
    narrow = HandLayout(max_aperture=0.04, fingers=2, patch_radius=0.002)
    with pytest.raises(InfeasibleGrasp, match=r"no opposed pair .* within its 40 mm opening"):
        next(ranked_grasps(x, facets, com, 0.8, narrow))


@pytest.mark.slow
@pytest.mark.parametrize(("source", "material"), [("cube", None), ("ball:0.03", "rubber")])
def test_the_parallel_jaw_gripper_plans_the_sphere_and_the_cube(
    tmp_path: Path, source: str, material: str | None
) -> None:
    obj = sg.load_object(source, material=material)
    result = sg.plan(obj, hand="parallel_jaw")
    doc = result.document
    assert [f["name"] for f in doc["fingers"]] == ["left", "right"]
    sp = doc["setpoints_N"]
    assert set(sp) == {"left", "right"}
    assert math.isclose(sp["left"], sp["right"], rel_tol=0.01)  # symmetric pads, a symmetric object
    mg = obj.body.total_mass * 9.81
    assert 2 * result.config.contact.mu * min(sp.values()) >= mg  # friction carries the weight
    lift = sum(float(f.force[2]) for f in result.grasp.fingers)
    assert math.isclose(lift, mg, rel_tol=1e-3)  # the pads' friction holds the weight up
    pose = result.grasp.placement.palm_pose
    assert pose[2, 3] > obj.body.mesh.points[:, 2].max()  # from above, clear of the table
    result.save(tmp_path / "run", figures=None)
    saved = json.loads((tmp_path / "run" / "plan.json").read_text())
    assert saved["hand"]["model"] == "package:softgrasp/hand/parallel_jaw.urdf"
