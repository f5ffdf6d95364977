"""BSDFs → materials: ``diffuse`` → lambert, ``roughconductor`` → roughconductor,
``roughplastic`` → roughplastic, each alone or inside ``twosided``.

A conductor keeps its three channels of ``eta`` and ``k``, and ``specular`` holds each
channel's weight (see :mod:`warpis.kernels.shading`).  A shape with any other BSDF is an
occluder only (its :class:`Material` holds the error a receiver on it raises).  A texture
on a reflectance (or a roughconductor's alpha) is kept, to be evaluated by Mitsuba at each
receiver (:mod:`.receivers`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ...errors import WarpisError, fail
from ...vocabulary import DISTRIBUTIONS
from ..description import MICROFACET_DEFAULTS, MIN_ALPHA
from .parse import is_grey, object_fields, object_parameters, rgb_text, to_rgb

# Eta below which a conductor's Fresnel term is 1 to float32's precision: Mitsuba's
# material "none" (eta = 0, k = 1, a perfect mirror) becomes eta = NONE_ETA, whose
# Fresnel term is within 2e-6 of 1 at every angle.
NONE_ETA = 1e-6
SUPPORTED_BSDFS = ("diffuse, roughconductor and roughplastic (uniform or textured reflectances, and a uniform or "
                   "textured roughconductor alpha), alone or inside twosided (the same BSDF on both sides), on a "
                   "shape that holds receivers (a shape without receivers may have any BSDF: it only blocks light, "
                   "as in Mitsuba's direct integrator)")
_BSDF_PLUGINS = {"SmoothDiffuse": "diffuse", "RoughConductor": "roughconductor", "RoughPlastic": "roughplastic",
                 "TwoSided": "twosided", "TwoSidedBRDF": "twosided", "SmoothDielectric": "dielectric",
                 "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
                 "SmoothConductor": "conductor", "SmoothPlastic": "plastic", "BlendBSDF": "blendbsdf",
                 "MaskBSDF": "mask", "Mask": "mask", "BumpMap": "bumpmap", "NormalMap": "normalmap", "Principled": "principled",
                 "PrincipledThin": "principledthin", "Null": "null", "Hair": "hair", "PolarizedPlastic": "pplastic",
                 "LinearPolarizer": "polarizer", "LinearRetarder": "retarder", "Measured": "measured",
                 "MeasuredPolarized": "measured_polarized"}
_TEXTURE_PLUGINS = {"BitmapTexture": "bitmap", "Checkerboard": "checkerboard", "MeshAttribute": "mesh_attribute",
                    "VolumeTexture": "volume"}

# Mitsuba's spectra that are one value over the whole surface (in scalar_rgb).
_UNIFORM = {"UniformSpectrum", "SRGBReflectanceSpectrum", "SRGBEmitterSpectrum", "SRGBSpectrum"}


@dataclass
class Material:
    """A receiver's material in warpis's terms, as read from one Mitsuba BSDF."""

    kind: str  # MATERIALS name
    text: str  # how it reads in notes
    albedo: float = 0.0
    alpha: float = MICROFACET_DEFAULTS["alpha"]
    distribution: int = MICROFACET_DEFAULTS["distribution"]
    sample_visible: int = MICROFACET_DEFAULTS["sample_visible"]
    eta: np.ndarray = field(default_factory=lambda: np.full(3, MICROFACET_DEFAULTS["eta"]))
    k: np.ndarray = field(default_factory=lambda: np.full(3, MICROFACET_DEFAULTS["k"]))
    specular: np.ndarray = field(default_factory=lambda: np.full(3, MICROFACET_DEFAULTS["specular"] / 3))
    specular_weight: float = MICROFACET_DEFAULTS["specular_weight"]
    twosided: bool = False
    grey: bool = True  # the same in every colour channel
    # A BSDF warpis cannot shade: the one-line error a receiver on it raises, and the
    # BSDF's name; "" for one it shades.  Such a shape is an occluder only.
    problem: str = ""
    unshaded: str = ""
    # Parameters given by a texture, evaluated at each receiver: "albedo", "specular" or
    # "alpha" → the Mitsuba Texture objects it comes from (alpha: alpha_u and alpha_v, or
    # alpha), and how each reads in notes.  The field itself holds NaN until then.
    textures: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    texture_text: dict[str, str] = field(default_factory=dict)
    weights: Any = None  # the channel's weights, for textured colours

    def same(self, other: Material) -> bool:
        """The same material (a textured parameter: the same texture)."""
        def equal(a: Any, b: Any) -> bool:
            return bool(np.array_equal(a, b, equal_nan=True))
        return (self.kind == other.kind and equal(self.albedo, other.albedo) and equal(self.alpha, other.alpha)
                and self.distribution == other.distribution and self.sample_visible == other.sample_visible
                and equal(self.eta, other.eta) and equal(self.k, other.k) and equal(self.specular, other.specular)
                and self.specular_weight == other.specular_weight and self.texture_text == other.texture_text)

    def check(self, where: str) -> None:
        """The kernels' domain for this material's parameters (textured ones: see receivers._texture_values)."""
        if (self.kind in ("roughconductor", "roughplastic") and "alpha" not in self.textures
                and not MIN_ALPHA <= self.alpha <= 1e3):
            raise fail(where, f"{self.kind} alpha={self.alpha:g}: warpis supports roughness in [{MIN_ALPHA:g}, 1000]")
        if not (np.all(self.eta > 0) and np.all(self.eta <= 1e3) and np.all(self.k >= 0) and np.all(self.k <= 1e3)):
            raise fail(where, f"{self.kind} eta={rgb_text(self.eta)} k={rgb_text(self.k)}: warpis supports eta in "
                              f"(0, 1000] and k in [0, 1000]")
        specular_ok = "specular" in self.textures or (np.all(self.specular >= 0) and np.all(self.specular <= 1e3))
        if not (specular_ok and ("albedo" in self.textures or 0 <= self.albedo <= 1e3)):
            raise fail(where, f"{self.kind}: reflectances must lie in [0, 1000] in every channel")


def texture_name(text: str) -> str:
    """The plugin name of a texture from Mitsuba's description of it."""
    cls = text.split("[")[0].strip()
    return _TEXTURE_PLUGINS.get(cls, cls)


