"""Output folders replaced whole: a command's set of files appears complete or not at all.

A command that writes a folder (``plan``, ``execute``, ``calibrate``, ``compress``, ``indent``,
``reproduce``, ``sweep``) does so inside :func:`run_folder`:

1. the folder is checked before any work (:func:`check_out`: not empty, not a file, not under
   ``/proc`` or ``/sys``, names not too long, writable) and locked: an exclusive ``flock`` on the
   hidden ``.softgrasp.lock``; a second run writing there is refused at once (``ConfigError``);
2. every file is written into a hidden staging folder inside it (``.softgrasp-stage.*``, the
   same file system), which a failure or an interrupt (SIGINT, SIGTERM) removes, leaving the
   folder as it was;
3. on success the staged files are moved into place with SIGINT and SIGTERM held back until the
   move is done. A journal (``.softgrasp-commit.json``) written before the first move lets the
   next run finish a move cut short by a kill or a power cut. The manifest
   (``.softgrasp-manifest.json``) records which command wrote each file; a command removes only
   files its own earlier run wrote and this one did not, never anyone else's.

Runs nest: :func:`run_folder` on a folder already open in this process (or on a folder inside it,
or inside its staging folder) writes into the same staging folder and leaves the move to the
outermost run. So ``Plan.save(out)`` alone replaces the plan's files whole, and inside
``softgrasp plan`` (which opens the folder before planning) it stages them for the command's
single move.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from softgrasp.errors import ConfigError
from softgrasp.interrupt import raise_if_interrupted
from softgrasp.io.atomic import write_json

__all__ = [
    "RunFolder",
    "run_folder",
    "save_whole",
    "check_out",
    "check_out_file",
    "write_failure",
    "MANIFEST",
    "LOCK",
]

#: The lock file, the manifest, the commit journal and the staging folders' prefix.
LOCK = ".softgrasp.lock"
MANIFEST = ".softgrasp-manifest.json"
JOURNAL = ".softgrasp-commit.json"
STAGE_PREFIX = ".softgrasp-stage."
#: Virtual file systems no output can go to.
_VIRTUAL = ("/proc", "/sys")
_NAME_MAX, _PATH_MAX = 255, 4096


@dataclass
class RunFolder:
    """An output folder being written.

    Attributes
    ----------
    path: the folder the files end up in.
    stage: where to write them now (a staging folder inside ``path``, or inside an enclosing run's).
    owner: the command writing them (the manifest records it per file).
    """

    path: Path
    stage: Path
    owner: str
    _live: set[str] = field(default_factory=set, repr=False)
    _live_root: Path | None = field(default=None, repr=False)
    _outer: RunFolder | None = field(default=None, repr=False)

    def live(self, name: str) -> Path:
        """Where to write ``name`` in place, visible as it grows (a sweep's streamed table, which
        ``--resume`` continues from): in the folder itself, owned by this command once the run
        ends; inside an enclosing run's staging folder, staged like every other file."""
        if self._live_root is None:
            return self.stage / name
        outer = self._outer if self._outer is not None else self
        full = self._live_root / name
        outer._live.add(full.resolve().relative_to(outer.path.resolve()).as_posix())
        return full


class _Open(threading.local):
    def __init__(self) -> None:
        self.folders: list[RunFolder] = []


#: The outermost run folders open in this thread.
_OPEN = _Open()


def _virtual_root(path: Path) -> str | None:
    for root in _VIRTUAL:
        if path == Path(root) or Path(root) in path.parents:
            return root
    return None


def _refuse(option: str, text: str, why: str) -> ConfigError:
    shown = text if len(text) <= 80 else f"{text[:40]}...{text[-20:]}"
    return ConfigError(f"{option} {shown!r}: {why}")


def _check_names(option: str, text: str, full: Path) -> None:
    if len(os.fsencode(str(full))) >= _PATH_MAX:
        raise _refuse(option, text, f"the path is longer than {_PATH_MAX - 1} bytes; give a shorter one")
    for part in full.parts:
        if len(os.fsencode(part)) > _NAME_MAX:
            raise _refuse(
                option, text, f"the name {part[:24]}... is longer than {_NAME_MAX} bytes; give a shorter one"
            )


def check_out(out: str | os.PathLike[str], option: str = "--out") -> Path:
    """``out`` as a folder softgrasp can write, checked before any work, or ConfigError saying why
    not (named after the command-line ``option``): empty, a file, under ``/proc`` or ``/sys``, a
    name or path too long, a file where a parent folder should be, not writable."""
    text = os.fspath(out)
    if not text.strip():
        raise ConfigError(f"{option} is empty: give a folder name (e.g. {option} results)")
    if "\0" in text:
        raise _refuse(option, text, "the name holds a NUL character")
    path = Path(text)
    full = Path(os.path.abspath(path))
    _check_names(option, text, full)
    for p in (full, path.resolve()):
        root = _virtual_root(p)
        if root is not None:
            raise _refuse(
                option, text, f"{root} is the kernel's virtual file system; give a folder elsewhere"
            )
    existing = full
    while not existing.exists() and not existing.is_symlink():
        existing = existing.parent
    if existing == full and not full.is_dir():
        raise _refuse(option, text, "is a file, not a folder; give a folder name")
    if not existing.is_dir():
        raise _refuse(option, text, f"{existing} is a file, so no folder can be made there")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise _refuse(option, text, f"{existing} is not writable; give a folder you can write to")
    return path


def check_out_file(out: str | os.PathLike[str], option: str = "--out") -> Path:
    """``out`` as a file softgrasp can write (its folder checked by :func:`check_out`), or
    ConfigError saying why not."""
    text = os.fspath(out)
    if not text.strip():
        raise ConfigError(f"{option} is empty: give a file name")
    path = Path(text)
    if path.is_dir():
        raise _refuse(option, text, "is a folder; give a file name")
    check_out(path.parent if str(path.parent) else ".", option)
    _check_names(option, text, Path(os.path.abspath(path)))
    return path


def _writing(exc: OSError, path: Path) -> bool:
    """Whether ``exc`` is a failure to write output: the disk or quota full, a file too large, or
    any failure on a file inside the output folder ``path``."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return True
    name = exc.filename
    if not isinstance(name, str | bytes | os.PathLike):
        return False
    try:
        full, top = Path(os.path.abspath(os.fsdecode(name))), Path(os.path.abspath(path))
    except (TypeError, ValueError):
        return False
    return full == top or top in full.parents


def write_failure(exc: OSError, out: str | os.PathLike[str], option: str = "--out") -> ConfigError | None:
    """``exc`` as one line naming ``option`` when it is a failure to write ``out`` (a file or a
    folder: the disk full, a read-only file system, ...); None when it is about another file."""
    return _os_error(option, os.fspath(out), exc) if _writing(exc, Path(out)) else None


def _os_error(option: str, text: str, exc: OSError, then: str = "") -> ConfigError:
    """A file-system failure (at the door, or while writing: ``then`` adds what became of the
    folder) as one line that says what to change."""
    why = {
        errno.ENAMETOOLONG: "a name in it is too long; give a shorter one",
        errno.EROFS: "it is on a read-only file system; give a folder elsewhere",
        errno.EACCES: "it is not writable; give a folder you can write to",
        errno.EPERM: "it is not writable; give a folder you can write to",
        errno.ENOSPC: "the disk is full; free space or give a folder elsewhere",
        errno.EDQUOT: "the disk quota is used up; free space or give a folder elsewhere",
        errno.EFBIG: "a file outgrew the file system's size limit; give a folder elsewhere",
        errno.ENOTDIR: "a part of it is a file, not a folder",
        errno.EEXIST: "is a file, not a folder; give a folder name",
    }.get(exc.errno or 0, f"cannot be written ({exc.strerror})")
    return _refuse(option, text, why + then)


def _makedirs(path: Path) -> list[Path]:
    """Make ``path`` and its missing parents; the folders made, deepest first."""
    made: list[Path] = []
    p = path
    while not p.exists():
        made.append(p)
        p = p.parent
    for d in reversed(made):
        with contextlib.suppress(FileExistsError):
            d.mkdir()
    return made


def _lock(path: Path, option: str, text: str) -> int:
    """An exclusive lock on ``path``'s lock file (the file still in place once locked)."""
    lock = path / LOCK
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise _refuse(
                option,
                text,
                "another softgrasp run is writing there; wait for it to end or give another folder",
            ) from None
        mine = os.fstat(fd)
        try:
            now = os.stat(lock)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (mine.st_dev, mine.st_ino):
            return fd
        os.close(fd)  # the file was removed by the run that held it: lock the new one


def _safe(name: object) -> str:
    """A relative path inside the folder (a damaged manifest or journal cannot reach outside)."""
    p = Path(str(name))
    if p.is_absolute() or ".." in p.parts or not p.parts:
        raise ConfigError(f"{MANIFEST} or {JOURNAL} names {name!r}, outside its folder; remove that file")
    return p.as_posix()


def _read_manifest(path: Path) -> dict[str, str]:
    try:
        doc = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
        files = doc["files"]
    except FileNotFoundError:
        return {}
    except (ValueError, KeyError, TypeError):
        return {}  # unreadable: own nothing (never remove a file on a guess)
    return {_safe(k): str(v) for k, v in files.items()}


def _prune(path: Path, file: Path) -> None:
    """Remove the folders left empty above ``file``, up to ``path`` (not it)."""
    d = file.parent
    while d != path and path in d.parents:
        try:
            d.rmdir()
        except OSError:
            return
        d = d.parent


def _apply(path: Path, journal: dict) -> None:
    """Carry out a commit ``journal``: move the staged files into place, remove the stale ones,
    write the manifest, drop the journal and the staging folder. Safe to repeat."""
    stage = path / _safe(journal["stage"])
    for name in journal["moves"]:
        src, dst = stage / _safe(name), path / _safe(name)
        if os.path.lexists(src):
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
    for name in journal["remove"]:
        p = path / _safe(name)
        if p.is_symlink() or p.is_file():
            p.unlink()
            _prune(path, p)
    write_json(path / MANIFEST, {"schema": "softgrasp.outputs/1", "files": journal["manifest"]})
    (path / JOURNAL).unlink(missing_ok=True)
    shutil.rmtree(stage, ignore_errors=True)


def _recover(path: Path) -> None:
    """Finish a commit cut short (its journal) and remove staging folders of runs that ended."""
    journal = path / JOURNAL
    if journal.exists():
        try:
            doc = json.loads(journal.read_text(encoding="utf-8"))
        except ValueError:  # cut short while written: no move had begun
            journal.unlink()
        else:
            _apply(path, doc)
    for p in path.glob(STAGE_PREFIX + "*"):
        shutil.rmtree(p, ignore_errors=True)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back meanwhile, then delivered."""
    sigs = (signal.SIGINT, signal.SIGTERM)
    if threading.current_thread() is not threading.main_thread():
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
        try:
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        return
    caught: list[int] = []
    before = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        signal.signal(s, lambda n, _f: caught.append(n))
    old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        for s, h in before.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        for n in caught[:1]:
            signal.raise_signal(n)


def _interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM stops the run as Ctrl-C does (its staging folder removed), where nothing else
    handles it."""
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGTERM) != signal.SIG_DFL
    ):
        yield
        return
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _commit(folder: RunFolder, complete: bool) -> None:
    path, stage = folder.path, folder.stage
    moves = sorted(p.relative_to(stage).as_posix() for p in stage.rglob("*") if p.is_file() or p.is_symlink())
    for name in moves:  # refused before anything moves: the folder stays as it was
        dst = path / name
        if dst.is_dir() and not dst.is_symlink():
            raise ConfigError(f"{dst} is a folder where softgrasp writes a file; move it away")
        for parent in Path(name).parents:
            p = path / parent
            if parent != Path(".") and (p.is_file() or p.is_symlink() and not p.is_dir()):
                raise ConfigError(f"{p} is a file where softgrasp writes a folder; move it away")
    written = set(moves) | {n for n in folder._live if (path / n).exists()}
    old = _read_manifest(path)
    stale = (
        sorted(n for n, who in old.items() if who == folder.owner and n not in written) if complete else []
    )
    manifest = {n: who for n, who in old.items() if n not in written and n not in stale}
    manifest.update({n: folder.owner for n in sorted(written)})
    journal = {"stage": stage.name, "moves": moves, "remove": stale, "manifest": manifest}
    with _signals_held():
        write_json(path / JOURNAL, journal)
        _apply(path, journal)


