"""``warpis check``: every applicable check on one subject, a verdict table and a figure per check.

Subjects: a technique (Warp, built in or registered with ``warpis.register_technique``;
or batched numpy functions registered with :func:`register_numpy_technique`), every BSDF
of a Mitsuba 3 XML file (through Mitsuba's own ``sample``, ``eval`` and ``pdf``), or a
combiner's weights (:func:`register_numpy_combiner`, or a built-in combiner's).  The
checks are in :mod:`.checks`, what they look at in :mod:`.subjects` and
:mod:`.mitsuba_bsdfs`, the run and its family-wise level in :mod:`.run`, the table, the
figures and ``index.html`` in :mod:`.report`.  docs/check.md shows them at work.
"""

from __future__ import annotations

from .checks import CHECKS, Verdict
from .entries import (NUMPY_COMBINERS, NUMPY_TECHNIQUES, NumpyCombiner, NumpyTechnique, register_numpy_combiner,
                      register_numpy_technique, unregister_numpy_combiner, unregister_numpy_technique)
from .run import Budget, CheckRun

__all__ = ["Budget", "CHECKS", "CheckRun", "NUMPY_COMBINERS", "NUMPY_TECHNIQUES", "NumpyCombiner", "NumpyTechnique",
           "Verdict", "register_numpy_combiner", "register_numpy_technique", "unregister_numpy_combiner",
           "unregister_numpy_technique"]
