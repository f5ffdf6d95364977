"""Output folders of ``warpis study``, ``demo`` and ``verify --out``: one writer at a time, atomic files.

* :func:`locked` takes an exclusive, non-blocking ``flock`` on ``OUT/.lock`` for a whole
  run (the file records the holder's PID), so a second run on the same folder stops at
  once with a one-line error instead of racing the first one's files.
* :func:`replacing` and :func:`write_text` write a file under a unique temporary name
  beside it and :func:`os.replace` it into place, so a reader (or a run killed at any
  moment) sees the old file or the new one, never half of one; the temporary file is
  removed on any failure.
* Every ``OSError`` while writing (a full disk, a read-only or missing folder) becomes a
  :class:`~warpis.errors.WarpisError` reading ``<path>: cannot write: <strerror>``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .. import files
from ..errors import WarpisError

LOCK_NAME = ".lock"
TMP_SUFFIX = files.TMP_SUFFIX
# Temporary names of warpis versions before the lock; a run holding the lock removes them.
LEGACY_TMP = ("results.csv.tmp", "summary.json.tmp", "report.md.tmp", "verify.json.tmp")

# Folders this process holds locked (resolved path → depth), so that verify() inside
# cmd_verify, both taking the lock, do not lock each other out: flock conflicts between
# two open files of one process too.
_held: dict[str, int] = {}


def cannot_write(path: Path | str, exc: OSError) -> WarpisError:
    """The one-line error for a failed write (``exc.strerror`` may be None for odd errors)."""
    return WarpisError(f"{path}: cannot write: {exc.strerror or exc}")


def out_option(text: str | None, option: str = "--out") -> Path | None:
    """An ``--out`` value as a Path (None when not given); an empty one is an error, not ``.``."""
    if text is None:
        return None
    if text == "":
        raise WarpisError(f"{option}: must name a directory, got an empty string")
    return Path(text)


def make_dir(path: Path) -> None:
    """``mkdir -p path``, or a one-line error (a regular file in the way, /proc, no permission)."""
    if path.exists() and not path.is_dir():
        raise WarpisError(f"{path}: the output must be a directory, and this is a file")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise cannot_write(path, exc) from None


@contextlib.contextmanager
def locked(out: Path) -> Iterator[Path]:
    """Create ``out`` if needed and hold its lock while the block runs.

    A folder this call created is removed again when the block fails before anything
    but the lock file was written, so bad input leaves nothing behind.
    """
    out = Path(out)
    key = os.path.realpath(out)
    if key in _held:
        _held[key] += 1
        try:
            yield out
        finally:
            _held[key] -= 1
        return
    created = not out.exists()
    make_dir(out)
    fd = _acquire(out)
    _held[key] = 1
    ok = False
    try:
        _sweep(out)
        yield out
        ok = True
    finally:
        del _held[key]
        _release(out, fd, remove=created and not ok)


def _acquire(out: Path) -> int:
    lock = out / LOCK_NAME
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise cannot_write(lock, exc) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = _holder(fd) if exc.errno in (errno.EAGAIN, errno.EACCES) else None
        os.close(fd)
        if exc.errno not in (errno.EAGAIN, errno.EACCES):
            raise WarpisError(f"{lock}: cannot lock: {exc.strerror or exc}") from None
        who = f"pid {holder}" if holder else "a process that has not yet written its pid"
        raise WarpisError(f"{out}: in use by another warpis run ({who}); wait for it to finish or choose "
                          f"another --out") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    except OSError as exc:
        os.close(fd)
        raise cannot_write(lock, exc) from None
    return fd


def _holder(fd: int) -> str | None:
    """The PID in a lock file held by another process (it writes it just after locking)."""
    for _ in range(20):
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        if text.isdigit():
            return text
        time.sleep(0.01)
    return None


def _release(out: Path, fd: int, remove: bool) -> None:
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)  # no stale PID for the next reader
    if remove:  # a folder this run created and left empty: bad input leaves no trace
        with contextlib.suppress(OSError):
            if os.listdir(out) == [LOCK_NAME]:
                os.unlink(out / LOCK_NAME)
                os.rmdir(out)
    os.close(fd)  # closing drops the flock


def _sweep(out: Path) -> None:
    """Remove temporary files of runs killed mid-write (none can be live: we hold the lock)."""
    for folder in (out, out / "figures"):
        with contextlib.suppress(OSError):
            for entry in os.scandir(folder):
                if entry.is_file() and (entry.name.endswith(TMP_SUFFIX) or entry.name in LEGACY_TMP):
                    with contextlib.suppress(OSError):
                        os.unlink(entry.path)


@contextlib.contextmanager
def replacing(path: Path) -> Iterator[IO[bytes]]:
    """A binary file to write ``path``'s new content into; on success it replaces ``path``
    (:func:`warpis.files.replacing`: atomic, flushed to disk, no temporary file left on a
    failure, ``path`` as it was).  Any ``OSError`` is the one-line :func:`cannot_write`."""
    try:
        with files.replacing(path) as fh:
            yield fh
    except OSError as exc:
        raise cannot_write(path, exc) from None


def _write(fh: IO[bytes], data: bytes) -> None:
    """The one place text files reach the disk (tests make it fail as a full disk would)."""
    fh.write(data)


def write_text(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` (UTF-8) atomically; a one-line error when it cannot be written."""
    with replacing(path) as fh:
        _write(fh, text.encode("utf-8"))