def _uniform(fields: dict[str, str], name: str, where: str, plugin: str) -> bool:
    """Whether the parameter ``name`` is given (a uniform value); a texture is an error."""
    text = fields.get(name)
    if text is None:
        return False
    if text.split("[")[0].strip() not in _UNIFORM:
        raise fail(where, f"{plugin}: its {name} is a {texture_name(text)!r} texture; warpis supports only uniform "
                          f"values")
    return True


def uniform_colour(fields: dict[str, str], params: dict[str, Any], name: str, where: str, plugin: str,
                   default: float | None = None) -> np.ndarray:
    """A uniform spectrum parameter of a BSDF or emitter as linear sRGB (3,)."""
    if not _uniform(fields, name, where, plugin):
        if default is not None:
            return np.full(3, default)
        raise fail(where, f"{plugin}: cannot read its {name}")
    value = params.get(f"{name}.value", params.get(name))
    if value is None:
        raise fail(where, f"{plugin}: cannot read its {name}")
    rgb = to_rgb(value)
    if not np.all(np.isfinite(rgb)):
        raise fail(where, f"{plugin}: its {name} {rgb.tolist()} is not finite")
    return rgb


def _scalar(params: dict[str, Any], name: str, where: str, plugin: str) -> float:
    if name not in params:
        raise fail(where, f"{plugin}: cannot read its {name}")
    return float(params[name])


def _microfacet_options(fields: dict[str, str], where: str, plugin: str) -> tuple[int, int]:
    distribution = fields.get("distribution", "")
    if distribution not in DISTRIBUTIONS:
        raise fail(where, f"{plugin}: distribution {distribution!r}; warpis supports {', '.join(DISTRIBUTIONS)}")
    visible = fields.get("sample_visible", "")
    if visible not in ("0", "1"):
        raise fail(where, f"{plugin}: cannot read sample_visible ({visible!r})")
    return DISTRIBUTIONS[distribution], int(visible)


def _options_text(m: Material) -> str:
    name = next(d for d, code in DISTRIBUTIONS.items() if code == m.distribution)
    alpha = "" if "alpha" in m.textures else f" alpha={m.alpha:.6g}"
    return f"{name}{alpha} ({'visible normals' if m.sample_visible else 'all normals'})"


def _children(mi: Any, obj: Any) -> dict[str, Any]:
    """The Mitsuba objects ``obj`` holds (its textures, nested BSDFs), by parameter name."""
    found: dict[str, Any] = {}

    class Children(mi.TraversalCallback):
        def put(self, name: str, value: Any, flags: Any, *rest: Any) -> None:
            if isinstance(value, mi.Object):
                found[name] = value

    obj.traverse(Children())
    return found


def _textured(fields: dict[str, str], name: str) -> bool:
    """Whether the parameter ``name`` is given by a texture (not a uniform value)."""
    text = fields.get(name)
    return text is not None and text.split("[")[0].strip() not in _UNIFORM


def _texture(fields: dict[str, str], objects: dict[str, Any], name: str) -> Any:
    """The Texture object of the parameter ``name`` if it is not uniform (a texture warpis
    evaluates at each receiver), else None."""
    return objects.get(name) if _textured(fields, name) else None


