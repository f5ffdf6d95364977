"""Delta lights as plain data: what each point, spot or directional light sends to each receiver.

A delta light (Mitsuba's ``point``, ``spot``, ``directional``) lights a receiver x from
one direction ω only, so its part of F is not an integral but one term,

    D(x) = Σ_l E_l(x) · ρ(ω_l) · max(0, n·ω_l) · V(x, ω_l, t_l),

with E_l the irradiance the light casts at x on a surface facing it (intensity ×
falloff / t² for a point or spot light at distance t, the irradiance of a directional
light, t = ∞), ρ and n the receiver's BRDF and shading normal, and V whether the
segment (or, for t = ∞, the ray) is free.  A scene source fills the table below at its
receivers (the Mitsuba source asks Mitsuba's own ``sample_direction``, so intensity,
falloff and the spot's cone are Mitsuba's); the kernels add ρ, the cosine and
visibility (:func:`warpis.kernels.integrand.delta_terms`), once per receiver, and every
estimate of F carries D: it has no variance (docs/theory.md, "Delta lights").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import fail

__all__ = ["DeltaLights", "check_delta_lights"]

KINDS = ("point", "spot", "directional")


@dataclass(frozen=True, eq=False)
class DeltaLights:
    """L delta lights seen from R receivers (numpy, read-only)."""

    labels: tuple[str, ...]  # (L,) how the source names each light
    kinds: tuple[str, ...]  # (L,) one of KINDS
    directions: np.ndarray  # (R, L, 3) float64, unit: from the receiver towards the light
    distances: np.ndarray  # (R, L) float64 > 0: to the light; inf for a directional light
    irradiance: np.ndarray  # (R, L) float64 ≥ 0: E_l at the receiver on a surface facing the light
    grey: bool = True  # the same in every colour channel

    def __post_init__(self) -> None:
        for name in ("directions", "distances", "irradiance"):
            view = np.asarray(getattr(self, name), dtype=np.float64).view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__post_init__()

    def __len__(self) -> int:
        return len(self.labels)


def check_delta_lights(delta: DeltaLights, receivers: int, where: object) -> None:
    """The kernels' domain: one row per receiver, unit directions, positive distances
    (inf only for directional lights) and finite, non-negative irradiance."""
    count = len(delta.labels)
    if len(delta.kinds) != count or any(k not in KINDS for k in delta.kinds):
        raise fail(where, f"delta lights: kinds must be one of {', '.join(KINDS)}, one per light")
    if delta.directions.shape != (receivers, count, 3) or delta.distances.shape != (receivers, count) \
            or delta.irradiance.shape != (receivers, count):
        raise fail(where, f"delta lights: expected directions ({receivers}, {count}, 3) and distances and "
                          f"irradiance ({receivers}, {count}), got {delta.directions.shape}, "
                          f"{delta.distances.shape}, {delta.irradiance.shape}")
    if not np.all(np.isfinite(delta.directions)) or \
            not np.allclose(np.linalg.norm(delta.directions, axis=-1), 1.0, atol=1e-6):
        raise fail(where, "delta lights: directions must be finite unit vectors")
    infinite = np.array([k == "directional" for k in delta.kinds], bool)
    d = delta.distances
    if np.any(~(d > 0)) or np.any(np.isinf(d) != infinite[None, :]) or np.any(np.isnan(d)):
        raise fail(where, "delta lights: distances must be > 0, and infinite exactly for directional lights")
    e = delta.irradiance
    if not np.all(np.isfinite(e)) or np.any(e < 0) or np.any(e > 3.0e38):
        raise fail(where, "delta lights: irradiance must be finite, non-negative and within float32's range")
