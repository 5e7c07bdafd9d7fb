"""The pictures of ``softgrasp execute``: MuJoCo's offscreen renderings of the executed scene from
one camera per run, titled by the event and the run's outcome; matplotlib's drawings, with a
warning naming the packages to install, where no renderer can be made; the choice of MuJoCo's
OpenGL back-end before it is imported."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from softgrasp.api.execution import execute  # noqa: E402
from softgrasp.cli import main  # noqa: E402
from softgrasp.errors import SoftgraspWarning  # noqa: E402
from softgrasp.execution.mujoco.render import FRAME_HEIGHT, FRAME_WIDTH, GL_PACKAGES, frame_camera  # noqa: E402
from softgrasp.offscreen import GL_BACKEND, prefer_headless_gl  # noqa: E402
from softgrasp.viz.execution_plots import TITLE_BAND, execution_frame_title  # noqa: E402

EVENTS = ("start", "contact", "closed", "end")
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def plan_json(tmp_path_factory) -> Path:
    """A coarse plan of the default sphere (~8 s)."""
    out = tmp_path_factory.mktemp("pictures-plan")
    argv = ["plan", "--mesh-size", "0.025", "--step", "0.001", "--hold-time", "0.2", "--out", str(out)]
    assert main(argv) == 0
    return out / "plan.json"


@pytest.fixture(scope="module")
def slick(tmp_path_factory) -> Path:
    """Fingertip friction 0.1 where the plan took 0.8: the set-points cannot hold the sphere."""
    path = tmp_path_factory.mktemp("pictures-material") / "slick.toml"
    path.write_text("[contact]\nmu = 0.1\n")
    return path


@pytest.fixture(scope="module")
def dropped(plan_json, slick, tmp_path_factory):
    """The plan executed on a slick sphere that drops (a 10 mm lift), its files written (~9 s)."""
    run = execute(plan_json, lift_m=0.01, material=str(slick))
    out = tmp_path_factory.mktemp("pictures-run")
    names = run.save(out)
    return run, out, names


def _read(path: Path) -> np.ndarray:
    from matplotlib.image import imread

    assert path.read_bytes()[:8] == PNG
    img = imread(path)
    return np.asarray(img[..., :3] * 255, dtype=np.float64)  # RGB in 0..255


def _object_mask(scene: np.ndarray) -> np.ndarray:
    """The red flex's pixels (the table is grey-brown, the sky grey-blue, the hand beige)."""
    r, g, b = scene[..., 0], scene[..., 1], scene[..., 2]
    return (r > 120) & (r > 1.6 * g) & (r > 1.6 * b)


def test_the_pictures_are_mujocos_renderings_from_one_camera(dropped):
    run, out, names = dropped
    assert run.dropped and not run.lifted
    assert names == [f"frame_{e}.png" for e in EVENTS]
    assert set(run.images) == set(EVENTS) and run.frames == {}
    pictures = [_read(out / n) for n in names]
    for img in pictures:  # the rendering unscaled under its title band
        assert img.shape == (FRAME_HEIGHT + TITLE_BAND, FRAME_WIDTH, 3)
    scenes = [img[TITLE_BAND:] for img in pictures]
    for scene in scenes:
        assert scene.std() > 20.0  # not blank, not black
        assert scene.mean() > 60.0
        assert _object_mask(scene).sum() > 0.03 * FRAME_WIDTH * FRAME_HEIGHT  # the sphere is in view
    # one fixed camera: the sky in the top left corner is the same in every picture
    corner = [s[:40, :40] for s in scenes]
    for c in corner[1:]:
        assert np.abs(c - corner[0]).max() <= 2.0
    # the object's pixels change as the hand squeezes it and as it slips out
    start = scenes[0]
    for later in (scenes[2], scenes[3]):
        region = _object_mask(start) | _object_mask(later)
        changed = np.abs(later - start).max(axis=2) > 12.0
        assert (changed & region).sum() > 200


def test_the_titles_say_the_run_dropped(dropped):
    run, out, _ = dropped
    res = run.result
    titles = {
        e: execution_frame_title(
            e, run.event_times[e], reached=res.reached, lifted=res.lifted, rise_m=res.rise, lift_m=0.01
        )
        for e in EVENTS
    }
    assert titles["end"].startswith("dropped (t = ")
    for title in titles.values():
        assert "run: dropped" in title and "lifted" not in title
    band = _read(out / "frame_end.png")[:TITLE_BAND]
    assert band.min() < 80.0 and np.median(band) > 240.0  # dark text on the white band


def test_a_held_run_is_titled_lifted():
    title = execution_frame_title("end", 4.68, reached=True, lifted=True, rise_m=0.0987, lift_m=0.1)
    assert title == (
        "lifted and held (t = 4.68 s, MuJoCo)\nrun: lifted, rose 98.7 of 100 mm; set-points reached"
    )
    short = execution_frame_title("closed", 6.3, reached=False, lifted=False, rise_m=-1e-5, lift_m=0.1)
    assert short.startswith("closing ended short of the set-points (t = 6.30 s")
    assert "rose 0.0 of 100 mm; set-points not reached" in short