def _one_bsdf(cls: str, fields: dict[str, str], params: dict[str, Any], where: str, weights: np.ndarray,
              notes: list[str], objects: dict[str, Any] | None = None) -> Material:
    """One (not twosided) Mitsuba BSDF → a warpis material.  A texture on a reflectance,
    or on a roughconductor's alpha, is kept (``textures``) to be evaluated at each receiver."""
    plugin = _BSDF_PLUGINS.get(cls, cls)
    objects = objects or {}
    if cls == "SmoothDiffuse":
        tex = _texture(fields, objects, "reflectance")
        if tex is not None:
            name = texture_name(fields["reflectance"])
            return Material("lambert", f"diffuse reflectance from a {name!r} texture", albedo=math.nan,
                            textures={"albedo": (tex,)}, texture_text={"albedo": fields["reflectance"]},
                            grey=False)  # not known to be grey: channel y's note then applies
        rgb = uniform_colour(fields, params, "reflectance", where, plugin)
        albedo = float(weights @ rgb)
        return Material("lambert", f"diffuse albedo={albedo:.6g}", albedo=albedo, grey=is_grey(rgb))
    if cls == "RoughConductor":
        distribution, visible = _microfacet_options(fields, where, plugin)
        textures: dict[str, tuple[Any, ...]] = {}
        texture_text: dict[str, str] = {}
        if _textured(fields, "alpha_u") or _textured(fields, "alpha_v"):
            keys = ("alpha",) if "alpha" in objects else ("alpha_u", "alpha_v")
            if not all(key in objects for key in keys):
                raise fail(where, f"{plugin}: cannot read its alpha texture")
            textures["alpha"] = tuple(objects[key] for key in keys)
            texture_text["alpha"] = " / ".join(fields.get(n, "") for n in ("alpha_u", "alpha_v"))
            alpha_u = alpha_v = math.nan
        else:
            for name in ("alpha_u", "alpha_v"):
                if not _uniform(fields, name, where, plugin):
                    raise fail(where, f"{plugin}: cannot read its {name}")
            try:
                alpha_u, alpha_v = ((float(params["alpha.value"]),) * 2 if "alpha.value" in params else
                                    (float(params["alpha_u.value"]), float(params["alpha_v.value"])))
            except KeyError:
                raise fail(where, f"{plugin}: cannot read its alpha") from None
        if alpha_u != alpha_v and "alpha" not in textures:
            raise fail(where, f"{plugin}: anisotropic roughness alpha_u={alpha_u:.6g}, alpha_v={alpha_v:.6g}; "
                              f"warpis supports an isotropic alpha only")
        eta = uniform_colour(fields, params, "eta", where, plugin)
        k = uniform_colour(fields, params, "k", where, plugin)
        tex = _texture(fields, objects, "specular_reflectance")
        if tex is not None:
            textures["specular"] = (tex,)
            texture_text["specular"] = fields["specular_reflectance"]
            specular = np.full(3, math.nan)
        else:
            specular = uniform_colour(fields, params, "specular_reflectance", where, plugin, default=1.0)
        if np.any(eta == 0):
            notes.append(f"roughconductor eta=0 (Mitsuba's material \"none\" is eta=0, k=1, a perfect mirror) "
                         f"taken as eta={NONE_ETA:g}: its Fresnel term stays within 2e-6 of Mitsuba's")
            eta = np.where(eta == 0, NONE_ETA, eta)
        m = Material("roughconductor", "", alpha=alpha_u, distribution=distribution,
                     sample_visible=visible, eta=eta, k=k, specular=weights * specular,
                     grey=is_grey(eta) and is_grey(k) and is_grey(specular) and not textures, textures=textures,
                     texture_text=texture_text)
        m.text = (f"roughconductor {_options_text(m)} eta={rgb_text(eta)} k={rgb_text(k)}"
                  + ("" if "specular" in textures or np.all(specular == 1) else
                     f" specular_reflectance={rgb_text(specular)}")
                  + _textures_text(texture_text, {"alpha": "alpha", "specular": "specular_reflectance"}))
        return m
    if cls == "RoughPlastic":
        distribution, visible = _microfacet_options(fields, where, plugin)
        if fields.get("nonlinear", "0") != "0":
            raise fail(where, f"{plugin}: nonlinear=true; warpis supports the linear roughplastic only")
        alpha = _scalar(params, "alpha", where, plugin)
        eta = _scalar(params, "eta", where, plugin)
        textures, texture_text, means = {}, {}, []
        for field_name, name in (("albedo", "diffuse_reflectance"), ("specular", "specular_reflectance")):
            tex = _texture(fields, objects, name)
            if tex is not None:
                textures[field_name] = (tex,)
                texture_text[field_name] = fields[name]
                means.append(float(tex.mean()))  # Mitsuba's specular_sampling_weight takes the texture's mean
        diffuse = (np.full(3, math.nan) if "albedo" in textures else
                   uniform_colour(fields, params, "diffuse_reflectance", where, plugin))
        specular = (np.full(3, math.nan) if "specular" in textures else
                    uniform_colour(fields, params, "specular_reflectance", where, plugin, default=1.0))
        d_mean = means.pop(0) if "albedo" in textures else float(diffuse.mean())
        s_mean = means.pop(0) if "specular" in textures else float(specular.mean())
        # Mitsuba's specular_sampling_weight: the lobe choice, from the RGB means.
        weight = s_mean / (d_mean + s_mean) if d_mean + s_mean > 0 else 0.5
        m = Material("roughplastic", "", albedo=float(weights @ diffuse), alpha=alpha, distribution=distribution,
                     sample_visible=visible, eta=np.full(3, eta), k=np.zeros(3), specular=weights * specular,
                     specular_weight=weight, grey=is_grey(diffuse) and is_grey(specular) and not textures,
                     textures=textures, texture_text=texture_text)
        m.text = (f"roughplastic {_options_text(m)} eta={eta:.6g}"
                  + ("" if "albedo" in textures else f" albedo={m.albedo:.6g}")
                  + ("" if "specular" in textures else f" specular={float(m.specular.sum()):.6g}")
                  + f" specular_weight={weight:.6g}"
                  + _textures_text(texture_text, {"albedo": "diffuse_reflectance", "specular": "specular_reflectance"}))
        return m
    raise fail(where, f"BSDF {plugin!r} is not supported; warpis supports {SUPPORTED_BSDFS}")


