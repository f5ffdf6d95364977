"""What the kernels can represent, checked in one place.

Every count (samples N, trials M, quadrature samples, receivers, grid resolutions,
threads), every seed and every float that reaches a Warp kernel passes through one of
the functions here, from the command line, a scene or study file, or the Python API.
A value the kernels cannot hold exactly is refused with a one-line
:class:`~warpis.errors.WarpisError` naming where it came from, never truncated,
wrapped or silently rounded:

* counts index int32 loops and arrays in the kernels, so they must lie in
  [1, 2^31 − 1] (``MAX_COUNT``);
* seeds feed the 32-bit counter-based generator, so they lie in [0, 2^32);
* radiance, albedo and Phong exponents are float32 in the kernels, so they must be 0
  or lie in float32's normal range [2^-126, ``MAX_VALUE``] (a subnormal loses digits, an
  overflow turns into inf and then NaN);
* coordinates are float32 in the kernels and are squared there (distances, areas), so
  their magnitude is at most ``MAX_COORDINATE``.

Also here, because every floor needs them: the number of CPU threads a run uses
(``default_threads``) and the check of a Warp device name (``check_device``).
"""

from __future__ import annotations

import math
import numbers
import os
import re
from collections.abc import Iterable
from typing import Any

import numpy as np

from .errors import WarpisError

MAX_COUNT = 2**31 - 1
SEED_LIMIT = 2**32
FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # 2^-126, the smallest normal float32
# Largest radiance, albedo or exponent: products of two such values (radiance × BRDF ×
# cosine / pdf) must stay finite in float32 (max 3.4e38).
MAX_VALUE = 1e18
# Largest coordinate magnitude: squared distances and triangle areas (~ coordinate²)
# must stay finite and normal in float32.
MAX_COORDINATE = 1e15
# An analytic sphere's radius relative to its centre's distance from the origin: below
# 2^-16 (128 float32 ulps) a ray's float32 origin and direction cannot resolve it.
SPHERE_MIN_RELATIVE_RADIUS = 2.0**-16


def _integral(value: Any) -> int | None:
    """``value`` as an int when it is an integer (bool excluded), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, numbers.Integral):
        return int(value)
    return None


def count(value: Any, what: str, minimum: int = 1, maximum: int = MAX_COUNT) -> int:
    """An integer count in [minimum, maximum], or a one-line error naming ``what``.

    ``4.7``, ``True``, ``"4"`` and ``2**31`` are all refused: nothing is truncated or
    wrapped into the kernels' int32.
    """
    n = _integral(value)
    if n is None:
        raise WarpisError(f"{what}: expected an integer, got {value!r}")
    if n < minimum:
        raise WarpisError(f"{what}: must be at least {minimum}, got {n}")
    if n > maximum:
        raise WarpisError(f"{what}: must be at most {maximum:,} (the kernels count in 32-bit integers), got {n:,}")
    return n


def count_text(text: str, what: str, minimum: int = 1, maximum: int = MAX_COUNT) -> int:
    """A count written as text (an option or environment variable): digits only."""
    stripped = text.strip()
    if not stripped or not (stripped.isdigit() or (stripped[0] in "+-" and stripped[1:].isdigit())):
        raise WarpisError(f"{what}: expected an integer, got {text!r}")
    return count(int(stripped), what, minimum, maximum)


def receiver_list_text(text: str, what: str = "--receivers") -> list[int]:
    """Comma-separated receiver indices written as text: each a count from 0; a one-line
    WarpisError for an empty list, a non-integer or a negative index."""
    parts = [t.strip() for t in text.split(",") if t.strip()]
    if not parts:
        raise WarpisError(f"{what} is empty")
    out = [count_text(t, what, minimum=-MAX_COUNT) for t in parts]
    negative = [i for i in out if i < 0]
    if negative:
        raise WarpisError(f"{what}: receiver {negative[0]} does not exist (indices start at 0)")
    return out


def seed(value: Any, what: str = "seed") -> int:
    """A seed of the counter-based generator: an integer in [0, 2^32)."""
    s = _integral(value)
    if s is None:
        raise WarpisError(f"{what}: expected an integer in [0, 2^32), got {value!r}")
    if not 0 <= s < SEED_LIMIT:
        raise WarpisError(f"{what}: must be in [0, 2^32), got {s}")
    return s


def receiver_indices(values: Iterable[Any] | int, what: str, size: int) -> np.ndarray:
    """Receiver indices, integers in [0, size), as int32 (never truncated: 1.5 is refused).

    One integer is one receiver (``3`` is ``[3]``); a string, a bool or anything else that
    is not a sequence of integers is refused, naming ``what``.
    """
    if _integral(values) is not None or (isinstance(values, np.ndarray) and values.ndim == 0):
        values = [values.item() if isinstance(values, np.ndarray) else values]
    elif isinstance(values, (str, bytes, bool)) or not isinstance(values, Iterable):
        raise WarpisError(f"{what}: expected receiver indices (an integer or a sequence of integers), "
                          f"got {values!r}")
    out = []
    for v in values:
        i = _integral(v)
        if i is None:
            raise WarpisError(f"{what}: indices must be integers, got {v!r}")
        if not 0 <= i < size:
            raise WarpisError(f"{what}: receiver {i} does not exist (there are {size}: 0–{size - 1})")
        out.append(i)
    if not out:
        raise WarpisError(f"{what}: no index given")
    return np.asarray(out, dtype=np.int32)


def float32_value(value: float, what: str) -> float:
    """A non-negative value that float32 kernels hold without overflow or lost digits.

    Zero is allowed; anything else must lie in [2^-126, ``MAX_VALUE``].
    """
    if not math.isfinite(value) or value < 0:
        raise WarpisError(f"{what}: must be a finite number >= 0, got {value!r}")
    if value != 0 and not FLOAT32_TINY <= value <= MAX_VALUE:
        raise WarpisError(f"{what}: {value!r} is outside the range the float32 kernels compute in "
                          f"(0, or {FLOAT32_TINY:.3g} to {MAX_VALUE:.0e})")
    return float(value)


def float32_values(values: np.ndarray, what: str) -> None:
    """:func:`float32_value` for every entry of an array; the first bad entry is named."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    with np.errstate(invalid="ignore"):
        ok = (v == 0) | ((v >= FLOAT32_TINY) & (v <= MAX_VALUE))  # False for NaN
    if not ok.all():
        i = int(np.argmin(ok))
        float32_value(float(v[i]), f"{what}[{i}]")


