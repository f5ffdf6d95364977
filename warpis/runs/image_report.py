"""Pictures and the HTML page of ``warpis image``: per-pixel variance of each estimator.

A camera makes every pixel a receiver.  From the per-pixel arrays (row 0 at the top of
the picture) this module draws:

* ``mean.png`` - the reference and each estimator's mean radiance, one shared linear scale
  clipped at a high percentile (one hot pixel does not wash the rest out);
* ``single.png`` - one trial of each estimator, on the reference's scale: the noise of a
  render at N samples as a viewer sees it;
* ``variance.png`` and ``predicted.png`` - measured and predicted variance, one shared log
  scale for both;
* ``ratio.png`` - measured / predicted variance, diverging log scale centred on 1;
* ``rel_error.png`` - √variance / reference, one shared log scale;
* ``efficiency.png`` - efficiency relative to the baseline, diverging log scale centred on 1;
* ``winner.png`` - which estimator is the most efficient at each pixel;

and ``index.html``, a self-contained page showing them with the summary table, the run's
settings, how predictions were bounded, the masked pixel counts and a link to the numbers
(``image.npz``).  :func:`write_exr` optionally writes every array to ``image.exr``.

Colours shared by every map: light grey is a pixel that is not a receiver (it sees
nothing, an emitter, the back of a one-sided surface, or a surface whose BSDF warpis cannot
shade: one grey for all four), mid grey
a receiver without a value (not predicted, or undefined), black an exact zero on a log
scale.  Every file is written atomically (:func:`warpis.runs.outdir.replacing`).
"""

from __future__ import annotations

import contextlib
import html
import io
import json
import math
import os
import re
import tempfile
import urllib.parse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm, Normalize  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from PIL import Image  # noqa: E402  (a dependency of matplotlib)

from . import outdir  # noqa: E402

# Special colours (RGB in [0, 1]); none of them occurs in the colour maps used below.
MASKED_RGB = (0.85, 0.85, 0.85)  # not a receiver: sees nothing, an emitter, a back face, or a surface not shaded
MISSING_RGB = (0.55, 0.55, 0.55)  # a receiver with no value: not predicted, or undefined
ZERO_RGB = (0.0, 0.0, 0.0)  # exactly zero on a log scale (an umbra has zero variance)
MASKED_NAME, MISSING_NAME, ZERO_NAME = "light grey", "mid grey", "black"

LINEAR_CMAP, LOG_CMAP, DIVERGING_CMAP = "inferno", "viridis", "RdBu_r"
MEAN_PERCENTILE = 99.5  # the mean images' scale ends here: a few hot pixels are clipped
LOG_CLIP = 0.5  # log scales span the 0.5th to 99.5th percentile of the positive values
LOG_DECADES = 8.0  # ... and at most this many decades
RATIO_CAP = 10.0  # measured/predicted shown up to 10x each way
EFFICIENCY_CAP = 100.0  # relative efficiencies legitimately span more than ratios do
MIN_SPAN = 1.1  # a diverging scale spans at least ±10%, so noise around 1 stays pale

DPI = 100
MAX_COLS = 4
PANEL_IN = 3.0  # width of one panel in inches (less for very tall images)
MAX_PANEL_HEIGHT_IN = 4.0
TITLE_WIDTH = 38  # characters per title line at the title font size

MASK_KINDS = (("nothing", 1, "sees nothing"), ("emitter", 2, "sees an emitter"),
              ("back", 3, "sees the back of a one-sided surface"),
              ("unshaded", 4, "sees a surface whose BSDF warpis cannot shade"))