def _textures_text(texture_text: dict[str, str], names: dict[str, str]) -> str:
    """How a material's textured parameters read in notes."""
    return "".join(f" {names[f]} from a {texture_name(first_texture(t))!r} texture" for f, t in texture_text.items())


def first_texture(text: str) -> str:
    """The first non-uniform of the ' / '-joined texture descriptions (alpha_u / alpha_v)."""
    for part in text.split(" / "):
        if part.split("[")[0].strip() not in _UNIFORM:
            return part
    return text


def read_material(mi: Any, bsdf: Any, where: str, weights: np.ndarray, notes: list[str]) -> Material:
    """A shape's Mitsuba BSDF → its warpis material; one warpis cannot shade → an
    occluder's placeholder holding the error (``problem``), which a receiver on the
    shape raises (a shape only blocks light in Mitsuba's ``direct``, whatever its BSDF)."""
    kept: list[str] = []
    try:
        material = _shaded_material(mi, bsdf, where, weights, kept)
    except WarpisError as exc:
        cls = bsdf.class_name()
        name = _BSDF_PLUGINS.get(cls, cls)
        return Material("lambert", f"BSDF {name!r}, which warpis cannot shade: an occluder only (it blocks light, "
                                   f"as any shape does in Mitsuba's direct integrator)", problem=str(exc),
                        unshaded=name)
    notes += kept
    return material


def _shaded_material(mi: Any, bsdf: Any, where: str, weights: np.ndarray, notes: list[str]) -> Material:
    """A shape's Mitsuba BSDF → its warpis material, or a one-line error."""
    params = object_parameters(mi, bsdf)
    _, fields = object_fields(str(bsdf))
    cls = bsdf.class_name()
    objects = _children(mi, bsdf)
    if _BSDF_PLUGINS.get(cls) != "twosided":
        return replace(_one_bsdf(cls, fields, params, where, weights, notes, objects), weights=weights)
    sides = []
    for i in (0, 1):
        side_cls, side_fields = object_fields(fields.get(f"brdf[{i}]", ""))
        prefix = f"brdf_{i}." if any(key.startswith(f"brdf_{i}.") for key in params) else "brdf_0."
        side_params = {key[len(prefix):]: value for key, value in params.items() if key.startswith(prefix)}
        side = objects.get(f"brdf_{i}", objects.get("brdf_0"))
        sides.append(_one_bsdf(side_cls, side_fields, side_params, where, weights, notes,
                               _children(mi, side) if side is not None else {}))
        sides[-1].weights = weights
    if not sides[0].same(sides[1]):
        raise fail(where, f"twosided with a different BSDF on each side ({sides[0].text}; {sides[1].text}); warpis "
                          f"supports twosided around one BSDF")
    sides[0].twosided = True
    sides[0].text = "twosided " + sides[0].text
    return sides[0]
