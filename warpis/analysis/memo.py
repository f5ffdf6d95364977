"""Theory results kept on disk by content, so that the next process reuses them.

An exact variance or a receiver's reference moments costs seconds of dense quadrature
(most of a study's time beside its trials: a cold ``warpis demo`` spends about 30 s on
moments and predictions, both cores busy, against 17 s of trials), and depends on nothing
but its inputs.  So each is
kept in ``cache_dir()/theory/`` (``WARPIS_CACHE_DIR``, else ``~/.cache/warpis``), in a
JSON file named by the SHA-256 of everything it depends on:

* the scene's digest (equal digests mean equal results: :attr:`Scene.digest`) and the
  Warp device it ran on (CPU and GPU round differently);
* what was asked: the quantity and every argument, floats spelled exactly (``repr``);
* the code that computes it: every source file of the warpis package, and the versions
  of warp-lang and numpy (the kernels' compiler, the quadrature's random points).

A changed scene, argument, warpis file, Warp or numpy is another name, never a stale
answer.  Techniques and patterns registered from Python (whose code the package hash does
not see) are never kept: :func:`keepable` says so.  Floats round-trip exactly through
JSON, so a kept result is bit-identical to a computed one.  A file that cannot be read or
does not decode is computed again and replaced; one that cannot be written only costs the
next computation.  Clearing the folder is always safe.

Each version of the code keeps its results in a folder of its own,
``theory/<first 16 hex digits of code_digest()>/``.  The first process of a version to
use the folder marks it used and removes all but the ``KEEP_CODES`` most recently used
ones (and any file of the flat layout of earlier warpis versions), so editing warpis
or moving between releases never grows the cache past a few versions' results.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import warp as wp

from .. import files
from ..kernels.bvh import cache_dir
from ..kernels.patterns import user_patterns
from ..kernels.techniques import user_techniques

T = TypeVar("T")

_FORMAT = "warpis theory 1"  # a new encoding gets a new number
PACKAGE = Path(__file__).resolve().parents[1]


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 of every ``.py`` file of the warpis package (paths and contents) and of the
    versions of warp-lang and numpy: what the kept results were computed by."""
    h = hashlib.sha256(_FORMAT.encode())
    for path in sorted(PACKAGE.rglob("*.py")):
        h.update(path.relative_to(PACKAGE).as_posix().encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes()).digest())
    h.update(f"warp-lang {wp.config.version} numpy {np.__version__}".encode())
    return h.hexdigest()


def keepable(techniques: tuple[str, ...], pattern: str | None = None) -> bool:
    """Whether results over these techniques (and pattern) may be kept: none of them was
    registered from Python, whose code the package's digest does not cover."""
    user = {u.name for u in user_techniques()} | {u.name for u in user_patterns()}
    return not user.intersection(techniques) and pattern not in user


def kept_path(quantity: str, digest: str, device: str, args: tuple) -> Path:
    """The file of one result: ``theory/<code>/<quantity>-<SHA-256 of its inputs>.json``."""
    code = code_digest()
    key = repr((_FORMAT, quantity, digest, device, args, code))
    folder = code_folder(cache_dir() / "theory", code[:16])
    return folder / f"{quantity}-{hashlib.sha256(key.encode()).hexdigest()[:40]}.json"


KEEP_CODES = 4  # code versions whose results stay: a few branches or releases in turn
_CODE_NAME = re.compile(r"[0-9a-f]{16}")


@functools.lru_cache(maxsize=8)
def code_folder(theory: Path, code: str) -> Path:
    """``theory/<code>``, the folder of one code version's results, marked used; the first
    call per process (per cache folder and code) also prunes the others (:data:`KEEP_CODES`)."""
    folder = theory / code
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)  # used now, whether this process reads or writes
        _prune(theory, folder)
    except OSError:
        pass  # a cache that cannot be written only costs computations (kept)
    return folder


def _prune(theory: Path, current: Path) -> None:
    """Remove the code folders beyond the KEEP_CODES most recently used (never ``current``)
    and the result files of the flat layout.  Another process may be using a folder this
    one removes: it then finds no file, or cannot write one, and computes (kept)."""
    folders, flat = [], []
    for entry in os.scandir(theory):
        if entry.is_dir(follow_symlinks=False) and _CODE_NAME.fullmatch(entry.name):
            folders.append((entry.stat(follow_symlinks=False).st_mtime, entry.path))
        elif entry.is_file(follow_symlinks=False) and entry.name.endswith(".json"):
            flat.append(entry.path)
    older = sorted((f for f in folders if f[1] != str(current)), reverse=True)[KEEP_CODES - 1:]
    for _, path in older:
        shutil.rmtree(path, ignore_errors=True)
    for path in flat:
        try:
            os.unlink(path)
        except OSError:
            pass


def kept(path: Path, compute: Callable[[], T], encode: Callable[[T], Any], decode: Callable[[Any], T]) -> T:
    """The result stored at ``path`` (:func:`kept_path`), else ``compute()``, stored there."""
    value = read(path, decode)
    if value is None:
        value = compute()
        keep(path, value, encode)
    return value


def read(path: Path, decode: Callable[[Any], T]) -> T | None:
    """The result stored at ``path``, or None where there is none that decodes."""
    try:
        return decode(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError, KeyError, IndexError):
        return None  # absent, unreadable or another layout: the caller computes it again


def keep(path: Path, value: T, encode: Callable[[T], Any]) -> None:
    """Store ``value`` at ``path``; a cache that cannot be written only costs the next computation."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with files.replacing(path, durable=False) as fh:  # a reader sees no file or the whole file
            fh.write(json.dumps(encode(value)).encode())
    except OSError:
        pass
