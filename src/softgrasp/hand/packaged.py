"""Portable names of the files softgrasp ships (the packaged hand models): outputs record
``package:softgrasp/hand/shadow_like.urdf`` rather than where this installation put the file, so
that a plan means the same on another machine."""

from __future__ import annotations

from pathlib import Path

__all__ = ["PACKAGE_PREFIX", "package_name", "package_file", "portable_name"]

#: The prefix of a packaged file's portable name.
PACKAGE_PREFIX = "package:softgrasp/"


def _root() -> Path:
    return Path(__file__).resolve().parents[1]


def package_name(path: str | Path) -> str | None:
    """``package:softgrasp/<path inside the package>`` for a file of the installed package, else None."""
    text = str(path)
    if text.startswith(PACKAGE_PREFIX):
        return text
    try:
        rel = Path(text).resolve().relative_to(_root())
    except (ValueError, OSError):
        return None
    return PACKAGE_PREFIX + rel.as_posix()


def package_file(name: str) -> Path | None:
    """The file a ``package:softgrasp/...`` name stands for in this installation, else None."""
    if not name.startswith(PACKAGE_PREFIX):
        return None
    rel = Path(name[len(PACKAGE_PREFIX) :])
    if rel.is_absolute() or ".." in rel.parts:
        return None
    return _root() / rel


def portable_name(path: str | Path) -> str:
    """How outputs name the file ``path``: its package name for a packaged file, else as given."""
    return package_name(path) or str(path)
