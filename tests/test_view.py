"""The `softgrasp view` page: a self-contained HTML file, checked as text and in a real headless browser."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from softgrasp.cli import main
from softgrasp.errors import ConfigError
from softgrasp.viz.view import _deformation, write_view

ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "src" / "softgrasp" / "viz" / "static"
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
BACKGROUND = (243, 244, 246)  # the page's canvas background, #f3f4f6


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """One small plan run (the default object, ~3 s), shared by every test here."""
    out = tmp_path_factory.mktemp("view") / "run"
    assert main(["plan", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def page(run_dir) -> Path:
    return write_view(run_dir)


def _embedded(html: str) -> dict:
    m = re.search(r'<script type="application/json" id="softgrasp-data">(.*?)</script>', html, re.S)
    assert m, "no embedded data"
    return json.loads(m.group(1))


def _octahedron_run(path: Path, names=("thumb", "first", "middle"), **override) -> Path:
    """A tiny synthetic frames.npz (an octahedron squeezed in two steps, free fingertips: no hand)."""
    nodes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * 0.02
    nodes[:, 2] += 0.02
    facets = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    )
    positions = np.stack([nodes, nodes * [0.99, 1, 1], nodes * [0.98, 1, 1.01]])
    centres = np.array([[[0.03, 0, 0.02], [-0.03, 0.01, 0.02], [-0.03, -0.01, 0.02]]] * 3)
    forces = np.array([np.zeros((3, 3)), [[-0.1, 0, 0], [0.05, 0, 0], [0.05, 0, 0]], [[-0.2, 0, 0.1]] * 3])
    arrays = dict(
        travel=np.array([0.0, 0.0005, 0.001]),
        positions=positions,
        centres=centres,
        forces=forces,
        held_positions=positions[-1],
        held_centres=centres[-1],
        held_forces=forces[-1],
        facets=facets,
        fingertip_radius=np.float64(0.008),
        finger_names=np.array(names),
        normal_forces=np.abs(forces[:, :, 0]),
        held_normal_forces=np.abs(forces[-1, :, 0]),
        hand_points=np.zeros((3, 0, 3)),
        held_hand_points=np.zeros((0, 3)),
        hand_lines=np.array([0]),
    )
    arrays.update(override)
    path.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path / "frames.npz", **arrays)
    return path


# --- the page as text ---------------------------------------------------------------------------


def test_page_is_self_contained_and_embeds_every_frame(run_dir, page):
    assert page == run_dir / "view.html"
    html = page.read_text(encoding="utf-8")
    assert html.startswith("<!DOCTYPE html>")
    # Nothing to fetch: no script/link/img sources; the one URL is an XML namespace inside three.js.
    assert not re.search(r"<(script|link|img|iframe)\b[^>]*\b(src|href)\s*=", html, re.I)
    assert set(re.findall(r"https?://[^\s\"'<>)]+", html)) <= {"http://www.w3.org/1999/xhtml"}
    assert (STATIC / "three.min.js").read_text(encoding="utf-8") in html
    assert '<input type="range" id="frame"' in html
    data = _embedded(html)
    assert data["format"] == "softgrasp.view/2"
    with np.load(run_dir / "frames.npz") as z:
        K = z["travel"].shape[0]
        facets, positions, held = z["facets"], z["positions"], z["held_positions"]
        names = [str(s) for s in z["finger_names"]]
        held_forces, normals, held_normals = z["held_forces"], z["normal_forces"], z["held_normal_forces"]
        hand, held_hand, lines = z["hand_points"], z["held_hand_points"], z["hand_lines"]
    assert len(data["frames"]) == K + 1
    assert [f["label"] for f in data["frames"]][-1] == "held"
    assert [f["held"] for f in data["frames"]] == [False] * K + [True]
    assert data["fingers"] == names
    np.testing.assert_allclose(data["frames"][-1]["forces"], held_forces, atol=1e-6)
    np.testing.assert_allclose([f["normals"] for f in data["frames"]], [*normals, held_normals], atol=1e-6)
    np.testing.assert_allclose(
        [f["hand"] for f in data["frames"]], [*hand.reshape(K, -1), held_hand.ravel()], atol=1e-6
    )
    assert data["hand_lines"] == lines.tolist()
    setpoints = json.loads((run_dir / "plan.json").read_text(encoding="utf-8"))["setpoints_N"]
    assert data["setpoints"] == pytest.approx([setpoints[n] for n in names], abs=1e-6)
    # The micrometre differences decode to the boundary nodes of every frame (within 1 um).
    used = np.unique(facets)
    assert data["nodes"] == used.size and len(data["tris"]) == facets.size
    pos = np.cumsum([f["pos"] for f in data["frames"]], axis=0).reshape(K + 1, -1, 3) * 1e-6
    np.testing.assert_allclose(pos[:K], positions[:, used], atol=0.6e-6, rtol=0)
    np.testing.assert_allclose(pos[K], held[used], atol=0.6e-6, rtol=0)
    # Deformation levels: none at the start, the largest 1000 somewhere.
    levels = np.array([f["deformation"] for f in data["frames"]])
    assert levels.shape == (K + 1, used.size) and levels[0].max() == 0 and levels.max() == 1000
    assert 0 < data["deformation_max_m"] < 0.01


def test_frames_carry_the_hand_and_the_normal_forces(run_dir):
    """The plan's frames.npz: a palm and three finger polylines in every frame, each finger ending at
    its fingertip's centre; the normal forces of the held state are plan.json's."""
    doc = json.loads((run_dir / "plan.json").read_text(encoding="utf-8"))
    with np.load(run_dir / "frames.npz") as z:
        K = z["travel"].shape[0]
        lines, hand, held_hand = z["hand_lines"], z["hand_points"], z["held_hand_points"]
        centres, held_centres = z["centres"], z["held_centres"]
        normals, held_normals = z["normal_forces"], z["held_normal_forces"]
    assert lines[0] == 0 and lines.size == 5 and np.all(np.diff(lines) >= 2)
    assert hand.shape == (K, lines[-1], 3) and held_hand.shape == (lines[-1], 3)
    ends = lines[2:] - 1  # the fingers' last points
    np.testing.assert_allclose(hand[:, ends], centres, atol=2e-5)
    np.testing.assert_allclose(held_hand[ends], held_centres, atol=2e-5)
    np.testing.assert_allclose(hand[:, 0], hand[:, lines[1] - 1])  # the palm outline is closed
    assert normals.shape == (K, 3) and np.all(normals[0] == 0) and np.all(normals[-1] > 0)
    np.testing.assert_allclose(held_normals, [f["normal_force_N"] for f in doc["fingers"]], rtol=1e-9)


def test_deformation_leaves_out_rigid_motion():
    rng = np.random.default_rng(3)
    start = rng.normal(size=(40, 3))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    moved = start @ R.T + [0.1, -0.2, 0.3]
    dented = moved.copy()
    dented[5] += [0.0, 0.0, 0.05]
    d = _deformation(start, np.stack([start, moved, dented]))
    assert d.shape == (3, 40)
    assert d[0].max() < 1e-12 and d[1].max() < 1e-12
    assert d[2].argmax() == 5 and 0.04 < d[2, 5] < 0.05 and np.delete(d[2], 5).max() < 0.01


def test_vendored_three_is_the_pinned_version():
    """three.min.js names the version that tools/three pins (package.json and its lock), carries the
    licence and can sit inside a <script> element."""
    lib = (STATIC / "three.min.js").read_text(encoding="utf-8")
    pinned = json.loads((ROOT / "tools" / "three" / "package.json").read_text())["dependencies"]["three"]
    lock = json.loads((ROOT / "tools" / "three" / "package-lock.json").read_text())
    assert lock["packages"]["node_modules/three"]["version"] == pinned
    assert lib.startswith(f"/* three.js {pinned} (npm three@{pinned}")
    assert "SPDX-License-Identifier: MIT" in lib and "OrbitControls" in lib
    assert "The MIT License" in (STATIC / "three.LICENSE").read_text(encoding="utf-8")
    assert "</script" not in lib.lower() and "<!--" not in lib


def test_custom_out_and_no_temporary_files(run_dir, tmp_path):
    out = write_view(run_dir, tmp_path / "sub" / "page.html")
    assert out == tmp_path / "sub" / "page.html" and out.stat().st_size > 1000
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]


def test_names_cannot_break_out_of_the_page(tmp_path):
    run = _octahedron_run(tmp_path / "run", names=("</script><b>x", "a&b", "c"))
    html = write_view(run).read_text(encoding="utf-8")
    assert html.count("</script>") == 3  # the data, three.js and the page script, nothing injected
    assert _embedded(html)["fingers"] == ["</script><b>x", "a&b", "c"]


def test_missing_run_dir(tmp_path):
    with pytest.raises(ConfigError, match=r"does not exist: run `softgrasp plan --out .*nope` first"):
        write_view(tmp_path / "nope")


def test_dir_without_frames(tmp_path):
    (tmp_path / "plan.json").write_text("{}")
    with pytest.raises(
        ConfigError, match=r"not a plan run \(no frames.npz\): run `softgrasp plan --out DIR`"
    ):
        write_view(tmp_path)
    assert not (tmp_path / "view.html").exists()


def test_corrupt_frames(tmp_path):
    (tmp_path / "frames.npz").write_bytes(b"PK\x03\x04 this is not a zip file")
    with pytest.raises(ConfigError, match=r"frames.npz is corrupt.*rerun `softgrasp plan --out"):
        write_view(tmp_path)


def test_frames_missing_arrays(tmp_path):
    np.savez(tmp_path / "frames.npz", travel=np.zeros(2))
    with pytest.raises(ConfigError, match=r"lacks the arrays positions, centres, .*rerun `softgrasp plan"):
        write_view(tmp_path)


def test_frames_inconsistent_arrays(tmp_path):
    run = _octahedron_run(tmp_path / "run", facets=np.array([[0, 1, 99]]))
    with pytest.raises(ConfigError, match=r"corrupt: facets index nodes outside 0\.\.5"):
        write_view(run)
    run = _octahedron_run(tmp_path / "run2", held_positions=np.zeros((4, 3)))
    with pytest.raises(ConfigError, match=r"held_positions has shape \(4, 3\), expected \(6, 3\)"):
        write_view(run)
    run = _octahedron_run(
        tmp_path / "run3",
        hand_points=np.zeros((3, 3, 3)),
        held_hand_points=np.zeros((3, 3)),
        hand_lines=[0, 1, 3],
    )
    with pytest.raises(
        ConfigError, match=r"hand_lines must rise from 0 to 3 in steps of at least 2, got \[0, 1, 3\]"
    ):
        write_view(run)
    run = _octahedron_run(tmp_path / "run4", normal_forces=np.zeros((2, 3)))
    with pytest.raises(
        ConfigError, match=r"normal_forces / held_normal_forces have shapes \(2, 3\) / \(3,\)"
    ):
        write_view(run)


# --- the page in a real browser -------------------------------------------------------------------

# WebGL canvas snapshot (drawn with preserveDrawingBuffer), copied to a scratch canvas for reading:
# the share of pixels that differ from the background, those of the hand's colour (dark blue-grey:
# none of the object's, the fingers' or the background's), whether anything is drawn on the
# canvas's border, and a 48 x 32 grid of mean grey levels to compare pictures.
_SNAPSHOT = """
const view = document.getElementById("view");
const c = document.createElement("canvas");
c.width = view.width; c.height = view.height;
const g = c.getContext("2d", {willReadFrequently: true});
g.drawImage(view, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data, bg = arguments[0];
const GX = 48, GY = 32, sum = new Array(GX * GY).fill(0), cnt = new Array(GX * GY).fill(0);
let differ = 0, hand = 0, border = 0;
for (let y = 0; y < c.height; y++) {
  for (let x = 0; x < c.width; x++) {
    const i = 4 * (y * c.width + x), r = d[i], gr = d[i + 1], b = d[i + 2];
    const off = Math.abs(r - bg[0]) + Math.abs(gr - bg[1]) + Math.abs(b - bg[2]) > 12;
    if (off) differ++;
    if (off && (x < 2 || y < 2 || x >= c.width - 2 || y >= c.height - 2)) border++;
    const lo = Math.min(r, gr, b), hi = Math.max(r, gr, b), grey = (r + gr + b) / 3;
    if (b - r >= 6 && b - r <= 45 && hi - lo <= 50 && grey >= 20 && grey <= 160) hand++;
    const k = Math.floor(y * GY / c.height) * GX + Math.floor(x * GX / c.width);
    sum[k] += grey; cnt[k]++;
  }
}
return {fraction: differ / (c.width * c.height), hand: hand, border: border,
        grid: sum.map((s, k) => s / cnt[k]), width: c.width, height: c.height,
        readout: document.getElementById("readout").textContent,
        label: document.getElementById("frame-label").textContent, frame: window.softgraspView.frame};
"""


def _browser():
    """A headless Chromium through ChromeDriver, or a pytest skip saying what is missing."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (pip install 'selenium>=4.20')")
    for exe in (CHROMIUM, CHROMEDRIVER):
        if not exe.exists():
            pytest.skip(f"{exe} is missing (apt-get install chromium chromium-driver)")
    profile = tempfile.mkdtemp(prefix="softgrasp-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--enable-unsafe-swiftshader",  # WebGL in software (SwiftShader), for this local page
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        "--window-size=1100,800",
        f"--user-data-dir={profile}",
    ):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    except BaseException:
        shutil.rmtree(profile, ignore_errors=True)
        raise
    return driver, profile


