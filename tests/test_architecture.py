"""The package's shape: layers import only downwards, modules stay small, no environment switches.

The layer contract lives in ``pyproject.toml`` (``[tool.importlinter]``) and is checked here with
import-linter. Every module stays within 500 lines; the only environment variable the package reads
is the thread setting (solver routes, precisions, kernels and figure modes are function arguments).
"""

from __future__ import annotations

import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "softgrasp"
LIMIT = 500

#: The environment variables the package reads: the thread count, nothing that chooses code.
ENV_VARIABLES = {"SOFTGRASP_THREADS"}


def test_layer_contract_is_kept() -> None:
    """import-linter runs in a child process: it reconfigures logging (disabling the loggers that
    exist), which would silence softgrasp's loggers for the tests after this one."""
    pytest.importorskip("importlinter.cli")
    code = (
        "from importlinter.cli import lint_imports; "
        f"raise SystemExit(lint_imports(config_filename={str(ROOT / 'pyproject.toml')!r}, no_cache=True))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, f"an import crosses the layers of [tool.importlinter]:\n{proc.stdout}"


def test_every_module_is_within_the_size_limit() -> None:
    sizes = {
        p.relative_to(SRC).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
        for p in SRC.rglob("*.py")
    }
    assert len(sizes) > 100
    too_big = {m: n for m, n in sizes.items() if n > LIMIT}
    assert not too_big, f"modules over {LIMIT} lines: split them by concept: {too_big}"


def test_environment_variables_are_only_the_thread_setting() -> None:
    names: set[str] = set()
    for p in SRC.rglob("*.py"):
        names |= set(re.findall(r"SOFTGRASP_[A-Z0-9_]+", p.read_text(encoding="utf-8")))
    assert names == ENV_VARIABLES, f"environment variables read: {sorted(names)}"
