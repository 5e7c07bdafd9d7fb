"""Atomic file output: every file appears whole or not at all."""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["atomic_write", "read_umask", "write_json", "write_text"]


def read_umask() -> int:
    """Read the process umask into the mode new files get, and return it: at import (setting
    the umask to read it is process-wide, so not per write), and again in a process whose umask
    changed since (a child of softgrasp's warm server takes its client's: :mod:`softgrasp.cli.zygote`)."""
    global _UMASK
    mask = os.umask(0o022)
    os.umask(mask)
    _UMASK = mask
    return mask


_UMASK = 0o022
read_umask()


def atomic_write(path: str | Path, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` on a temporary file beside ``path``, then rename it into place.

    If the writer raises, the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        writer(tmp_path)
        # mkstemp creates the file private (0600); give it the permissions of an ordinary new file.
        os.chmod(tmp_path, 0o666 & ~_UMASK)
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def _strict(data: Any) -> Any:
    """``data`` with every non-finite float (NaN, infinities) as None: strict JSON (null), which
    every JSON reader accepts (Python's writes NaN and Infinity, which most readers refuse)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {k: _strict(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_strict(v) for v in data]
    return data


def write_json(path: str | Path, data: Any) -> Path:
    """Atomically write ``data`` as indented, strict JSON to ``path`` (non-finite numbers as null)."""
    return write_text(path, json.dumps(_strict(data), indent=2, sort_keys=False, allow_nan=False) + "\n")
