"""Which OpenGL MuJoCo renders offscreen with: Mesa's EGL on Linux, where the user chose nothing.

MuJoCo reads ``MUJOCO_GL`` once, when it is first imported; every module that imports MuJoCo
(the execution scenes, an MJCF hand's reader, the reproduce report) calls
:func:`prefer_headless_gl` first, so that ``execute``'s pictures render without a screen.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Container, MutableMapping

__all__ = ["GL_BACKEND", "prefer_headless_gl"]

#: MuJoCo's OpenGL back-end without a screen on Linux (the value of ``MUJOCO_GL``): Mesa's EGL.
GL_BACKEND = "egl"


def prefer_headless_gl(
    environ: MutableMapping[str, str] | None = None,
    modules: Container[str] | None = None,
    platform: str | None = None,
) -> bool:
    """Set ``MUJOCO_GL`` to :data:`GL_BACKEND` on Linux when the user has not set it and MuJoCo
    is not imported yet (it reads the variable once, at import); whether it was set.

    ``environ``, ``modules`` and ``platform`` default to this process's (``os.environ``, the
    names in ``sys.modules``, ``sys.platform``)."""
    environ = os.environ if environ is None else environ
    loaded = sys.modules if modules is None else modules
    platform = sys.platform if platform is None else platform
    if not platform.startswith("linux") or "MUJOCO_GL" in environ or "mujoco" in loaded:
        return False
    environ["MUJOCO_GL"] = GL_BACKEND
    return True