def test_without_a_renderer_matplotlib_draws_the_pictures_and_says_what_to_install(
    plan_json, slick, tmp_path
):
    def no_gl(model, height, width):
        raise RuntimeError("cannot make an OpenGL context")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run = execute(plan_json, lift_m=0.01, material=str(slick), renderer=no_gl)
    said = [str(w.message) for w in caught if issubclass(w.category, SoftgraspWarning)]
    assert len(said) == 1 and "\n" not in said[0]
    assert "cannot make an OpenGL context" in said[0]
    assert all(p in said[0] for p in GL_PACKAGES) and "matplotlib" in said[0]
    assert run.images == {} and set(run.frames) == set(EVENTS)
    names = run.save(tmp_path)
    assert names == [f"frame_{e}.png" for e in EVENTS]
    for n in names:
        img = _read(tmp_path / n)
        assert img.shape[:2] != (FRAME_HEIGHT + TITLE_BAND, FRAME_WIDTH)  # matplotlib's figure
        assert img.std() > 20.0


def test_the_command_line_gives_the_fallback_in_one_line(plan_json, slick, tmp_path, monkeypatch, capsys):
    import mujoco

    def no_gl(model, height, width):
        raise RuntimeError("no EGL display")

    monkeypatch.setattr(mujoco, "Renderer", no_gl)
    argv = ["execute", str(plan_json), "--material", str(slick), "--lift", "0.01", "--out", str(tmp_path)]
    assert main(argv) == 1  # dropped
    err = capsys.readouterr().err.splitlines()
    said = [line for line in err if line.startswith("softgrasp: warning: ")]
    assert len(said) == 1 and "no EGL display" in said[0] and "libegl-mesa0" in said[0]
    assert not any("Warning" in line or "warnings.warn" in line for line in err)
    assert (tmp_path / "frame_end.png").read_bytes()[:8] == PNG


def _projected(cam, points: np.ndarray, aspect: float, fovy_deg: float = 45.0) -> np.ndarray:
    """Points in the picture of MuJoCo's free camera ``cam``, in [-1, 1] across each side."""
    az, el = math.radians(cam.azimuth), math.radians(cam.elevation)
    forward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    eye = cam.lookat - cam.distance * forward
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    v = points - eye
    depth = v @ forward
    assert np.all(depth > 0)
    t = math.tan(math.radians(0.5 * fovy_deg))
    return np.column_stack([(v @ right) / depth / (t * aspect), (v @ up) / depth / t])


@pytest.mark.parametrize("lift", [0.0, 0.1, 0.3])
@pytest.mark.parametrize("radius", [0.02, 0.064, 0.15])
def test_the_camera_shows_the_object_the_hand_and_the_lift(radius, lift):
    rng = np.random.default_rng(3)
    d = rng.normal(size=(400, 3))
    centre = np.array([0.01, -0.02, radius])
    points = centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)
    r = radius + 0.008
    tips = centre + np.array([[r, 0.0, 0.0], [-r, 0.03, 0.0], [-r, -0.03, 0.0]])
    hand = centre + np.array([[0.0, 0.0, radius + 0.08], [0.05, 0.02, radius + 0.06]])
    cam = frame_camera(points, tips, hand, lift, light_dir=np.array([-0.3, 0.3, -1.0]))
    shown = np.vstack([points, tips, hand])
    for rise in (0.0, lift):
        xy = _projected(cam, shown + [0.0, 0.0, rise], FRAME_WIDTH / FRAME_HEIGHT)
        assert np.all(np.abs(xy) <= 1.0)
        assert np.abs(xy).max() > 0.3  # and not lost in the distance
    # it looks across the line from the thumb to the other fingers (along y here), from the side
    # the light comes from (the light travels towards +y)
    assert cam.azimuth == pytest.approx(90.0)


def test_mujoco_renders_offscreen_unless_the_user_chose_otherwise():
    env: dict[str, str] = {}
    assert prefer_headless_gl(env, modules=set(), platform="linux")
    assert env == {"MUJOCO_GL": GL_BACKEND}
    mine = {"MUJOCO_GL": "osmesa"}
    assert not prefer_headless_gl(mine, modules=set(), platform="linux")
    assert mine == {"MUJOCO_GL": "osmesa"}
    late: dict[str, str] = {}  # MuJoCo read the variable when it was imported: too late
    assert not prefer_headless_gl(late, modules={"mujoco"}, platform="linux") and late == {}
    mac: dict[str, str] = {}  # MuJoCo refuses egl outside Linux
    assert not prefer_headless_gl(mac, modules=set(), platform="darwin") and mac == {}
