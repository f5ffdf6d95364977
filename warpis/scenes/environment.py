"""An environment light as plain data: Mitsuba's lat-long radiance table and its rotation.

A ray that leaves the scene sees the environment's radiance in its direction ω.  warpis
holds the environment exactly as Mitsuba 3's ``envmap`` emitter holds it, so that the
lookup is Mitsuba's own (``EnvironmentMapEmitter::eval_spectrum``):

* ``texels`` is the (H, W) bitmap in warpis's one channel, times ``scale``: rows are
  latitudes, row j at θ = π j/(H − 1) from the local +y axis (the first row is the pole
  θ = 0, the last θ = π); columns are longitudes, column k centred at u = (k + ½)/W,
  and they wrap around (column W is column 0);
* ω is taken to the local frame, v = Rᵀ ω (``rotation`` R, the linear part of the
  emitter's ``to_world``), and to (u, v) = (atan2(v_x, −v_z)/2π, acos(v_y)/π);
* u is shifted by half a texel, u' = u − 1/(2W) taken modulo 1, and (u'W, v(H − 1)) is
  interpolated bilinearly between the four texels around it.

Mitsuba 3.9 stores the bitmap with a copy of its last column before the first and of its
first after the last, and looks up at u W + ½ in that table: the same values.
tests/test_environment.py holds the two lookups against each other.

A ``constant`` emitter is the same with every texel equal.  The grid's cells (between
rows j, j + 1 and columns i, i + 1) are what the ``envmap`` technique samples
(:mod:`warpis.kernels.environment`); :func:`cell_energies` integrates the bilinear
radiance over each exactly (docs/theory.md, "Environment lights").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import fail

__all__ = ["Environment", "cell_energies", "local_directions", "lookup"]

# The least bitmap Mitsuba's envmap accepts: 2 texels wide, 3 high.
MIN_ROWS, MIN_COLUMNS = 3, 2


@dataclass(frozen=True, eq=False)
class Environment:
    """Radiance arriving from infinitely far away, in Mitsuba's envmap layout (see above)."""

    texels: np.ndarray  # (H, W) float64 ≥ 0: radiance at the grid's nodes (columns wrap around)
    rotation: np.ndarray  # (3, 3) float64, orthogonal: world ← local (the emitter's to_world)
    kind: str = "envmap"  # "envmap" or "constant": how a source spelled it
    label: str = ""  # the file or element it came from, for notes
    grey: bool = True  # the same in every colour channel (channel y is then exact: mitsuba/__init__.py)
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        for name in ("texels", "rotation"):
            view = np.asarray(getattr(self, name), dtype=np.float64).view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__post_init__()

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the bitmap."""
        return self.texels.shape[1], self.texels.shape[0]

    @property
    def table(self) -> np.ndarray:
        """(H, W + 1): the texels with column 0 repeated after the last, so that every
        cell's four corners are neighbours (what the kernels read)."""
        return wrapped(self.texels)

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """(K,) radiance seen along each world direction of ``directions`` (K, 3)."""
        return lookup(self.table, local_directions(self.rotation, directions))

    @property
    def power(self) -> float:
        """∫ L dω over the sphere (exact for the bilinear table: :func:`cell_energies`)."""
        return float(cell_energies(self.table).sum())

    def brightest_share(self, fraction: float = 0.01) -> float:
        """The share of ∫ L dω that the brightest ``fraction`` of the bitmap's texels carry,
        each texel weighted by the solid angle of its latitude band."""
        height, width = self.texels.shape
        theta = np.pi * np.arange(height) / (height - 1)
        half = 0.5 * np.pi / (height - 1)
        band = (np.cos(np.clip(theta - half, 0, np.pi)) - np.cos(np.clip(theta + half, 0, np.pi))) * 2 * np.pi / width
        energy = (self.texels * band[:, None]).ravel()
        total = energy.sum()
        if total <= 0:
            return 0.0
        top = max(1, math.ceil(fraction * energy.size))
        return float(np.sort(energy)[-top:].sum() / total)

    def irradiance(self, normals: np.ndarray, points: int = 1 << 14) -> np.ndarray:
        """(R,) ∫ L(ω) max(0, n·ω) dω for unit ``normals`` (R, 3), with nothing in the way:
        a scale for each receiver (reference.py's floor), by a fixed Fibonacci-sphere rule."""
        i = np.arange(points) + 0.5
        z = 1.0 - 2.0 * i / points
        phi = i * math.pi * (3.0 - math.sqrt(5.0))
        s = np.sqrt(1.0 - z * z)
        dirs = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
        weight = self.radiance(dirs) * (4.0 * math.pi / points)
        return np.maximum(np.asarray(normals, dtype=np.float64) @ dirs.T, 0.0) @ weight


