"""The quadrature's evaluate kernel: f and every technique's pdf at dense points of a square.

:mod:`warpis.analysis.quadrature` builds exact variances and moments from what this
kernel returns at dense jittered points of each technique's primary-sample square
(docs/theory.md, "Exact variance of any estimator: independent blocks" and "Reference
moments").  It is a kernel over the technique dispatch, as the trial kernel is:
:func:`make_evaluate_kernel` builds it over any dispatch (the built-in one here, one that
also knows the user techniques in :mod:`warpis.kernels.registered`).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .device import ReceiverData, SceneData
from .integrand import integrand, shading_point
from .precompiled import compile_portably
from .techniques import LightTable, sample_direction, technique_pdf

compile_portably(__name__)  # shipped compiled: precompiled.py says why portably


def make_evaluate_kernel(sample_direction: Any, technique_pdf: Any, module: Any) -> Any:
    """The evaluate kernel over the technique dispatch ``sample_direction``/``technique_pdf``,
    in the Warp module ``module`` (None: this one)."""

    @wp.kernel(module=module, enable_backward=False)
    def evaluate_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, receivers: wp.array(dtype=wp.int32),
                        techs: wp.array(dtype=wp.int32), k: wp.int32, u: wp.array(dtype=wp.vec2), every: wp.int32,
                        f_out: wp.array2d(dtype=wp.float64), pdf_out: wp.array3d(dtype=wp.float64)):
        """f and every technique's pdf at the direction technique k maps u[j] to, seen
        from receiver receivers[i].

        Unless ``every`` is set, f is found first and the pdfs only where it is > 0: ψ is
        0 wherever f is, and a light pdf (a traversal of the emitters) costs more than the
        shadow ray.  With ``every`` (optimal MIS, whose ψ is non-zero where f is 0) the
        pdfs are found at every sample.  A sample whose own pdf is 0 (a failed sample) has
        f = 0 and every pdf 0, as in the estimators.
        """
        i, j = wp.tid()
        sp = shading_point(scene, recv, receivers[i])
        w = sample_direction(techs[k], scene, table, sp, u[j])
        f = float(0.0)
        own = float(0.0)
        if wp.length_sq(w) > 0.0:
            if every != 0:
                own = technique_pdf(techs[k], scene, table, sp, w)
                if own > 0.0:
                    f = integrand(scene, sp, w)
            else:
                f = integrand(scene, sp, w)
                if f > 0.0:
                    own = technique_pdf(techs[k], scene, table, sp, w)
        if own <= 0.0:
            f = float(0.0)
        for t in range(techs.shape[0]):
            g = own
            if t != k and own > 0.0:
                g = technique_pdf(techs[t], scene, table, sp, w)
            pdf_out[i, j, t] = wp.float64(g)
        f_out[i, j] = wp.float64(f)

    return evaluate_kernel


evaluate_kernel = make_evaluate_kernel(sample_direction, technique_pdf, None)