def _nested(path: Path, owner: str) -> RunFolder | None:
    """A view of an open run folder for ``path`` (the folder itself, one inside it, or one inside
    its staging folder), or None."""
    real = path.resolve()
    for f in _OPEN.folders:
        top, stage = f.path.resolve(), f.stage.resolve()
        if real == stage or stage in real.parents:
            real.mkdir(parents=True, exist_ok=True)
            return RunFolder(f.path / real.relative_to(stage), real, owner, _outer=f)
        if real == top or top in real.parents:
            rel = real.relative_to(top)
            (f.stage / rel).mkdir(parents=True, exist_ok=True)
            return RunFolder(path, f.stage / rel, owner, _live_root=path, _outer=f)
    return None


@contextlib.contextmanager
def run_folder(
    out: str | os.PathLike[str], owner: str, *, complete: bool = True, option: str = "--out"
) -> Iterator[RunFolder]:
    """Write a command's files into ``out`` whole (module docstring): yields the
    :class:`RunFolder` whose ``stage`` the files go to; they replace the folder's earlier ones
    when the block ends without an exception. ``complete``: this run writes all of ``owner``'s
    files, so those of its earlier run it did not write again are removed (False: it adds to
    them). ConfigError, before anything is written, when the folder cannot be written or
    another run is writing there (``option`` names it)."""
    path = check_out(out, option)
    view = _nested(path, owner)
    if view is not None:
        yield view
        return
    text = os.fspath(out)
    try:
        made = _makedirs(path)
    except OSError as exc:
        raise _os_error(option, text, exc) from None
    committed = False
    try:
        try:
            fd = _lock(path, option, text)
        except OSError as exc:
            raise _os_error(option, text, exc) from None
        try:
            _recover(path)
            try:
                stage = Path(tempfile.mkdtemp(prefix=STAGE_PREFIX, dir=path))
            except OSError as exc:
                raise _os_error(option, text, exc) from None
            folder = RunFolder(path, stage, owner, _live_root=path)
            _OPEN.folders.append(folder)
            try:
                with _sigterm_interrupts():
                    try:
                        yield folder
                    except OSError as exc:  # a full disk, say, while the files were staged
                        if not _writing(exc, path):
                            raise
                        raise _os_error(option, text, exc, "; its earlier files are unchanged") from None
                    raise_if_interrupted()  # a Ctrl-C that a library swallowed still stops the run
                    try:
                        _commit(folder, complete)
                    except OSError as exc:
                        raise _os_error(option, text, exc) from None
                committed = True
            finally:
                _OPEN.folders.remove(folder)
                shutil.rmtree(stage, ignore_errors=True)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(path / LOCK)
            os.close(fd)
    finally:
        if not committed:
            for d in made:  # the folders this run made, left empty by its failure
                try:
                    d.rmdir()
                except OSError:
                    break


def save_whole(out: str | os.PathLike[str], owner: str, write: Callable[[Path], None]) -> Path:
    """``write(folder)`` into :func:`run_folder`'s staging folder for ``out``, its files replacing
    the folder's earlier ones of ``owner`` whole; return ``out``."""
    with run_folder(out, owner) as folder:
        write(folder.stage)
    return Path(out)
