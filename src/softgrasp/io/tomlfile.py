"""Reading softgrasp's TOML input files (config, material, sweep) with clear errors."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from softgrasp.errors import ConfigError

__all__ = ["read_toml"]


def read_toml(path: str | Path, what: str) -> dict[str, Any]:
    """The TOML document at ``path``; ConfigError naming ``what`` ("material file", "sweep file",
    "config file") and the file when it is missing, unreadable or not valid TOML."""
    name = str(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{what} {name} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} {name} is a directory, not a TOML file") from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {name}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} {name} is not valid TOML: {exc}") from None
