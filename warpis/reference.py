"""Ground truth F(x) per receiver: Lambert's closed form where exact, dense quadrature otherwise.

The closed form (``closed_form.irradiance_closed_form``) is exact for irradiance and
lambert receivers when no scene triangle meets any receiver–emitter pyramid.  Elsewhere
(occluders, Phong receivers) F is integrated by dense stratified sampling with the same
Warp integrand: ``QUADRATURE_REPLICAS`` independent jittered estimates of
``QUADRATURE_SAMPLES`` samples each, whose spread gives an honest standard error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from .closed_form import irradiance_closed_form
from .engine import run_trials, select_receivers
from .integrand import IRRADIANCE, LAMBERT
from .scene import Scene

QUADRATURE_SAMPLES = 4096
QUADRATURE_REPLICAS = 32
# A seed no estimator run uses by default, so reference and estimates are independent.
REFERENCE_SEED = 0x5EED


@dataclass(frozen=True)
class Reference:
    """The reference value of one receiver."""

    index: int
    value: float
    stderr: float
    method: str  # "closed-form" or "quadrature"
    samples: int  # 0 for the closed form

    def as_dict(self) -> dict:
        return asdict(self)


def quadrature_estimator(scene: Scene, receiver: int) -> str:
    """The estimator used to integrate one receiver densely: light + BSDF where glossy."""
    if int(scene.receivers.material[receiver]) in (int(IRRADIANCE), int(LAMBERT)):
        return "jittered:single:light-solid-angle"
    return "jittered:balance:light-solid-angle+phong"


def reference(
    scene: Scene,
    receivers: Sequence[int] | None = None,
    samples: int = QUADRATURE_SAMPLES,
    replicas: int = QUADRATURE_REPLICAS,
    seed: int = REFERENCE_SEED,
) -> list[Reference]:
    """Reference values for the chosen receivers (default: all), with standard errors.

    Parameters
    ----------
    scene
        A loaded scene.
    receivers
        Receiver indices; default all.
    samples, replicas
        Quadrature: jittered samples per replica and independent replicas.
    seed
        Seed of the quadrature's random numbers.
    """
    idx = select_receivers(scene, receivers)
    rx = scene.receivers
    shading = rx.positions[idx] + scene.data.ray_eps * rx.normals[idx]
    diffuse = np.isin(rx.material[idx], [int(IRRADIANCE), int(LAMBERT)])
    values, exact = irradiance_closed_form(shading, rx.normals[idx], scene.triangle_vertices(), scene.emission)
    scale = np.where(rx.material[idx] == int(LAMBERT), rx.albedo[idx] / np.pi, 1.0)
    out: dict[int, Reference] = {}
    for i, r in enumerate(idx):
        if diffuse[i] and exact[i]:
            out[int(r)] = Reference(int(r), float(values[i] * scale[i]), 0.0, "closed-form", 0)
    todo = [int(r) for r in idx if int(r) not in out]
    for spec in sorted({quadrature_estimator(scene, r) for r in todo}):
        group = [r for r in todo if quadrature_estimator(scene, r) == spec]
        est = run_trials(scene, spec, samples, replicas, seed=seed, receivers=group)
        for r, row in zip(group, est):
            out[r] = Reference(r, float(row.mean()), float(row.std(ddof=1) / np.sqrt(len(row))), "quadrature",
                               samples * replicas)
    return [out[int(r)] for r in idx]
