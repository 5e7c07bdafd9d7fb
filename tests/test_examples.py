"""The scripts in examples/ run as they are, and print the numbers the API gives for the same
inputs."""

from __future__ import annotations

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import softgrasp as sg

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(name: str, *args: str) -> str:
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, timeout=1200
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def _module(name: str):
    spec = importlib.util.spec_from_file_location(name.removesuffix(".py"), EXAMPLES / name)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _numbers(text: str, pattern: str) -> dict[str, float]:
    return {m[0]: float(m[1]) for m in re.findall(pattern, text)}


@pytest.mark.slow
def test_plan_your_mesh(tmp_path):
    out = _run("01_plan_your_mesh.py", str(tmp_path / "plan"))
    printed = _numbers(out, r"(?m)^(thumb|first|middle) ([0-9.]+) N$")
    example = _module("01_plan_your_mesh.py")
    plan = example.plan_ellipsoid(example.write_ellipsoid_stl(tmp_path))
    assert printed == pytest.approx(plan.setpoints_N, abs=1e-6)
    assert list(printed) == ["thumb", "first", "middle"]
    assert (tmp_path / "plan" / "plan.json").is_file()


@pytest.mark.slow
def test_execute_plan(tmp_path):
    """The example prints the run it saves (``execute.json``, to its last digit), its set-points
    are the API's plan's, and the executed plan reaches them within the controller's tolerance
    and lifts the sphere."""
    out = _run("02_execute_plan.py", str(tmp_path))
    setpoints = _numbers(out, r"(?m)^(thumb|first|middle) set-point ([0-9.]+) N")
    measured = _numbers(out, r"(?m)^(thumb|first|middle) set-point [0-9.]+ N, measured ([0-9.]+) N")
    plan = sg.plan(sg.load_object("sphere"), hand=sg.load_hand("shadow_like"), mu=0.8)
    assert setpoints == pytest.approx(plan.setpoints_N, abs=1e-6)
    doc = json.loads((tmp_path / "execute" / "execute.json").read_text())
    saved = {f["name"]: f for f in doc["fingers"]}
    for name, value in measured.items():
        assert value == pytest.approx(saved[name]["measured_N"], abs=1e-6)
        assert value == pytest.approx(setpoints[name], rel=0.05)  # the controller's tolerance
    assert f"lifted {doc['lifted']}" in out and doc["lifted"]
    slip_mm = float(re.search(r"(?m)^slip ([0-9.]+) mm$", out)[1])  # type: ignore[index]
    assert slip_mm == pytest.approx(doc["slip_m"] * 1e3, abs=1e-6)


def test_calibrate_from_csv(tmp_path):
    out = _run("03_calibrate_from_csv.py")
    E = float(re.search(r"(?m)^E ([0-9.]+) Pa$", out)[1])  # type: ignore[index]
    example = _module("03_calibrate_from_csv.py")
    cal = example.calibrate_cube(example.write_compression_csv(tmp_path))
    assert E == pytest.approx(cal.E_Pa, abs=1e-6)
    assert E == pytest.approx(2.0e5, rel=0.01)  # the modulus that made the curve
