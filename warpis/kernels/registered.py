"""The kernels of the registry as it stands: built in, or rebuilt once around the user's code.

Five kernels dispatch on technique or pattern codes: the trial and pilot kernels
(:mod:`~warpis.kernels.estimators`), the sample and pdf kernels behind
``sample_directions``/``direction_pdf`` (:mod:`~warpis.kernels.techniques`) and the
quadrature's evaluate kernel (:mod:`~warpis.kernels.evaluate`).  With no user technique
or pattern registered they are the built-in kernels, shipped compiled.  A registered one
is Warp code of the user's, so each of the five is rebuilt around it — and all five go
into **one** Warp module per registered set.  Warp compiles a module as one translation
unit, and these kernels share nearly all their code (the integrand, the materials, the
ray queries): one module compiles in little more than the trial kernel's time alone,
once, for whatever a command or session runs next, where modules of their own each
compiled that shared code again.  A technique of the ``warpis check`` gallery on the
2-core box: the trial (with the pilot), sample, pdf and evaluate kernels took 28–30 s as
four modules and take 16–20 s as one; ``warpis check`` needed three of those modules and
``study`` and ``verify`` two (trial and evaluate, 22–27 s), where one module serves all.
The price: a command that runs the trial kernel alone (``estimate``) compiles the others
with it, 19–23 s against 16–19 s for the trial kernel's module alone.

The module is named by its content hash, as Warp names a ``module="unique"`` one, so
Warp's kernel cache finds it again in the next process, and a process that registers the
same code again runs the kernels it already loaded.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from typing import Any

import warp as wp

from .estimators import make_trial_kernel, pilot_kernel, trial_kernel
from .evaluate import evaluate_kernel, make_evaluate_kernel
from .patterns import point_dispatch, user_patterns
from .precompiled import compile_portably
from .techniques import (dispatch, make_numpy_kernels, pdf_kernel, register_numpy_kernels, sample_kernel, sampler,
                         user_techniques)
from ..vocabulary import UserEntry


@dataclass(frozen=True)
class RegisteredKernels:
    """The five kernels that dispatch on technique or pattern codes, for one registered set."""

    trial: Any
    pilot: Any
    sample: Any
    pdf: Any
    evaluate: Any

    @property
    def all(self) -> tuple[Any, ...]:
        return (self.trial, self.pilot, self.sample, self.pdf, self.evaluate)


BUILT_IN = RegisteredKernels(trial_kernel, pilot_kernel, sample_kernel, pdf_kernel, evaluate_kernel)

# Two lookups: _kernels_for's cache by registry entries (fast, but an entry registered
# again is a new key), and _by_module by content, so that the same code registered again
# runs the kernels this process already built and loaded.
_lock = threading.Lock()
_by_module: dict[str, RegisteredKernels] = {}  # module name (its content hash) → its kernels, this process's


def registered_kernels() -> RegisteredKernels:
    """The kernels that know every registered technique and pattern (the built-in ones
    when none is registered)."""
    return _kernels_for(user_techniques(), user_patterns())


@functools.lru_cache(maxsize=None)
def _kernels_for(user: tuple[UserEntry, ...], user_points: tuple[UserEntry, ...]) -> RegisteredKernels:
    if not user and not user_points:
        return BUILT_IN
    with _lock:
        module = wp.Module("warpis_registered", None)
        compile_portably(module)  # one object for every CPU that shares the kernel cache
        sample_direction, technique_pdf = dispatch(user)
        trial, pilot = make_trial_kernel(sample_direction, technique_pdf, point_dispatch(user_points), module)
        if user:  # the other three know techniques only: user patterns alone leave them built in
            sample, pdf = make_numpy_kernels(sampler(user), technique_pdf, module)
            evaluate = make_evaluate_kernel(sample_direction, technique_pdf, module)
        else:
            sample, pdf, evaluate = BUILT_IN.sample, BUILT_IN.pdf, BUILT_IN.evaluate
        # Named before anything loads it: Warp's cache folder is the name and the hash.
        module.name = f"warpis_registered_{module.get_module_hash().hex()[:8]}"
        return _by_module.setdefault(module.name, RegisteredKernels(trial, pilot, sample, pdf, evaluate))


def _numpy_pair() -> tuple[Any, Any]:
    kernels = registered_kernels()
    return kernels.sample, kernels.pdf


register_numpy_kernels(_numpy_pair)
