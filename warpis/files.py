"""Files replaced whole, the one way warpis writes a file that another process may read.

The new content goes to a unique temporary name beside the target (``os.replace`` is
atomic only within one filesystem), then is renamed over it, so a reader, or a process
killed at any moment, sees the old file or the whole new one, never half of one.  On any
failure the temporary file is removed and the failure goes on to the caller: output
folders turn an ``OSError`` into a one-line error (:mod:`warpis.runs.outdir`), caches
into one more computation (BVHs, theory results, the shipped kernels' copies).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

TMP_SUFFIX = ".warpis-tmp"  # the end of every temporary name (a killed run's leftovers are found by it)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once: os.umask can only be read by setting it, which is not thread-safe.
_UMASK = _umask()


@contextlib.contextmanager
def replacing(path: Path | str, durable: bool = True) -> Iterator[IO[bytes]]:
    """A binary file to write ``path``'s new content into; when the block ends without an
    exception it replaces ``path``.  ``durable`` flushes it to disk first (results a user
    keeps; a cache, which can always be computed again, need not wait for the disk)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TMP_SUFFIX)
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
            if durable:
                fh.flush()
                os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; these are ordinary shareable files
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