def local_directions(rotation: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """World directions (K, 3) in the environment's local frame: v = Rᵀ ω."""
    return np.asarray(directions, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64)


def wrapped(texels: np.ndarray) -> np.ndarray:
    """(H, W) texels → (H, W + 1), column 0 repeated at the end."""
    return np.concatenate([texels, texels[:, :1]], axis=1)


def lookup(texels: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Mitsuba's envmap lookup (module docstring) of local directions ``v`` (K, 3) in a
    wrapped table ``texels`` (H, W + 1)."""
    height, columns = texels.shape
    u = np.arctan2(v[:, 0], -v[:, 2]) / (2 * np.pi)
    t = np.arccos(np.clip(v[:, 1], -1.0, 1.0)) / np.pi
    u = u - 0.5 / (columns - 1)
    u = (u - np.floor(u)) * (columns - 1)
    t = (t - np.floor(t)) * (height - 1)  # Mitsuba wraps v too: only v = 1 exactly moves (to 0)
    i = np.minimum(u.astype(np.int64), columns - 2)
    j = np.minimum(t.astype(np.int64), height - 2)
    wu, wt = u - i, t - j
    top = (1 - wu) * texels[j, i] + wu * texels[j, i + 1]
    bottom = (1 - wu) * texels[j + 1, i] + wu * texels[j + 1, i + 1]
    return (1 - wt) * top + wt * bottom


def band_weights(height: int) -> tuple[np.ndarray, np.ndarray]:
    """(H − 1,) pairs I0, I1: ∫ over cell row j of (1 − s) sin θ dθ and s sin θ dθ, where
    s = (θ − θ_j)/Δθ runs from 0 at row j to 1 at row j + 1 (docs/theory.md)."""
    a = np.pi * np.arange(height - 1) / (height - 1)
    b = np.pi * np.arange(1, height) / (height - 1)
    mean_cos = (np.sin(b) - np.sin(a)) / (b - a)  # (1/Δθ) ∫ cos θ dθ over the band
    return np.cos(a) - mean_cos, mean_cos - np.cos(b)


def cell_energies(texels: np.ndarray) -> np.ndarray:
    """(H − 1, W) ∫ L dω over each cell of the wrapped table ``texels`` (H, W + 1), exactly
    for the bilinear L: the weights of the ``envmap`` technique's cells."""
    height, columns = texels.shape
    i0, i1 = band_weights(height)
    top = 0.5 * (texels[:-1, :-1] + texels[:-1, 1:])
    bottom = 0.5 * (texels[1:, :-1] + texels[1:, 1:])
    return (2 * np.pi / (columns - 1)) * (top * i0[:, None] + bottom * i1[:, None])


def check_environment(env: Environment, where: object) -> None:
    """The kernels' domain: a finite table of at least 3 rows × 2 columns of non-negative
    values, and a rotation."""
    t = env.texels
    if t.ndim != 2 or t.shape[0] < MIN_ROWS or t.shape[1] < MIN_COLUMNS:
        raise fail(where, f"environment: expected a table of at least {MIN_ROWS} rows and {MIN_COLUMNS} columns, "
                          f"got shape {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(t < 0) or np.any(t > 3.0e38):
        raise fail(where, "environment: its radiance must be finite, non-negative and within float32's range")
    r = env.rotation
    if r.shape != (3, 3) or not np.all(np.isfinite(r)) or not np.allclose(r.T @ r, np.eye(3), atol=1e-6):
        raise fail(where, "environment: its to_world must be a rotation (no scale or shear): warpis samples "
                          "directions in its frame")
