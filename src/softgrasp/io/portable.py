"""Paths as output files record them: no machine's absolute paths.

A file softgrasp ships is named ``package:softgrasp/...`` (:mod:`softgrasp.hand.packaged`); any
other file a user named (a mesh, a material file, a URDF, a plan) by its path relative to the
output folder that records it, with ``/`` separators, so that a folder of results can be moved,
shared or archived with its inputs beside it. :func:`resolve_path` reads such a name back.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from softgrasp.hand.packaged import package_file, package_name

__all__ = ["PATH_OPTIONS", "portable_path", "portable_options", "resolve_path"]

#: Plan and sweep options whose text may name a file.
PATH_OPTIONS = ("object", "material", "hand", "grasp")


def _split(text: str) -> tuple[str, str]:
    """A material value ``FILE.toml,key=value`` split into the file and its overrides (``,...``)."""
    k = text.lower().find(".toml,")
    return (text, "") if k < 0 else (text[: k + 5], text[k + 5 :])


def portable_path(text: str, folder: str | Path) -> str:
    """``text`` as an output in ``folder`` records it: a packaged file's package name; an existing
    file's path relative to ``folder`` (``/`` separators; a material file keeps its ``,key=value``
    overrides); any other text (a preset, a built-in object, a shape) unchanged."""
    name, rest = _split(str(text))
    packaged = package_name(name) if name else None
    if packaged is not None:
        return packaged + rest
    p = Path(name)
    if not name or not p.is_file():
        return str(text)
    rel = os.path.relpath(p.resolve(), Path(folder).resolve())
    return Path(rel).as_posix() + rest


def portable_options(options: Mapping[str, object], folder: str | Path) -> dict[str, object]:
    """``options`` with the file names of :data:`PATH_OPTIONS` made portable (:func:`portable_path`)."""
    out = dict(options)
    for k in PATH_OPTIONS:
        if isinstance(out.get(k), str):
            out[k] = portable_path(str(out[k]), folder)
    return out


def resolve_path(text: str, folder: str | Path) -> Path:
    """The file a recorded name stands for: a package name's file in this installation, a relative
    path from ``folder``, an absolute path as it is."""
    packaged = package_file(text)
    if packaged is not None:
        return packaged
    p = Path(text)
    return p if p.is_absolute() else Path(folder) / p