@pytest.fixture(scope="module")
def browser():
    driver, profile = _browser()
    yield driver
    driver.quit()
    shutil.rmtree(profile, ignore_errors=True)


def _open(driver, page: Path) -> None:
    driver.get(page.resolve().as_uri())
    deadline = time.monotonic() + 15
    while (ready := driver.execute_script("return document.body.dataset.ready")) != "1":
        assert ready != "error", driver.find_element("id", "error").text
        assert time.monotonic() < deadline, "the page never finished its first drawing"
        time.sleep(0.05)


def _severe(driver) -> list[dict]:
    return [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def _change(a: dict, b: dict) -> float:
    """Mean absolute difference of two snapshots' grey grids (0 to 255)."""
    return float(np.mean(np.abs(np.array(a["grid"]) - np.array(b["grid"]))))


def test_page_in_headless_chromium(browser, page, run_dir):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    _open(browser, page)
    assert _severe(browser) == []
    assert browser.execute_script("return performance.getEntriesByType('resource').length") == 0
    n_frames = browser.execute_script("return window.softgraspView.frames")
    with np.load(run_dir / "frames.npz") as z:
        K = z["travel"].shape[0]
        n_links = int(np.sum(np.diff(z["hand_lines"]) - 1))
    assert n_frames == K + 1 and browser.execute_script("return window.softgraspView.held") == K

    # It opens on the held state, with the hand drawn.
    held = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert held["frame"] == K and held["label"] == "held" and "held" in held["readout"]
    assert held["width"] > 500 and held["height"] > 300
    assert held["fraction"] > 0.05, f"canvas nearly blank: {held['fraction']:.1%} drawn"
    assert re.search(r"thumb 0\.\d{3} N", held["readout"]) and "thumb 0.000 N" not in held["readout"]
    labels = browser.execute_script(
        "return [...document.querySelectorAll('#labels .force')].filter(e => e.style.display !== 'none')"
        ".map(e => e.textContent)"
    )
    # each label: the finger's normal force in this frame, then its set-point (plan.json's)
    setpoints = json.loads((run_dir / "plan.json").read_text(encoding="utf-8"))["setpoints_N"]
    assert len(labels) == 3
    for text in labels:
        m = re.fullmatch(r"(\w+) (0\.\d{3}) N \(set-point (0\.\d{3}) N\)", text)
        assert m, text
        assert m[3] == f"{setpoints[m[1]]:.3f}" and m[2] != m[3]
    assert browser.execute_script("return window.softgraspView.handLinks") == n_links > 0
    assert held["hand"] > 1000, f"only {held['hand']} pixels of the hand's colour"
    browser.save_screenshot(str(run_dir / "view_held.png"))
    browser.execute_script("window.softgraspView.showHand(false)")
    no_hand = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert no_hand["hand"] < held["hand"] / 10 and _change(held, no_hand) > 0.3
    browser.execute_script("window.softgraspView.showHand(true)")

    # The slider: the keyboard moves it one frame, then to the start.
    slider = browser.find_element(By.ID, "frame")
    slider.send_keys(Keys.ARROW_LEFT)
    last = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert last["frame"] == K - 1 and last["label"] == f"increment {K - 1} / {K - 1}"
    assert last["readout"] != held["readout"] and _change(held, last) > 0.1
    shown = browser.execute_script(
        "return [...document.querySelectorAll('#labels .force')].map(e => e.textContent)"
    )
    for text in shown:  # the force changed with the frame, the set-point did not
        assert text.endswith(f" (set-point {setpoints[text.split(' ')[0]]:.3f} N)"), text
    assert shown != labels
    browser.execute_script(
        "const s = arguments[0]; s.value = '0'; s.dispatchEvent(new Event('input', {bubbles: true}));", slider
    )
    start = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert start["frame"] == 0 and start["label"] == "start" and "travel 0.000 mm" in start["readout"]
    assert _change(start, last) > 0.5, "the picture did not change with the slider"
    browser.save_screenshot(str(run_dir / "view_start.png"))

    # Turned every way, the held scene stays inside the canvas (nothing drawn on its border).
    browser.execute_script("window.softgraspView.setFrame(window.softgraspView.held)")
    canvas = browser.find_element(By.ID, "view")
    shots = []
    for dx, dy in ((160, 0), (160, 0), (0, 120), (0, -300), (240, 60)):
        drag = ActionChains(browser).move_to_element(canvas).click_and_hold()
        drag.move_by_offset(dx, dy).release().perform()
        shots.append(browser.execute_script(_SNAPSHOT, BACKGROUND))
        assert shots[-1]["border"] == 0 and shots[-1]["fraction"] > 0.03 and shots[-1]["frame"] == K
    assert _change(held, shots[0]) > 0.5 and _change(shots[0], shots[1]) > 0.5
    # The wheel zooms in; a double click restores the first view.
    ActionChains(browser).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, -400).perform()
    time.sleep(0.2)  # the wheel's events are handled as they come
    zoomed = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert zoomed["fraction"] > shots[-1]["fraction"] + 0.02, "zooming in did not enlarge the picture"
    ActionChains(browser).double_click(canvas).perform()
    assert _change(held, browser.execute_script(_SNAPSHOT, BACKGROUND)) < 0.05
    assert _severe(browser) == []
    for png in ("view_held.png", "view_start.png"):
        assert (run_dir / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_free_fingertips_in_browser(browser, tmp_path):
    """A run without a hand model: no hand drawn and no hand switch, the forces still labelled."""
    run = _octahedron_run(tmp_path / "run")
    _open(browser, write_view(run))
    assert browser.execute_script("return window.softgraspView.handLinks") == 0
    assert not browser.find_element("id", "hand").is_displayed()
    held = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert held["frame"] == 3 and held["label"] == "held" and held["fraction"] > 0.03 and held["border"] == 0
    assert "thumb 0.200 N" in held["readout"]
    labels = browser.execute_script(
        "return [...document.querySelectorAll('#labels .force')].map(e => e.textContent)"
    )
    assert labels[0] == "thumb 0.200 N"  # no plan.json in the run: no set-point to show
    browser.execute_script("window.softgraspView.setFrame(0)")
    start = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert _change(start, held) > 0.2
    assert _severe(browser) == []
