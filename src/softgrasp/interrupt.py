"""A Ctrl-C that no library can swallow.

Python turns SIGINT into ``KeyboardInterrupt`` wherever the main thread happens to be. Some
libraries a command imports catch every exception around their optional imports (``except
BaseException``), so a Ctrl-C landing in one of those imports would vanish and the command run on
to exit 0. The command line installs :func:`handle_sigint`, which also records the interrupt;
:func:`raise_if_interrupted` raises it again at the next phase of a command and before a run
folder's files are moved into place, so an interrupted run stops and leaves earlier outputs as
they were.
"""

from __future__ import annotations

import signal
import threading

__all__ = ["handle_sigint", "install", "interrupted", "raise_if_interrupted"]

_RECEIVED = threading.Event()


def handle_sigint(_signum: int, _frame: object) -> None:
    """SIGINT handler: record the interrupt, then raise ``KeyboardInterrupt`` as Python does."""
    _RECEIVED.set()
    raise KeyboardInterrupt


def install() -> None:
    """Make :func:`handle_sigint` this process's SIGINT handler (main thread only; an ignored
    SIGINT stays ignored)."""
    if threading.current_thread() is threading.main_thread() and (
        signal.getsignal(signal.SIGINT) is signal.default_int_handler
    ):
        _RECEIVED.clear()  # (a command run earlier in this process is over)
        signal.signal(signal.SIGINT, handle_sigint)


def interrupted() -> bool:
    """Whether a Ctrl-C was received (a C extension interrupted while it initialises reports
    it as another exception, e.g. NumPy's ``ImportError``)."""
    return _RECEIVED.is_set()


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if a Ctrl-C was received, even one a library swallowed."""
    if interrupted():
        raise KeyboardInterrupt
