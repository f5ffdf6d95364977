"""Every BSDF of a Mitsuba 3 XML file as a subject of ``warpis check``, through Mitsuba itself.

The BSDFs are Mitsuba's own objects in its vectorised ``llvm_ad_rgb`` variant: ``sample``,
``eval`` and ``pdf`` run on Dr.Jit arrays of a million directions at once, no per-sample
Python.  Each is seen in the frames of the file's receivers that lie on a shape carrying
it (a ray down each receiver's normal finds its surface interaction: uv, shading frame),
the view of each receiver as ``wi``; a BSDF on no receiver's shape (or every BSDF, for a
file without a receivers file) is seen at a spread of views in a plain frame, uv (½, ½).
All directions are local to the shading frame (normal +z).

A sample is *produced* when Mitsuba reports a density and either a non-zero weight or a
non-zero ``pdf`` at its direction: Mitsuba marks a failed sample (a reflection below the
horizon) by a zero weight, and a black BSDF's samples have a zero weight but a density.

Dr.Jit's LLVM backend needs libLLVM 19 (``DRJIT_LIBLLVM_PATH``, or the system's
``libLLVM.so.19*``); an older one aborts the process that compiles a kernel, so the
variant is first tried in a child process (:func:`mitsuba_unusable`).
"""

from __future__ import annotations

import functools
import glob
import importlib.util
import math
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import WarpisError
from .subjects import Draw, Frame, Subject

VARIANT = "llvm_ad_rgb"
LLVM_GLOB = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19*"
# Spread views: θi from 0 to this (in a plain frame), when no receiver sees the BSDF.
SPREAD_MAX_DEGREES = 80.0
# Mitsuba BSDF classes whose f(a → b) = f(b → a) (reflection only; refraction scales
# radiance by η² one way): their nesting (twosided) keeps the claim.
RECIPROCAL = {"SmoothDiffuse", "RoughConductor", "RoughPlastic", "TwoSidedBRDF"}
_NAMES = {"SmoothDiffuse": "diffuse", "RoughConductor": "roughconductor", "RoughPlastic": "roughplastic",
          "TwoSidedBRDF": "twosided", "RoughDielectric": "roughdielectric", "Principled": "principled"}
_SMOKE = ("import mitsuba as mi, drjit as dr; mi.set_variant('llvm_ad_rgb'); "
          "x = dr.maximum(mi.Float([1.0, 2.0]), dr.opaque(mi.Float, 1.5)); dr.eval(x); print('ok')")


def llvm_library() -> str | None:
    """``DRJIT_LIBLLVM_PATH``, else the first system ``libLLVM.so.19*`` (exported, so that
    Dr.Jit and a child process load it), else None."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path:
        return path
    found = sorted(glob.glob(LLVM_GLOB))
    if not found:
        return None
    os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    return found[0]


@functools.lru_cache(maxsize=1)
def mitsuba_unusable() -> str | None:
    """None when Mitsuba's llvm_ad_rgb variant runs a kernel here, else why not (one line)."""
    if importlib.util.find_spec("mitsuba") is None:
        return 'Mitsuba is not installed: pip install "warpis[mitsuba]"'
    lib = llvm_library()
    if lib is None:
        return f"Mitsuba's {VARIANT} variant needs libLLVM 19: set DRJIT_LIBLLVM_PATH (nothing matches {LLVM_GLOB})"
    try:
        res = subprocess.run([sys.executable, "-c", _SMOKE], capture_output=True, text=True, timeout=300, check=False)
    except subprocess.TimeoutExpired:
        return f"Mitsuba's {VARIANT} variant did not start within 300 s"
    if res.returncode == 0 and res.stdout.strip().endswith("ok"):
        return None
    lines = [ln.strip() for ln in (res.stderr + res.stdout).splitlines() if ln.strip()]
    llvm = [ln for ln in lines if ln.startswith("LLVM ERROR")]
    why = (llvm or lines or ["no output"])[0 if llvm else -1][:200]
    return f"Mitsuba's {VARIANT} variant does not run with DRJIT_LIBLLVM_PATH={lib}: {why}"


