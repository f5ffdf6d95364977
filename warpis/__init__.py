"""warpis: the variance of Monte Carlo direct-illumination estimators on real mesh scenes.

Warp kernels cast light-sampling and BSDF-sampling rays against trimesh-loaded geometry;
the variance measured over many independent trials is held against closed forms.
"""

from __future__ import annotations

import warp as wp

# Warp's start-up banner and per-module load lines would drown the tool's own output.
if hasattr(wp, "LOG_WARNING"):
    wp.config.log_level = wp.LOG_WARNING
else:  # pragma: no cover - warp-lang before the logging API
    wp.config.quiet = True

from .errors import WarpisError  # noqa: E402
from .version import __version__  # noqa: E402
from .scenes import Scene, bundled_scenes, load_scene  # noqa: E402
from .scenes.environment import Environment  # noqa: E402
from .kernels.engine import run_moments, run_trials  # noqa: E402
from .kernels import camera as _camera  # noqa: E402,F401  (registers the camera's ray cast)
from .kernels.integrand import ShadingPoint  # noqa: E402
from .kernels.patterns import register_pattern, unregister_pattern  # noqa: E402
from .kernels.rng import uniform  # noqa: E402
from .kernels.techniques import register_technique, unregister_technique  # noqa: E402
from .stats import variance_interval  # noqa: E402
from .analysis import quadrature as _quadrature  # noqa: E402,F401  (registers the optimal oracle's solver)
from .check.entries import (register_numpy_combiner, register_numpy_technique,  # noqa: E402
                            unregister_numpy_combiner, unregister_numpy_technique)

__all__ = ["Environment", "Scene", "ShadingPoint", "WarpisError", "bundled_scenes", "load_scene",
           "register_numpy_combiner", "register_numpy_technique", "register_pattern", "register_technique",
           "run_moments", "run_trials", "uniform", "unregister_numpy_combiner", "unregister_numpy_technique",
           "unregister_pattern", "unregister_technique", "variance_interval", "__version__"]
