"""The optional extras of the ``softgrasp`` distribution a command needs, checked before any work.

The core install plans, compresses, indents, calibrates and views. ``sweep`` (and ``plan
--uncertain``) run on Dask and write Parquet: the ``sweep`` extra; ``execute`` (and a sweep that
executes its plans) runs MuJoCo: the ``execute`` extra.
"""

from __future__ import annotations

import importlib

from softgrasp.errors import ConfigError

__all__ = ["EXTRAS", "require"]

#: Each extra and the modules it installs.
EXTRAS = {"sweep": ("dask.distributed", "pyarrow"), "execute": ("mujoco",)}


def require(extra: str, what: str) -> None:
    """Import the modules of ``extra`` (:data:`EXTRAS`); :class:`ConfigError` naming the install
    command if one is missing. ``what``: what needs them, for the message (``softgrasp sweep``)."""
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            missing = exc.name or module
            raise ConfigError(
                f"{what} needs softgrasp's '{extra}' extra ({missing} is not installed): "
                f"pip install 'softgrasp[{extra}]'"
            ) from None