@contextmanager
def llvm_variant(mi: Any) -> Iterator[SimpleNamespace]:
    """Inside: Mitsuba's variant is llvm_ad_rgb; yields the classes the frames use, which
    keep working after the caller's variant is back."""
    before = mi.variant()
    mi.set_variant(VARIANT)
    try:
        ml = getattr(mi, VARIANT)
        yield SimpleNamespace(mi=mi, Float=ml.Float, UInt32=ml.UInt32, Point2f=ml.Point2f, Point3f=ml.Point3f,
                              Vector3f=ml.Vector3f, Ray3f=ml.Ray3f, Frame3f=ml.Frame3f, ShapePtr=ml.ShapePtr,
                              SI=ml.SurfaceInteraction3f, Context=mi.BSDFContext, Flags=mi.BSDFFlags)
    finally:
        if before is not None:
            mi.set_variant(before)


def _checked_file(path: str) -> Path:
    file = Path(path)
    if file.is_dir():
        raise WarpisError(f"--bsdfs {path}: is a directory, not a Mitsuba XML file")
    if not file.is_file():
        raise WarpisError(f"--bsdfs {path}: no such file")
    if file.suffix.lower() != ".xml":
        raise WarpisError(f"--bsdfs {path}: not a Mitsuba scene (expected a .xml file)")
    return file


def bsdf_subjects(path: str, frames: int, receivers_file: str | None = None) -> list[Subject]:
    """A subject per BSDF of the Mitsuba file ``path`` (see the module docstring)."""
    file = _checked_file(path)
    problem = mitsuba_unusable()
    if problem is not None:
        raise WarpisError(f"--bsdfs {path}: {problem}")
    receivers = _receivers(file, receivers_file)
    import mitsuba as mi

    with llvm_variant(mi) as ns:
        try:
            scene = mi.load_file(str(file), parallel=False, optimize=False)
        except Exception as exc:  # Mitsuba's own message, first line
            first = str(exc).strip().splitlines()
            raise WarpisError(f"--bsdfs {path}: Mitsuba cannot load it: {first[0] if first else exc}") from None
        groups = _bsdfs(scene)
        at = _receiver_interactions(ns, scene, receivers) if receivers is not None else None
    subjects = []
    for key, (bsdf, shapes) in groups.items():
        subjects.append(_subject(ns, key, bsdf, shapes, at, frames))
    if not subjects:
        raise WarpisError(f"--bsdfs {path}: no shape of the file carries a BSDF")
    return subjects


def _receivers(file: Path, receivers_file: str | None) -> Any:
    """The warpis scene's receivers (positions, normals, views), or None without a receivers file."""
    from ..scenes import load_scene
    from ..scenes.mitsuba.receivers import receivers_path

    sidecar = Path(receivers_file) if receivers_file is not None else receivers_path(file)
    if not sidecar.is_file():
        if receivers_file is not None:
            raise WarpisError(f"--receivers-file {receivers_file}: no such file")
        return None
    return load_scene(str(file), receivers=str(sidecar) if receivers_file is not None else None).receivers


def _bsdfs(scene: Any) -> dict[str, tuple[Any, list[Any]]]:
    """BSDF key → (the BSDF, the shapes carrying it), a BSDF shared by id counted once."""
    out: dict[str, tuple[Any, list[Any]]] = {}
    for k, shape in enumerate(scene.shapes()):
        bsdf = shape.bsdf()
        if bsdf is None:
            continue
        key = bsdf.id() or shape.id() or f"shape {k}"
        out.setdefault(key, (bsdf, []))[1].append(shape)
    return out