def coordinates(points: np.ndarray, what: str) -> None:
    """Refuse NaN/inf or coordinates beyond ``MAX_COORDINATE`` (float32 kernels square them)."""
    if points.size == 0:
        return
    finite = np.isfinite(points)
    if not finite.all():
        bad = int(np.argmax(~finite.reshape(len(points), -1).all(axis=1)))
        raise WarpisError(f"{what}: point {bad} is NaN or infinite")
    big = np.abs(points).max(axis=-1) > MAX_COORDINATE
    if big.any():
        bad = int(np.argmax(big))
        raise WarpisError(f"{what}: point {bad} has a coordinate of magnitude {np.abs(points[bad]).max():.3g}, "
                          f"beyond the {MAX_COORDINATE:.0e} that float32 kernels can square; rescale the scene")


def available_memory() -> int:
    """Bytes of memory available to a new allocation (MemAvailable, else physical memory)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 1 << 34


def memory(needed: float, what: str) -> None:
    """Refuse up front a job whose arrays would need more than half the available memory."""
    have = available_memory()
    if needed > have / 2:
        raise WarpisError(f"{what}: would need about {needed / 2**30:.3g} GiB of memory, more than half the "
                          f"{have / 2**30:.3g} GiB available")


def default_threads() -> int:
    """Worker threads for CPU launches: ``WARPIS_THREADS`` or the number of usable cores."""
    env = os.environ.get("WARPIS_THREADS")
    if env:
        return count_text(env, "WARPIS_THREADS")
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def check_device(device: str, what: str = "device") -> str:
    """``device`` if it names a Warp device of this machine (cpu, cuda, cuda:N), else a
    one-line error saying which devices exist."""
    name = str(device)
    if name == "cpu":
        return name
    match = re.fullmatch(r"cuda(?::(\d+))?", name)
    if match is None:
        raise WarpisError(f"{what} {name!r}: unknown device (valid: cpu, cuda, cuda:N)")
    import warp as wp  # only a CUDA name needs Warp: the limits stay under the kernels

    count = wp.get_cuda_device_count()
    if count == 0:
        raise WarpisError(f"{what} {name!r}: this machine has no CUDA device (use cpu)")
    ordinal = int(match.group(1) or 0)
    if ordinal >= count:
        raise WarpisError(f"{what} {name!r}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return name
