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
from softgrasp.viz.view import write_view

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
    """A tiny synthetic frames.npz (an octahedron squeezed in two steps)."""
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
    # Nothing is fetched: no script/link/img sources, no URLs at all.
    assert "http://" not in html and "https://" not in html
    assert not re.search(r"<(script|link|img|iframe)\b[^>]*\b(src|href)\s*=", html, re.I)
    assert '<input type="range" id="frame"' in html
    data = _embedded(html)
    with np.load(run_dir / "frames.npz") as z:
        K = z["travel"].shape[0]
        facets, positions, held = z["facets"], z["positions"], z["held_positions"]
        names = [str(s) for s in z["finger_names"]]
        held_forces = z["held_forces"]
    assert len(data["frames"]) == K + 1
    assert [f["label"] for f in data["frames"]][-1] == "held"
    assert [f["held"] for f in data["frames"]] == [False] * K + [True]
    assert data["fingers"] == names
    np.testing.assert_allclose(data["frames"][-1]["forces"], held_forces, atol=1e-6)
    # The micrometre differences decode to the boundary nodes of every frame (within 1 um).
    used = np.unique(facets)
    assert data["nodes"] == used.size and len(data["tris"]) == facets.size
    pos = np.cumsum([f["pos"] for f in data["frames"]], axis=0).reshape(K + 1, -1, 3) * 1e-6
    np.testing.assert_allclose(pos[:K], positions[:, used], atol=0.6e-6, rtol=0)
    np.testing.assert_allclose(pos[K], held[used], atol=0.6e-6, rtol=0)


def test_custom_out_and_no_temporary_files(run_dir, tmp_path):
    out = write_view(run_dir, tmp_path / "sub" / "page.html")
    assert out == tmp_path / "sub" / "page.html" and out.stat().st_size > 1000
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]


def test_names_cannot_break_out_of_the_page(tmp_path):
    run = _octahedron_run(tmp_path / "run", names=("</script><b>x", "a&b", "c"))
    html = write_view(run).read_text(encoding="utf-8")
    assert html.count("</script>") == 2  # the data and the page script, nothing injected
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


# --- the page in a real browser -------------------------------------------------------------------

# Canvas snapshot, copied to a scratch canvas for reading: the share of pixels that differ from the
# background and a 48 x 32 grid of mean grey levels to compare pictures.
_SNAPSHOT = """
const view = document.getElementById("view");
const c = document.createElement("canvas");
c.width = view.width; c.height = view.height;
const g = c.getContext("2d", {willReadFrequently: true});
g.drawImage(view, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data, bg = arguments[0];
const GX = 48, GY = 32, sum = new Array(GX * GY).fill(0), cnt = new Array(GX * GY).fill(0);
let differ = 0;
for (let y = 0; y < c.height; y++) {
  for (let x = 0; x < c.width; x++) {
    const i = 4 * (y * c.width + x);
    if (Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]) > 12) differ++;
    const k = Math.floor(y * GY / c.height) * GX + Math.floor(x * GX / c.width);
    sum[k] += (d[i] + d[i + 1] + d[i + 2]) / 3; cnt[k]++;
  }
}
return {fraction: differ / (c.width * c.height), grid: sum.map((s, k) => s / cnt[k]),
        width: c.width, height: c.height, readout: document.getElementById("readout").textContent,
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
    while driver.execute_script("return document.body.dataset.ready") != "1":
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
    n_frames = browser.execute_script("return window.softgraspView.frames")
    with np.load(run_dir / "frames.npz") as z:
        K = z["travel"].shape[0]
    assert n_frames == K + 1 and browser.execute_script("return window.softgraspView.held") == K

    start = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert start["frame"] == 0 and start["width"] > 500 and start["height"] > 300
    assert start["fraction"] > 0.10, f"canvas nearly blank: {start['fraction']:.1%} drawn"
    assert "travel 0.000 mm" in start["readout"] and start["label"] == "step 0 / " + str(K - 1)
    browser.save_screenshot(str(run_dir / "view_frame0.png"))

    # The keyboard moves the slider one frame.
    slider = browser.find_element(By.ID, "frame")
    slider.send_keys(Keys.ARROW_RIGHT)
    one = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert one["frame"] == 1 and one["readout"] != start["readout"]

    # The last closing step: fingers pressed in, forces drawn.
    browser.execute_script(
        "const s = arguments[0]; s.value = String(arguments[1]);"
        "s.dispatchEvent(new Event('input', {bubbles: true}));",
        slider,
        K - 1,
    )
    last = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert last["frame"] == K - 1 and last["readout"] != start["readout"]
    assert _change(start, last) > 0.5, "the picture did not change with the slider"
    assert re.search(r"thumb \d\.\d{3} N", last["readout"]) and " 0.000 N" not in last["readout"]

    # The held state, the last slider position: no table, other forces.
    browser.execute_script("window.softgraspView.setFrame(window.softgraspView.frames - 1)")
    held = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert held["frame"] == K and held["label"] == "held" and "held" in held["readout"]
    assert held["fraction"] > 0.10
    assert _change(start, held) > 0.5 and _change(last, held) > 0.1
    browser.save_screenshot(str(run_dir / "view_held.png"))

    # Dragging turns the view, the wheel zooms.
    canvas = browser.find_element(By.ID, "view")
    ActionChains(browser).move_to_element(canvas).click_and_hold().move_by_offset(120, 30).release().perform()
    turned = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert _change(held, turned) > 0.5 and turned["frame"] == K
    ActionChains(browser).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, -400).perform()
    time.sleep(0.2)  # the wheel redraws on the next animation frame
    zoomed = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert zoomed["fraction"] > turned["fraction"] + 0.02, "zooming in did not enlarge the picture"
    assert _severe(browser) == []
    for png in ("view_frame0.png", "view_held.png"):
        assert (run_dir / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_exaggerated_deformation_in_browser(browser, tmp_path):
    run = _octahedron_run(tmp_path / "run")
    _open(browser, write_view(run))
    browser.execute_script("window.softgraspView.setFrame(2)")
    before = browser.execute_script(_SNAPSHOT, BACKGROUND)
    browser.execute_script(
        "const s = document.getElementById('scale'); s.value = '20';"
        "s.dispatchEvent(new Event('change', {bubbles: true}));"
    )
    after = browser.execute_script(_SNAPSHOT, BACKGROUND)
    assert before["fraction"] > 0.05 and _change(before, after) > 0.2
    assert _severe(browser) == []