# One line per picture for the page, by file stem.
DESCRIPTIONS = {
    "mean": f"Mean radiance of each estimator over all trials beside the reference, on one linear scale "
            f"clipped at the {MEAN_PERCENTILE:g}th percentile of all values (brighter pixels show the top colour).",
    "single": "One trial of each estimator: what a render at N samples per pixel looks like, on the reference's "
              "scale from the mean picture.",
    "variance": f"Measured variance of one estimate per pixel, on one log scale shared with the predicted "
                f"variance, from the {LOG_CLIP:g}th to the {100 - LOG_CLIP:g}th percentile and at most "
                f"{LOG_DECADES:g} decades (beyond: the end colours; {ZERO_NAME}: zero variance).",
    "predicted": f"Exact predicted variance on the measured variance's scale ({MISSING_NAME}: not predicted).",
    "ratio": f"Measured / predicted variance on a log scale centred on 1 (white), symmetric, spanning at most "
             f"{RATIO_CAP:g}x each way (beyond: the end colours); red: more variance than predicted "
             f"({MISSING_NAME}: not predicted, or 0/0).",
    "rel_error": f"Relative error √variance / reference of one estimate, on one shared log scale "
                 f"({ZERO_NAME}: zero).",
    "efficiency": f"Efficiency 1/(variance × cost) relative to the baseline's (whose own panel, all 1, is left out), "
                  f"log scale centred on 1, spanning at most {EFFICIENCY_CAP:g}x each way; red: more efficient "
                  f"than the baseline ({MISSING_NAME}: undefined).",
    "winner": f"The most efficient estimator at each pixel ({MISSING_NAME}: no winner, e.g. every variance zero).",
}


@dataclass(frozen=True)
class Scale:
    """A colour scale: ``kind`` is ``linear``, ``log`` or ``diverging`` (log, centred on 1)."""

    kind: str
    vmin: float
    vmax: float
    label: str

    @property
    def cmap(self):
        name = {"linear": LINEAR_CMAP, "log": LOG_CMAP, "diverging": DIVERGING_CMAP}[self.kind]
        return plt.get_cmap(name)

    def norm(self) -> Normalize:
        return Normalize(self.vmin, self.vmax) if self.kind == "linear" else LogNorm(self.vmin, self.vmax)


# --------------------------------------------------------------------------- scales (pure)


def _finite(images: Sequence[np.ndarray], positive: bool = False) -> np.ndarray:
    values = [np.asarray(a, float).ravel() for a in images]
    flat = np.concatenate(values) if values else np.array([])
    keep = np.isfinite(flat) & (flat > 0) if positive else np.isfinite(flat)
    return flat[keep]


def linear_range(images: Sequence[np.ndarray], percentile: float = MEAN_PERCENTILE) -> tuple[float, float] | None:
    """(vmin, vmax) of one linear scale for all ``images``: from min(0, lowest) to ``percentile``.

    NaN and ±inf are ignored; None when no value is finite.  Radiance is not negative, so
    the scale starts at 0 and a dark picture reads as dark.
    """
    values = _finite(images)
    if values.size == 0:
        return None
    lo = min(0.0, float(values.min()))
    hi = float(np.percentile(values, percentile))
    if hi <= lo:  # a constant (or all-zero) picture: any non-empty range draws it
        hi = lo + max(abs(lo), 1.0)
    return lo, hi


def shared_log_range(images: Sequence[np.ndarray], clip: float = LOG_CLIP,
                     decades: float = LOG_DECADES) -> tuple[float, float] | None:
    """(vmin, vmax) of one log scale for all ``images``: percentiles ``clip`` and 100 − ``clip``,
    and at most ``decades`` decades below the top (a glossy lobe's tail has variances of
    1e-70 next to 10: spanning them would leave no colours for what matters).

    Only finite positive values count (NaN, zero, negatives and inf are drawn by other
    rules); ``clip=0`` gives the exact min and max.  None when there is no such value.
    """
    values = _finite(images, positive=True)
    if values.size == 0:
        return None
    lo, hi = (float(x) for x in np.exp(np.percentile(np.log(values), [clip, 100.0 - clip])))
    lo = max(lo, hi * 10.0**-decades)
    if not hi > lo:  # one value everywhere: a factor of 2 each way keeps the norm valid
        lo, hi = lo / 2, hi * 2
    return lo, hi


