"""The documentation: the MkDocs site builds without a warning, and the front pages stay short."""

from __future__ import annotations

import ast
import pathlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _lines(relative: str) -> int:
    return len((ROOT / relative).read_text(encoding="utf-8").splitlines())


def test_readme_is_at_most_250_lines():
    assert _lines("README.md") <= 250


def test_benchmarks_readme_is_at_most_200_lines():
    assert _lines("benchmarks/README.md") <= 200


def test_the_site_builds_strictly(tmp_path):
    for module in ("mkdocs", "mkdocstrings"):
        pytest.importorskip(module, reason=f"{module} is not installed: `pip install -e .[test]` brings it")
    site = tmp_path / "site"
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml"),
         "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    for page in ("index.html", "guide/index.html", "formats/index.html", "physics/index.html",
                 "performance/index.html", "architecture/index.html", "api/index.html"):
        assert (site / page).is_file(), page
    api = (site / "api" / "index.html").read_text(encoding="utf-8")
    documented_names = (
        "softgrasp.grasp.equilibrium",
        "friction_feasibility",
        "softgrasp.physics.fingertip.laws",
        "effective_modulus",
        "softgrasp.model.material",
    )
    for documented in documented_names:
        assert documented in api, documented


def test_every_figure_the_docs_show_is_there():
    import re

    for page in (ROOT / "docs").glob("*.md"):
        for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", page.read_text(encoding="utf-8")):
            assert (page.parent / target).is_file(), f"{page.name}: {target}"
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for target in re.findall(r"\]\(((?:docs|benchmarks)/[^)#\s]+)", readme):
        assert (ROOT / target).is_file(), f"README.md: {target}"


def _table(text: str) -> list[str]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| what | script |"))
    end = next(i for i in range(start, len(lines)) if not lines[i].startswith("|"))
    return lines[start:end]


def test_the_performance_page_shows_the_benchmarks_table():
    bench = (ROOT / "benchmarks" / "README.md").read_text(encoding="utf-8")
    page = (ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    assert _table(page) == _table(bench)


@pytest.mark.slow
def test_readme_python_example_runs_as_written(tmp_path: Path, planned_sphere: Path) -> None:
    """The README's Python example, run as written in a fresh interpreter: its set-points are the
    command line's plan with the same safety factor (``softgrasp plan`` with every default: the
    session's plan, tests/conftest.py), and the executed plan lifts the sphere."""
    import json
    import re

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    first, second = proc.stdout.strip().splitlines()[-2:]
    setpoints = ast.literal_eval(first)
    doc = json.loads((planned_sphere / "plan.json").read_text())
    want = doc["setpoints_N"]
    assert setpoints.keys() == want.keys()
    for name, value in want.items():
        assert setpoints[name] == pytest.approx(value, rel=1e-6)
    assert (tmp_path / "out" / "plan.json").is_file()
    assert re.match(r"True ", second), second
