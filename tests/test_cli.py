"""The command line: files written, and one clear line with a non-zero exit for bad input."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

from softgrasp.cli import main


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "softgrasp.cli", *args], capture_output=True, text=True, timeout=300
    )


def test_compress_writes_csv_json_png(tmp_path):
    out = tmp_path / "run"
    assert (
        main(
            [
                "compress",
                "--object",
                "cube",
                "--mesh-size",
                "0.0125",
                "--strain",
                "0.05",
                "--steps",
                "3",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = list(csv.DictReader((out / "compress.csv").open()))
    assert list(rows[0]) == ["displacement_m", "force_N", "strain", "stress_Pa"]
    assert float(rows[-1]["strain"]) == pytest.approx(0.05)
    data = json.loads((out / "compress.json").read_text())
    assert data["object"]["material"]["E_Pa"] == 4.9284e6
    assert data["object"]["nodes"] > 0 and data["apparent_E_Pa"] > 0
    assert (out / "compress.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no temporary files left: of the hidden ones, only the manifest of the files softgrasp wrote
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [".softgrasp-manifest.json"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--material", "E=-1,nu=0.3,density=5"], "E = -1.0 Pa is invalid"),
        (["--material", "E=1e5,nu=0.5,density=5"], "nu = 0.5 is invalid"),
        (["--material", "E=1e5,nu=0.3,mass=-1"], "mass = -1.0 kg is invalid"),
        (["--object", "no/such/file.msh"], "file.msh"),
        (["--object", "teapot"], "unknown object 'teapot'"),
        (["--strain", "0.95"], "--strain must be a number in (0, 0.8], got 0.95"),
        (["--mesh-size", "-1"], "--mesh-size must be a number in [1e-05, 0.25] m, got -1 m"),
        (["--mesh-size", "0.04"], "fewer than two cells across its thinnest edge (50 mm)"),
        (["--object", "box:0.04x0.04x0.02", "--mesh-size", "8"], "for 8 mm write 0.008"),
        (["--object", "ball:0.03", "--mesh-size", "5"], "for 5 mm write 0.005"),
        (["--object", "ball:0.003", "--mesh-size", "0.005"], "use mesh_size <= 0.003 m"),
        (["--plate-friction", "-0.2"], "--plate-friction must be a number in [0, 5], got -0.2"),
    ],
)
def test_compress_bad_input_one_line_nonzero(tmp_path, args, needle):
    out = tmp_path / "out"
    proc = (
        _run("compress", "--object", "cube", *args, "--out", str(out))
        if "--object" not in args
        else _run("compress", *args, "--out", str(out))
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("softgrasp: error:") and needle in lines[0]
    assert "Traceback" not in proc.stderr
    assert not out.exists() or not any(out.iterdir())  # nothing half-written


def test_verbose_prints_the_solver_progress(tmp_path):
    """``--verbose`` shows every Newton iteration and friction pass on stderr; without it the
    solver is silent."""
    args = ["compress", "--object", "cube", "--mesh-size", "0.025", "--strain", "0.02", "--steps", "2"]
    loud = _run("--verbose", *args, "--out", str(tmp_path / "a"))
    quiet = _run(*args, "--out", str(tmp_path / "b"))
    assert loud.returncode == quiet.returncode == 0, loud.stderr
    assert "softgrasp: newton it 1: unbalanced" in loud.stderr
    assert "softgrasp: friction pass 1:" in loud.stderr
    assert "newton it" not in quiet.stderr


def test_default_compress_job_runs(tmp_path):
    """`softgrasp compress` with every default (rubber sphere to 30 %)."""
    out = tmp_path / "default"
    assert main(["compress", "--out", str(out)]) == 0
    data = json.loads((out / "compress.json").read_text())
    assert data["parameters"]["strain"] == 0.3
    rows = list(csv.DictReader((out / "compress.csv").open()))
    forces = [float(r["force_N"]) for r in rows]
    assert forces[-1] == max(forces) > 0