def diverging_span(images: Sequence[np.ndarray], cap: float, floor: float = MIN_SPAN) -> float:
    """The symmetric span s ≥ 1 of a log scale [1/s, s] around 1 that holds every finite positive value.

    Capped at ``cap`` (values beyond are clipped to the end colours) and at least ``floor``.
    """
    values = _finite(images, positive=True)
    if values.size == 0:
        return floor
    span = float(np.exp(np.max(np.abs(np.log(values)))))
    return float(min(max(span, floor), cap))


# --------------------------------------------------------------------------- colouring (pure)


def colorize(image: np.ndarray, mask: np.ndarray, scale: Scale) -> np.ndarray:
    """An (H, W, 4) RGBA array: values through the scale, special pixels in their fixed colours.

    Masked pixels (mask ≠ 0) are :data:`MASKED_RGB`; NaN at a receiver :data:`MISSING_RGB`;
    on a log scale 0 is :data:`ZERO_RGB`, while on a diverging scale 0 and +inf are clipped
    to the end colours (a ratio of 0 is a measured zero against a positive prediction).
    Values outside the scale take its end colours.
    """
    v = np.asarray(image, float)
    masked = np.asarray(mask) != 0
    if scale.kind == "linear":
        t = (v - scale.vmin) / (scale.vmax - scale.vmin)
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (np.log(v) - math.log(scale.vmin)) / (math.log(scale.vmax) - math.log(scale.vmin))
    t = np.clip(np.nan_to_num(t, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    rgba = scale.cmap(t)
    missing = np.isnan(v)
    if scale.kind == "log":
        rgba[(v == 0) & ~masked] = (*ZERO_RGB, 1.0)
        missing |= v < 0  # no log scale for a negative value; it should not occur
    rgba[missing & ~masked] = (*MISSING_RGB, 1.0)
    rgba[masked] = (*MASKED_RGB, 1.0)
    return rgba


# --------------------------------------------------------------------------- figures


def _tex_safe(text: str) -> str:
    """Matplotlib reads ``$...$`` as math; a scene or spec name is shown as written."""
    return text.replace("$", r"\$")


def _wrap(text: str, width: int = TITLE_WIDTH) -> str:
    """Lines of at most ``width`` characters, broken after ':' '+' ',' or spaces where possible."""
    parts = re.findall(r"[^:+, ]*[:+, ]?", text)
    lines, line = [], ""
    for part in filter(None, parts):
        if line and len(line) + len(part) > width:
            lines.append(line.rstrip())
            line = ""
        while len(part) > width:  # one unbreakable run longer than a line
            lines.append(part[:width])
            part = part[width:]
        line += part
    if line:
        lines.append(line.rstrip())
    return "\n".join(lines)


def _title(i: int | None, spec: str, extra: str = "") -> str:
    head = spec if i is None else f"[{i}] {spec}"
    return _tex_safe(_wrap(head + extra))


def _colour_bar(fig, scale: Scale, axes, extend: str, special: str) -> None:
    """The shared colour bar, and under the panels the colours that are not on it."""
    bar = fig.colorbar(plt.cm.ScalarMappable(scale.norm(), scale.cmap), ax=axes, shrink=0.85, extend=extend)
    bar.set_label(_tex_safe(_wrap(scale.label, 34)), fontsize=7)
    if scale.kind == "diverging":  # plain numbers at 1/s, 1/√s, 1, √s, s read better than powers of ten
        ticks = [scale.vmin, math.sqrt(scale.vmin), 1.0, math.sqrt(scale.vmax), scale.vmax]
        bar.set_ticks(ticks, labels=[f"{t:.3g}" for t in ticks])
        bar.ax.minorticks_off()
    bar.ax.tick_params(which="both", labelsize=7)
    fig.supxlabel(_tex_safe(f"{MASKED_NAME}: not a receiver (sees nothing, an emitter, a back face or a surface "
                            f"warpis cannot shade); {special}"), fontsize=7)


def _figure(n_panels: int, shape: tuple[int, int], extra_width: float = 1.3):
    """A figure of up to MAX_COLS panels a row, sized from the image aspect (width grows with panels)."""
    height, width = shape
    n_panels = max(n_panels, 1)
    rows = -(-n_panels // MAX_COLS)
    cols = -(-n_panels // rows)  # balanced rows: 5 panels as 3 + 2, not 4 + 1
    panel_w = min(PANEL_IN, MAX_PANEL_HEIGHT_IN * width / height)
    panel_h = panel_w * height / width
    size = (cols * panel_w + extra_width, rows * (panel_h + 0.55) + 0.45)
    fig, axes = plt.subplots(rows, cols, figsize=size, squeeze=False, layout="constrained")
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in list(axes.flat)[n_panels:]:
        ax.axis("off")
    return fig, axes


def _png_bytes(fig) -> bytes:
    """The figure as a small lossless PNG: RGB (the alpha channel is all opaque), a palette
    when 256 colours hold it exactly (a categorical map), and zlib's best effort, since
    these pictures may be committed."""
    raw = io.BytesIO()
    fig.savefig(raw, format="png", dpi=DPI)
    raw.seek(0)
    with Image.open(raw) as image:
        rgb = image.convert("RGB")
    if rgb.getcolors(256) is not None:  # exact: every colour gets its own palette entry
        rgb = rgb.convert("P", palette=Image.Palette.ADAPTIVE, colors=256)
    small = io.BytesIO()
    rgb.save(small, format="png", optimize=True)
    return small.getvalue()


def _save_png(fig, path: Path) -> Path:
    """Written atomically: a page never links a half-written picture."""
    try:
        data = _png_bytes(fig)
    finally:
        plt.close(fig)
    outdir.make_dir(path.parent)
    with outdir.replacing(path) as fh:
        fh.write(data)
    return path


def _panels(path: Path, panels: Sequence[tuple[str, np.ndarray]], mask: np.ndarray, scale: Scale,
            suptitle: str, special: str) -> Path:
    """One picture per panel on ``scale``, with one colour bar for all of them."""
    fig, axes = _figure(len(panels), mask.shape)
    for ax, (title, image) in zip(axes.flat, panels):
        # origin="upper": row 0 of a camera image is the top of the picture
        ax.imshow(colorize(image, mask, scale), origin="upper", interpolation="antialiased")
        ax.set_title(title, fontsize=7)
    # arrows: values beyond either end are drawn in the end colours
    _colour_bar(fig, scale, axes.ravel().tolist(), "max" if scale.kind == "linear" else "both", special)
    fig.suptitle(_tex_safe(_wrap(suptitle, 110)), fontsize=8)
    return _save_png(fig, path)


def save_image(path: Path, image: np.ndarray, mask: np.ndarray, *, log: bool, label: str, title: str,
               vmin: float | None = None, vmax: float | None = None) -> Path:
    """One picture with a colour bar at ``path`` (PNG), e.g. for a README.

    ``log`` chooses a log scale (black: zero) or a linear one; without ``vmin``/``vmax`` the
    scale comes from the image (:func:`shared_log_range` / :func:`linear_range`).  Masked
    pixels are light grey, NaN at a receiver mid grey; the colour-bar label says so.
    """
    image = np.asarray(image, float)
    mask = np.asarray(mask)
    if image.shape != mask.shape or image.ndim != 2:
        raise ValueError(f"image {image.shape} and mask {mask.shape} must be the same (H, W)")
    auto = (shared_log_range if log else linear_range)([np.where(mask == 0, image, np.nan)]) or (1.0, 10.0)
    lo = auto[0] if vmin is None else float(vmin)
    hi = auto[1] if vmax is None else float(vmax)
    scale = Scale("log" if log else "linear", lo, hi, label)
    special = f"{MISSING_NAME}: no value" + (f"; {ZERO_NAME}: zero" if log else "")
    fig, axes = _figure(1, mask.shape)
    ax = axes[0, 0]
    ax.imshow(colorize(image, mask, scale), origin="upper", interpolation="antialiased")
    ax.set_title(_tex_safe(_wrap(title)), fontsize=8)
    _colour_bar(fig, scale, ax, "both" if log else "max", special)
    return _save_png(fig, Path(path))


# --------------------------------------------------------------------------- the pictures of a run


def _image(arrays: Mapping[str, np.ndarray], key: str, shape: tuple[int, ...]) -> np.ndarray:
    if key not in arrays:
        raise KeyError(f"image report: the array {key!r} is missing")
    a = np.asarray(arrays[key])
    if a.shape != shape:
        raise ValueError(f"image report: {key!r} has shape {a.shape}, the mask {shape}")
    return a


def _series(arrays: Mapping[str, np.ndarray], name: str, k: int, shape: tuple[int, ...]) -> list[np.ndarray]:
    return [_image(arrays, f"{name}_{i}", shape).astype(float) for i in range(k)]


def picture_scales(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> dict[str, Scale | None]:
    """The colour scale of each picture by stem (None: nothing to draw).

    ``mean`` and ``single`` share one scale (from the reference and the means), as do
    ``variance`` and ``predicted``; ``ratio`` and ``efficiency`` are diverging around 1
    (the baseline's own efficiency panel, all ones, is not drawn and does not count).
    """
    shape = np.asarray(arrays["mask"]).shape
    k, base = len(meta["estimators"]), int(meta["baseline"])
    means = [_image(arrays, "reference", shape)] + _series(arrays, "mean", k, shape)
    predicted = _series(arrays, "predicted", k, shape)
    variances = _series(arrays, "variance", k, shape) + predicted
    ratios = _series(arrays, "ratio", k, shape)
    effs = [e for i, e in enumerate(_series(arrays, "relative_efficiency", k, shape)) if i != base]
    lin = linear_range(means)
    log_v = shared_log_range(variances)
    log_r = shared_log_range(_series(arrays, "rel_error", k, shape))
    mean = Scale("linear", *lin, f"radiance (shared linear scale, clipped at the {MEAN_PERCENTILE:g}th "
                                 f"percentile)") if lin else None
    var = Scale("log", *log_v, "variance of one estimate (shared log scale)") if log_v else None
    return {
        "mean": mean,
        "single": mean,
        "variance": var,
        "predicted": var if _finite(predicted).size else None,
        "ratio": _diverging(ratios, RATIO_CAP, "measured / predicted variance") if _finite(ratios).size else None,
        "rel_error": Scale("log", *log_r, "√variance / reference (shared log scale)") if log_r else None,
        "efficiency": _diverging(effs, EFFICIENCY_CAP, "efficiency / the baseline's") if effs else None,
        "winner": None,  # categorical: drawn by _winner
    }


def _diverging(images: Sequence[np.ndarray], cap: float, what: str) -> Scale:
    span = diverging_span(images, cap)
    return Scale("diverging", 1 / span, span, f"{what} (log scale, ends at {span:.3g}x each way)")


def write_pictures(out: Path, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> list[Path]:
    """Write the PNGs of a run into ``out``; the paths written, in page order.

    Needs ``mask``, ``reference``, ``winner`` and, for i < len(meta["estimators"]),
    ``mean_i``, ``single_i``, ``variance_i``, ``predicted_i``, ``ratio_i``, ``rel_error_i``,
    ``relative_efficiency_i``.  A picture with nothing to show (no prediction anywhere, one
    estimator only for efficiency) is not written.
    """
    out = Path(out)
    outdir.make_dir(out)
    mask = np.asarray(arrays["mask"])
    specs = [str(s) for s in meta["estimators"]]
    k, base, scene = len(specs), int(meta["baseline"]), str(meta.get("scene", ""))
    scales = picture_scales(arrays, meta)
    shape = mask.shape

    def per(name: str, extra=lambda i: "") -> list[tuple[str, np.ndarray]]:
        return [(_title(i, specs[i], extra(i)), a) for i, a in enumerate(_series(arrays, name, k, shape))]

    predicted = _series(arrays, "predicted", k, shape)
    unpredicted = [not np.isfinite(p).any() for p in predicted]
    no_exact = (lambda i: " (not predicted)" if unpredicted[i] else "")
    reference = [("reference", _image(arrays, "reference", shape).astype(float))]
    n = meta.get("n", "?")
    plans = {
        "mean": (reference + per("mean"), f"{scene}: mean radiance", f"{MISSING_NAME}: no value"),
        "single": (reference + per("single"), f"{scene}: one trial at N = {n}", f"{MISSING_NAME}: no value"),
        "variance": (per("variance"), f"{scene}: measured variance at N = {n}", f"{ZERO_NAME}: zero"),
        "predicted": (per("predicted", no_exact), f"{scene}: predicted variance",
                      f"{ZERO_NAME}: zero; {MISSING_NAME}: not predicted"),
        "ratio": (per("ratio", no_exact), f"{scene}: measured / predicted variance",
                  f"{MISSING_NAME}: not predicted, or 0/0"),
        "rel_error": (per("rel_error"), f"{scene}: relative error √variance / reference",
                      f"{ZERO_NAME}: zero; {MISSING_NAME}: undefined"),
        "efficiency": ([p for i, p in enumerate(per("relative_efficiency")) if i != base],
                       f"{scene}: efficiency relative to the baseline [{base}] {specs[base]}",
                       f"{MISSING_NAME}: undefined"),
    }
    paths = []
    for stem, (panels, suptitle, special) in plans.items():
        if scales[stem] is not None and panels:
            paths.append(_panels(out / f"{stem}.png", panels, mask, scales[stem], suptitle, special))
    paths.append(_winner(out / "winner.png", _image(arrays, "winner", shape), mask, specs, scene))
    return paths


def _palette(k: int) -> list[tuple[float, float, float]]:
    """Distinct category colours, leaving out the greys (they mean masked / no value)."""
    tab10 = [c for i, c in enumerate(plt.get_cmap("tab10").colors) if i != 7]
    tab20 = [c for i, c in enumerate(plt.get_cmap("tab20").colors) if i % 2 and i not in (15,)]
    colours = tab10 + tab20
    return [tuple(colours[i % len(colours)]) for i in range(k)]


def _winner(path: Path, winner: np.ndarray, mask: np.ndarray, specs: Sequence[str], scene: str) -> Path:
    """A categorical map: a colour per estimator, named in the legend."""
    colours = _palette(len(specs))
    rgb = np.empty(winner.shape + (3,))
    rgb[:] = MISSING_RGB
    for i, c in enumerate(colours):
        rgb[winner == i] = c
    rgb[mask != 0] = MASKED_RGB
    handles = [Patch(color=c, label=_title(i, s)) for i, (c, s) in enumerate(zip(colours, specs))]
    handles.append(Patch(color=MASKED_RGB, label=f"{MASKED_NAME}: not a receiver"))
    if ((winner < 0) & (mask == 0)).any():
        handles.append(Patch(color=MISSING_RGB, label=f"{MISSING_NAME}: no winner (every variance zero)"))
    fig, axes = _figure(1, mask.shape, extra_width=3.2)
    ax = axes[0, 0]
    ax.imshow(rgb, origin="upper", interpolation="nearest")
    ax.set_title(_tex_safe(_wrap(f"{scene}: most efficient estimator", 60)), fontsize=8)
    fig.legend(handles=handles, loc="outside right upper", fontsize=7, frameon=False)
    return _save_png(fig, path)


# --------------------------------------------------------------------------- the page

PAGE_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; max-width: 110em; }
h1 { font-size: 1.3em; } h2 { font-size: 1.1em; margin-top: 1.5em; }
.pictures { display: flex; flex-wrap: wrap; gap: 1em; }
figure { margin: 0; flex: 1 1 30em; max-width: 100%; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; }
table { border-collapse: collapse; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
td.spec, th.spec { text-align: left; font-family: monospace; }
pre { background: #f4f4f4; padding: 0.5em; white-space: pre-wrap; word-break: break-all; }
dt { font-weight: bold; } dd { margin: 0 0 0.4em 1.5em; }
"""


def _e(value: Any) -> str:
    """Every string from meta is user input (scene names, specs): escaped, quotes too."""
    return html.escape(str(value), quote=True)


def _num(value: Any) -> str:
    """Three significant digits; — for a missing or NaN value."""
    if value is None:
        return "—"
    x = float(value)
    if math.isnan(x):
        return "—"
    if math.isinf(x):
        return "∞" if x > 0 else "−∞"
    return f"{x:.3g}"


def _share(value: Any) -> str:
    return "—" if value is None or math.isnan(float(value)) else f"{100 * float(value):.1f}%"


def _href(path: Path, out: Path) -> str:
    rel = Path(os.path.relpath(Path(path), Path(out))).as_posix()
    return _e(urllib.parse.quote(rel))


def _figures(out: Path, pictures: Sequence[Path]) -> str:
    items = []
    for p in pictures:
        p = Path(p)
        caption = DESCRIPTIONS.get(p.stem, p.name)
        href = _href(p, out)
        items.append(f'<figure><a href="{href}"><img src="{href}" alt="{_e(p.stem)}"></a>'
                     f"<figcaption><b>{_e(p.name)}</b>: {_e(caption)}</figcaption></figure>")
    return '<div class="pictures">\n' + "\n".join(items) + "\n</div>"


def _summary_table(meta: Mapping[str, Any]) -> str:
    base = meta.get("baseline")
    rows = []
    for i, row in enumerate(meta.get("summary", [])):
        tag = " (baseline)" if i == base else ""
        rows.append(f'<tr><td>{i}</td><td class="spec">{_e(row.get("estimator", ""))}{tag}</td>'
                    f'<td>{_num(row.get("median_relative_efficiency"))}</td>'
                    f'<td>{_num(row.get("relative_efficiency_p05"))} – {_num(row.get("relative_efficiency_p95"))}</td>'
                    f'<td>{_share(row.get("beats_baseline_share"))}</td><td>{_share(row.get("wins_share"))}</td>'
                    f'<td>{_num(row.get("median_variance"))}</td><td>{_num(row.get("median_ratio"))}</td></tr>')
    head = ('<tr><th>#</th><th class="spec">estimator</th><th>median relative efficiency</th>'
            '<th>5th – 95th percentile</th><th>pixels where it beats the baseline</th>'
            '<th>pixels where most efficient</th><th>median variance</th><th>median measured / predicted</th></tr>')
    return "<table>\n" + head + "\n" + "\n".join(rows) + "\n</table>"


def _masked(meta: Mapping[str, Any]) -> str:
    counts = meta.get("masked", {}) or {}
    items = [f"<li>{_e(text)}: {_e(counts.get(key, 0))}</li>" for key, _, text in MASK_KINDS]
    width, height = meta.get("width"), meta.get("height")
    if isinstance(width, int) and isinstance(height, int):
        total = sum(int(counts.get(key, 0)) for key, _, _ in MASK_KINDS)
        items.append(f"<li>receivers (measured): {width * height - total} of {width * height}</li>")
    return "<ul>" + "".join(items) + "</ul>"


def _run(meta: Mapping[str, Any]) -> str:
    seconds = meta.get("seconds")
    took = f"{float(seconds):.1f} s" if isinstance(seconds, (int, float)) else "—"
    size = f"{meta.get('width', '?')} × {meta.get('height', '?')} pixels"
    fields = [("N (samples per estimate)", meta.get("n", "—")), ("trials", meta.get("trials", "—")),
              ("seed", meta.get("seed", "—")), ("image", size), ("run time", took)]
    items = "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in fields)
    return f"<pre>{_e(meta.get('command', ''))}</pre>\n<dl>{items}</dl>"


def write_index(out: Path, meta: Mapping[str, Any], pictures: Sequence[Path]) -> Path:
    """Write ``out/index.html``: the pictures, the summary table, the run, the numbers' link.

    Self-contained (inline style, no scripts); every string from ``meta`` is HTML-escaped.
    Links ``image.npz`` (and ``image.exr`` when it exists in ``out``).
    """
    out = Path(out)
    outdir.make_dir(out)
    scene = meta.get("scene", "")
    specs = meta.get("estimators", [])
    base = meta.get("baseline", 0)
    base_spec = specs[base] if isinstance(base, int) and 0 <= base < len(specs) else "?"
    colours = (f"Colours: {MASKED_NAME} marks a pixel that is not a receiver (it sees nothing, an emitter, or the "
               f"back of a one-sided surface; all three the same grey), {MISSING_NAME} a receiver without a value "
               f"(not predicted, or undefined), {ZERO_NAME} an exact zero on a log scale.")
    numbers = '<a href="image.npz">image.npz</a> (NumPy; every per-pixel array, row 0 at the top)'
    if (out / "image.exr").exists():
        numbers += ', <a href="image.exr">image.exr</a> (OpenEXR, one float channel per array)'
    body = [
        f"<h1>warpis image: {_e(scene)}</h1>",
        f"<p>Relative efficiencies are against the baseline [{_e(base)}] <code>{_e(base_spec)}</code>; "
        f"medians are over the unmasked pixels.</p>",
        "<h2>Summary</h2>", _summary_table(meta),
        "<h2>Pictures</h2>", f"<p>{_e(colours)}</p>", _figures(out, pictures),
        "<h2>Prediction</h2>", f"<p>{_e(meta.get('prediction', '—'))}</p>",
        "<h2>Masked pixels</h2>", _masked(meta),
        "<h2>Run</h2>", _run(meta),
        "<h2>Numbers</h2>", f"<p>{numbers}</p>",
    ]
    page = ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>warpis image: {_e(scene)}</title>\n<style>{PAGE_STYLE}</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")
    path = out / "index.html"
    outdir.write_text(path, page)
    return path


# --------------------------------------------------------------------------- OpenEXR (optional)


def exr_channel(key: str) -> str:
    """``variance_lo_3`` → ``variance_lo.3``: per-estimator arrays group by name in EXR viewers."""
    m = re.fullmatch(r"(.+)_(\d+)", key)
    return f"{m.group(1)}.{m.group(2)}" if m else key


def write_exr(out: Path, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> Path | None:
    """Write ``out/image.exr`` with one float32 channel per (H, W) array, when OpenEXR is installed.

    Returns None without the ``OpenEXR`` package (it is optional, not a dependency).  The
    header holds ``warpis_scene`` and ``warpis_estimators`` (a JSON list) as string attributes.
    """
    try:
        import Imath
        import OpenEXR
    except ImportError:
        return None
    mask = np.asarray(arrays["mask"])
    height, width = mask.shape
    channels = {exr_channel(k): np.ascontiguousarray(np.asarray(a), dtype=np.float32)
                for k, a in arrays.items() if np.ndim(a) == 2 and np.shape(a) == mask.shape}
    header = OpenEXR.Header(width, height)
    header["channels"] = {name: Imath.Channel(Imath.PixelType(Imath.PixelType.FLOAT)) for name in channels}
    header["warpis_scene"] = str(meta.get("scene", "")).encode("utf-8", "surrogatepass")
    header["warpis_estimators"] = json.dumps(list(meta.get("estimators", []))).encode("utf-8")
    out = Path(out)
    outdir.make_dir(out)
    path = out / "image.exr"
    # OpenEXR writes to a file name, not a handle: a temporary name beside it, then os.replace
    fd, tmp = tempfile.mkstemp(dir=out, prefix=".image.exr.", suffix=outdir.TMP_SUFFIX)
    os.close(fd)
    try:
        exr = OpenEXR.OutputFile(tmp, header)
        try:
            exr.writePixels({name: a.tobytes() for name, a in channels.items()})
        finally:
            exr.close()
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise outdir.cannot_write(path, exc) from None
        raise
    return path
