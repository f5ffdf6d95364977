"""Techniques and combiners written as batched numpy functions, for ``warpis check``.

For code that is not Warp: a technique is ``sample(n, wo, u) -> w`` (or ``(w, pdf)``, the
density the sampler reports) and ``pdf(n, wo, w) -> p`` over arrays — n, wo (K, 3) the
normal and the direction towards the viewer, u (K, 2) in [0, 1), w (K, 3) unit directions
(a zero or non-finite row: no sample) — with, optionally, ``eval(n, wo, w) -> f``, (K,)
or (K, C): the BSDF × |cos θ| the technique is meant to sample, which adds the checks of
a BSDF.  A combiner is ``weights(pdfs) -> w``: the pdfs (K, T) of T techniques at K
directions → the weight (K, T) each technique's sample gets there.

They are checked on the host by the same harness as Warp techniques.  Estimators do not
take them: a trial runs in Warp kernels without per-sample Python.  So their names join
``TECHNIQUES`` / ``COMBINERS`` only as names known elsewhere (``Registry.elsewhere``),
and an estimator spec that uses one gets a line saying so instead of "unknown".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..errors import WarpisError
from ..kernels.estimators import COMBINERS
from ..kernels.techniques import TECHNIQUES


@dataclass(frozen=True)
class NumpyTechnique:
    """A technique as numpy functions (see the module docstring)."""

    name: str
    sample: Callable[..., Any]
    pdf: Callable[..., Any]
    eval: Callable[..., Any] | None = None
    description: str = "a numpy technique"


@dataclass(frozen=True)
class NumpyCombiner:
    """A combiner's weights as a numpy function of the techniques' pdfs (K, T) → (K, T)."""

    name: str
    weights: Callable[..., Any]
    description: str = "a numpy combiner"


NUMPY_TECHNIQUES: dict[str, NumpyTechnique] = {}
NUMPY_COMBINERS: dict[str, NumpyCombiner] = {}


def _check_name(kind: str, name: Any, taken: Any) -> None:
    if not isinstance(name, str) or not name or any(c in name for c in ":+, "):
        raise WarpisError(f"{kind} {name!r}: a name must be a non-empty string without ':', '+', ',' or spaces")
    if name in taken:
        raise WarpisError(f"{kind} {name!r} is already registered")


def _check_callables(kind: str, name: str, functions: dict[str, Any]) -> None:
    for role, f in functions.items():
        if not callable(f):
            raise WarpisError(f"{kind} {name!r}: {role} must be a function, got {type(f).__name__}")


def register_numpy_technique(name: str, sample: Callable[..., Any], pdf: Callable[..., Any], *,
                             eval: Callable[..., Any] | None = None,
                             description: str = "a numpy technique") -> NumpyTechnique:
    """Register a technique written as batched numpy functions, for ``warpis check``.

    ``sample(n, wo, u)`` returns w (K, 3), or (w, pdf) when the sampler knows its
    density; ``pdf(n, wo, w)`` returns (K,); the optional ``eval(n, wo, w)`` returns the
    BSDF × |cos θ| (K,) or (K, C) it is meant for.  Estimators do not take it (their
    trials run in Warp, with no per-sample Python); ``warpis.register_technique`` takes a
    Warp pair for that.
    """
    _check_name("technique", name, set(TECHNIQUES) | set(NUMPY_TECHNIQUES))
    roles = {"sample": sample, "pdf": pdf, **({"eval": eval} if eval is not None else {})}
    _check_callables("technique", name, roles)
    entry = NumpyTechnique(name, sample, pdf, eval, str(description))
    NUMPY_TECHNIQUES[name] = entry
    TECHNIQUES.elsewhere[name] = (
        f"technique {name!r} is a numpy technique (warpis.register_numpy_technique): 'warpis check' tests it on "
        f"the host, but estimators run Warp techniques only, so that no per-sample Python enters a trial; "
        f"register a Warp sample/pdf pair (warpis.register_technique) to estimate with it")
    return entry


def unregister_numpy_technique(name: str) -> None:
    """Remove a technique added by :func:`register_numpy_technique`."""
    if name not in NUMPY_TECHNIQUES:
        raise WarpisError(f"technique {name!r} was not added by register_numpy_technique")
    del NUMPY_TECHNIQUES[name]
    TECHNIQUES.elsewhere.pop(name, None)


def register_numpy_combiner(name: str, weights: Callable[..., Any], *,
                            description: str = "a numpy combiner") -> NumpyCombiner:
    """Register MIS weights ``weights(pdfs) -> w`` ((K, T) → (K, T)) for ``warpis check``,
    which holds them to a partition of unity; estimators do not take them."""
    _check_name("combiner", name, set(COMBINERS) | set(NUMPY_COMBINERS))
    _check_callables("combiner", name, {"weights": weights})
    entry = NumpyCombiner(name, weights, str(description))
    NUMPY_COMBINERS[name] = entry
    COMBINERS.elsewhere[name] = (
        f"combiner {name!r} is a numpy combiner (warpis.register_numpy_combiner): 'warpis check' tests its "
        f"weights, but estimators run the kernels' combiners only, so that no per-sample Python enters a trial")
    return entry


def unregister_numpy_combiner(name: str) -> None:
    """Remove a combiner added by :func:`register_numpy_combiner`."""
    if name not in NUMPY_COMBINERS:
        raise WarpisError(f"combiner {name!r} was not added by register_numpy_combiner")
    del NUMPY_COMBINERS[name]
    COMBINERS.elsewhere.pop(name, None)
