"""Counter-based random numbers: every draw is a pure function of its coordinates.

A uniform number is a hash of (seed, receiver, trial, technique, sample, dimension), so
results are bit-identical whatever the thread count, batch size, receiver order or
device, and different seeds give independent streams.  The mixer is Wellons'
``lowbias32`` (an avalanche-tested 32-bit permutation), chained once per coordinate.
"""

from __future__ import annotations

import numpy as np
import warp as wp

_M1 = wp.constant(wp.uint32(0x7FEB352D))
_M2 = wp.constant(wp.uint32(0x846CA68B))
_GOLDEN = wp.constant(wp.uint32(0x9E3779B9))
_S15 = wp.constant(wp.uint32(15))
_S16 = wp.constant(wp.uint32(16))
_S8 = wp.constant(wp.uint32(8))
_INV_2_24 = wp.constant(1.0 / 16777216.0)


@wp.func
def mix32(x: wp.uint32) -> wp.uint32:
    """lowbias32: a bijective 32-bit mixer with low avalanche bias."""
    x = x ^ (x >> _S16)
    x = x * _M1
    x = x ^ (x >> _S15)
    x = x * _M2
    x = x ^ (x >> _S16)
    return x


@wp.func
def chain(h: wp.uint32, value: wp.int32) -> wp.uint32:
    """Fold one coordinate into a running hash (golden-ratio offset keeps 0s apart)."""
    return mix32(h ^ (wp.uint32(value) + _GOLDEN + (h << _S8)))


@wp.func
def stream(seed: wp.uint32, receiver: wp.int32, trial: wp.int32, technique: wp.int32) -> wp.uint32:
    """The hash of the coordinates that stay fixed within one technique of one trial."""
    h = mix32(seed ^ _GOLDEN)
    h = chain(h, receiver)
    h = chain(h, trial)
    return chain(h, technique)


@wp.func
def uniform(s: wp.uint32, sample: wp.int32, dim: wp.int32) -> float:
    """A uniform float in [0, 1) on a 2^-24 lattice, from a stream and (sample, dim)."""
    h = chain(chain(s, sample), dim)
    return float(h >> _S8) * _INV_2_24


# --------------------------------------------------------------------------- numpy twin


def _mix32_np(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.uint32)
    x ^= x >> np.uint32(16)
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def _chain_np(h: np.ndarray, value: np.ndarray) -> np.ndarray:
    v = np.asarray(value).astype(np.int64).astype(np.uint32)
    return _mix32_np(h ^ (v + np.uint32(0x9E3779B9) + (h << np.uint32(8))))


def uniform_np(seed: int, receiver, trial, technique, sample, dim) -> np.ndarray:
    """The numpy twin of :func:`stream` + :func:`uniform` (for tests and baselines)."""
    with np.errstate(over="ignore"):
        h = _mix32_np(np.uint32(seed) ^ np.uint32(0x9E3779B9))
        for v in (receiver, trial, technique, sample, dim):
            h = _chain_np(h, v)
    return (h >> np.uint32(8)).astype(np.float64) / 16777216.0