def _receiver_interactions(ns: SimpleNamespace, scene: Any, rx: Any) -> dict[str, Any]:
    """Each receiver's surface interaction (a ray down its normal) and the shape it hit."""
    p = np.asarray(rx.positions, np.float64)
    n = np.asarray(rx.normals, np.float64)
    bbox = scene.bbox()
    diag = float(np.linalg.norm(np.array(bbox.max) - np.array(bbox.min)))
    eps = 1e-4 * max(diag, 1e-30)
    o = (p + eps * n).astype(np.float32)
    d = (-n).astype(np.float32)
    ray = ns.Ray3f(ns.Point3f(o[:, 0], o[:, 1], o[:, 2]), ns.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    si = scene.ray_intersect(ray)
    hit = np.array(si.is_valid(), dtype=bool).reshape(-1)
    shapes = np.full(len(p), -1)
    for k, shape in enumerate(scene.shapes()):
        shapes[np.array(si.shape == ns.ShapePtr(shape), dtype=bool).reshape(-1) & hit] = k
    return {"si": si, "shape": shapes, "view": np.asarray(rx.view, np.float64),
            "names": [rx.group_names[g] for g in rx.group] if rx.group_names else [""] * len(p),
            "shapes": list(scene.shapes())}


def _label(key: str, bsdf: Any) -> str:
    text = str(bsdf)
    cls = bsdf.class_name()
    kind = _NAMES.get(cls, cls)
    parts = [kind]
    dist = re.search(r"distribution = (\w+)", text)
    alpha = re.search(r"alpha(?:_u)? = (?:UniformSpectrum\[value=)?\[([\d.eE+-]+)\]", text)
    if dist:
        parts.append(dist.group(1))
    if alpha:
        parts.append(f"α={float(alpha.group(1)):g}")
    if "sample_visible = 0" in text:
        parts.append("all normals")
    return f"{key} ({' '.join(parts)})"


def _claims_reciprocity(ns: SimpleNamespace, bsdf: Any) -> bool:
    classes = set(re.findall(r"(\w+)\[", str(bsdf))) | {bsdf.class_name()}
    classes -= {"UniformSpectrum", "SRGBReflectanceSpectrum", "SRGBSpectrum", "BitmapTexture", "Checkerboard",
                "MeshAttribute", "value"}
    transmits = bool(bsdf.flags() & (ns.Flags.GlossyTransmission | ns.Flags.DiffuseTransmission))
    return classes <= RECIPROCAL and not transmits


def _subject(ns: SimpleNamespace, key: str, bsdf: Any, shapes: list[Any], at: dict[str, Any] | None,
             frames: int) -> Subject:
    label = _label(key, bsdf)
    if bsdf.flags() & ns.Flags.Delta:
        return Subject("Mitsuba BSDF", label, [], notes=[f"{label}: not checked: a delta lobe has no density"])
    reciprocal = _claims_reciprocity(ns, bsdf)
    mine: list[int] = []
    if at is not None:
        ids = {at["shapes"].index(s) for s in shapes if s in at["shapes"]}
        mine = [int(r) for r in np.flatnonzero(np.isin(at["shape"], list(ids)))]
    out = []
    if mine:
        assert at is not None
        for r in _spread_by_angle(ns, at, mine, frames):
            si = _gather(ns, at["si"], r)
            view = at["view"][r].astype(np.float32)
            si.wi = si.to_local(ns.Vector3f(*map(float, view)))
            name = at["names"][r]
            out.append(_frame(ns, bsdf, si, f"receiver {r}" + (f" ({name})" if name else ""), reciprocal))
        note = f"{label}: frames of {len(out)} of its {len(mine)} receivers"
    else:
        for deg in np.linspace(0.0, SPREAD_MAX_DEGREES, frames) if frames > 1 else [45.0]:
            out.append(_frame(ns, bsdf, _plain(ns, math.radians(deg)), f"view θi = {deg:.0f}°", reciprocal))
        note = f"{label}: a spread of {len(out)} views (no receiver lies on it)"
    return Subject("Mitsuba BSDF", label, out, notes=[note])


def _spread_by_angle(ns: SimpleNamespace, at: dict[str, Any], receivers: list[int], frames: int) -> list[int]:
    """At most ``frames`` of ``receivers``, spread over their angle of view."""
    n = np.array(ns.Vector3f(at["si"].sh_frame.n)).reshape(3, -1).T[receivers]
    cos_i = np.abs(np.sum(n * at["view"][receivers], axis=1))
    order = [receivers[i] for i in np.argsort(-cos_i, kind="stable")]
    if len(order) <= frames:
        return order
    return [order[int(round(x))] for x in np.linspace(0, len(order) - 1, frames)]


def _gather(ns: SimpleNamespace, si: Any, r: int) -> Any:
    import drjit as dr

    return dr.gather(ns.SI, si, ns.UInt32(r))


def _plain(ns: SimpleNamespace, theta: float) -> Any:
    """A surface interaction in a plain frame (normal +z, uv (½, ½)) seen from θi."""
    import drjit as dr

    si = dr.zeros(ns.SI)
    si.sh_frame = ns.Frame3f(ns.Vector3f(0.0, 0.0, 1.0))
    si.n = ns.Vector3f(0.0, 0.0, 1.0)
    si.uv = ns.Point2f(0.5, 0.5)
    si.wi = ns.Vector3f(math.sin(theta), 0.0, math.cos(theta))
    return si


def _vec(ns: SimpleNamespace, d: NDArray) -> Any:
    d = np.ascontiguousarray(d, dtype=np.float32)
    return ns.Vector3f(d[:, 0], d[:, 1], d[:, 2])


def _rows(value: Any, width: int) -> NDArray:
    """A Dr.Jit 3-vector or colour of ``width`` lanes as a (width, 3) float64 array."""
    a = np.array(value, dtype=np.float64).reshape(3, -1)
    return np.broadcast_to(a, (3, width)).T.copy()


def _frame(ns: SimpleNamespace, bsdf: Any, si: Any, label: str, reciprocal: bool) -> Frame:
    ctx = ns.Context()

    def pdf(dirs: NDArray) -> NDArray:
        if len(dirs) == 0:
            return np.zeros(0)
        return np.array(bsdf.pdf(ctx, si, _vec(ns, dirs)), dtype=np.float64).reshape(-1)

    def eval_(dirs: NDArray) -> NDArray:
        if len(dirs) == 0:
            return np.zeros((0, 3))
        return _rows(bsdf.eval(ctx, si, _vec(ns, dirs)), len(dirs))

    def draw(count: int, seed: int) -> Draw:
        u = np.random.default_rng(seed).random((count, 3), dtype=np.float32)
        bs, w = bsdf.sample(ctx, si, ns.Float(u[:, 0]), ns.Point2f(u[:, 1], u[:, 2]))
        wo = _rows(bs.wo, count)
        reported = np.array(bs.pdf, dtype=np.float64).reshape(-1)
        weight = _rows(w, count)
        at_wo = pdf(wo)
        produced = (reported > 0.0) & np.all(np.isfinite(wo), axis=1) & np.isfinite(reported)
        produced &= np.any(weight != 0.0, axis=1) | (at_wo > 0.0)
        dirs = np.where(produced[:, None], wo / np.linalg.norm(np.where(produced[:, None], wo, 1.0), axis=1)[:, None],
                        0.0)
        return Draw(dirs, produced, np.where(produced, reported, 0.0), weight)

    frame = Frame(label, np.array([0.0, 0.0, 1.0]), draw, pdf, eval=eval_)
    if reciprocal:
        frame.reciprocity = lambda count, seed: _pairs(ns, bsdf, si, ctx, count, seed)
    return frame


def _pairs(ns: SimpleNamespace, bsdf: Any, si: Any, ctx: Any, count: int, seed: int) -> tuple[NDArray, NDArray]:
    """f(a → b) and f(b → a) (eval / cos of the outgoing direction): a uniform on the upper
    hemisphere (cos θ ≥ 0.05), b the BSDF's own sample from a, where f is large."""
    rng = np.random.default_rng([seed, 0xEC1])
    u = rng.random((count, 5), dtype=np.float32)
    z = 0.05 + 0.95 * u[:, 0]
    r = np.sqrt(1.0 - z * z)
    a = np.stack([r * np.cos(2 * math.pi * u[:, 1]), r * np.sin(2 * math.pi * u[:, 1]), z], axis=1)
    from_a = type(si)(si)
    from_a.wi = _vec(ns, a)
    bs, w = bsdf.sample(ctx, from_a, ns.Float(u[:, 2]), ns.Point2f(u[:, 3], u[:, 4]))
    b = _rows(bs.wo, count)
    ok = (b[:, 2] > 0.05) & np.any(_rows(w, count) != 0.0, axis=1)
    a, b = a[ok], b[ok]
    if len(a) == 0:  # a black BSDF: no sample has a weight, f is 0 at every pair
        return np.zeros((0, 3)), np.zeros((0, 3))
    from_a = type(si)(si)
    from_a.wi = _vec(ns, a)
    from_b = type(si)(si)
    from_b.wi = _vec(ns, b)
    ab = _rows(bsdf.eval(ctx, from_a, _vec(ns, b)), len(b)) / b[:, 2:3]
    ba = _rows(bsdf.eval(ctx, from_b, _vec(ns, a)), len(a)) / a[:, 2:3]
    return ab, ba
