"""What ``warpis check`` prints and writes: the verdict table, a figure per check, index.html.

The chi-square figure shows, as Mitsuba's chi2 notebook does, the histogram of the
samples and the expected counts side by side on the same colour scale (the windowed
(φ, cos θ) grid), and beside them the pdf-ratio map, observed/expected per cell.  The
other checks get a small figure of what they compared.  ``--out DIR`` receives
``index.html``, ``check.json`` and ``figures/*.png``, each written atomically.
"""

from __future__ import annotations

import html
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from .checks import Verdict
from .run import CheckRun

VERDICT = {True: "pass", False: "FAIL", None: "n/a"}


def table_lines(run: CheckRun) -> list[str]:
    """The verdict table, subject by subject, and the closing line."""
    b = run.budget
    lines = [run.title, f"{b.samples} samples per frame, seed {b.seed}, {run.seconds:.0f} s; {family_text(run)}"]
    lines += [f"note: {n}" for n in run.notes]
    width = max([len(v.frame) for v in run.verdicts] + [5])
    subject = None
    for v in run.verdicts:
        if v.subject != subject:
            subject = v.subject
            lines += ["", subject, f"  {'check':<16} {'frame':<{width}} {'verdict':<7} result"]
        lines.append(f"  {v.check:<16} {v.frame:<{width}} {VERDICT[v.passed]:<7} {v.summary}")
    lines.append("")
    lines.append(closing_line(run))
    return lines


def family_text(run: CheckRun) -> str:
    """How often the run fails a correct subject by chance."""
    fam = run.family
    if fam.tests == 0:
        return "every check deterministic (no false failure by chance)"
    return (f"family-wise false-failure rate {fam.alpha:g} over {fam.tests} statistical test(s) "
            f"(Šidák: each at {fam.per_test:.3g})")


def closing_line(run: CheckRun) -> str:
    done = [v for v in run.verdicts if v.passed is not None]
    na = len(run.verdicts) - len(done)
    tail = f" ({na} not applicable)" if na else ""
    if run.passed:
        return f"PASSED: all {len(done)} checks{tail}"
    failed: dict[tuple[str, str], int] = {}
    for v in run.failed:
        failed[(v.subject, v.check)] = failed.get((v.subject, v.check), 0) + 1
    what = "; ".join(f"{check} at {n} frame(s) of {subject}" for (subject, check), n in failed.items())
    return f"FAILED: {len(run.failed)} of {len(done)} checks{tail}: {what}"


# --------------------------------------------------------------------------- files


def write_report(run: CheckRun, out: Path, command: str) -> list[Path]:
    """index.html, check.json and a PNG per verdict with a figure, into ``out`` (locked)."""
    from ..runs import outdir

    figures = out / "figures"
    outdir.make_dir(figures)
    written = []
    rows = []
    for i, v in enumerate(run.verdicts):
        name = None
        if v.figure is not None:
            name = f"figures/{i:03d}-{_slug(v.check)}-{_slug(v.frame)}.png"
            with outdir.replacing(out / name) as fh:
                fh.write(_png(v))
            written.append(out / name)
        rows.append((v, name))
    data = run.as_dict() | {"command": command}
    outdir.write_text(out / "check.json", json.dumps(json_safe(data), indent=2, allow_nan=False) + "\n")
    outdir.write_text(out / "index.html", _html(run, rows, command))
    return [out / "index.html", out / "check.json"] + written


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:40] or "x"


def json_safe(x: Any) -> Any:
    """``x`` with every non-finite float as None (JSON holds no NaN or infinity)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x


def _html(run: CheckRun, rows: list[tuple[Verdict, str | None]], command: str) -> str:
    colour = {True: "#d9f2d9", False: "#f9d6d5", None: "#eeeeee"}
    out = ["<!doctype html><html><head><meta charset='utf-8'><title>warpis check</title>",
           "<style>body{font-family:sans-serif;margin:2em}td,th{padding:2px 8px;text-align:left;vertical-align:top}"
           "table{border-collapse:collapse}img{max-width:100%}</style></head><body>",
           f"<h1>{html.escape(run.title)}</h1>", f"<p><code>{html.escape(command)}</code></p>",
           f"<p><b>{html.escape(closing_line(run))}</b></p>",
           f"<p>{run.budget.samples} samples per frame, seed {run.budget.seed}; {html.escape(family_text(run))}.</p>"]
    out += [f"<p>{html.escape(n)}</p>" for n in run.notes]
    out.append("<table><tr><th>subject</th><th>check</th><th>frame</th><th>verdict</th><th>result</th></tr>")
    for i, (v, name) in enumerate(rows):
        link = f" <a href='#f{i}'>figure</a>" if name else ""
        out.append(f"<tr style='background:{colour[v.passed]}'><td>{html.escape(v.subject)}</td>"
                   f"<td>{html.escape(v.check)}</td><td>{html.escape(v.frame)}</td><td>{VERDICT[v.passed]}</td>"
                   f"<td>{html.escape(v.summary)}{link}</td></tr>")
    out.append("</table>")
    for i, (v, name) in enumerate(rows):
        if name:
            out.append(f"<h3 id='f{i}'>{html.escape(v.check)}: {html.escape(v.subject)}, {html.escape(v.frame)} "
                       f"({VERDICT[v.passed]})</h3><img src='{name}' alt='{html.escape(v.check)}'>")
    out.append("</body></html>\n")
    return "\n".join(out)


# --------------------------------------------------------------------------- figures


def _png(v: Verdict) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = _DRAW[v.figure["kind"]](plt, v)
    fig.suptitle(f"{v.check} — {v.subject}, {v.frame}: {VERDICT[v.passed]}", fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _histograms(plt: Any, v: Verdict) -> Any:
    panels = v.figure["panels"]
    fig, axes = plt.subplots(len(panels), 3, figsize=(13, 3.6 * len(panels)), squeeze=False)
    extent = (0.0, 2.0 * math.pi, -1.0, 1.0)
    for row, panel in zip(axes, panels):
        obs, exp = np.asarray(panel["observed"]), np.asarray(panel["expected"])
        top = max(float(obs.max()), float(exp.max()), 1.0)
        for ax, data, title in ((row[0], obs, "observed (samples)"),
                                (row[1], exp, f"expected (∫pdf per cell)\n{panel['window']}")):
            im = ax.imshow(data, origin="lower", aspect="auto", extent=extent, vmin=0.0, vmax=top, cmap="viridis")
            ax.set_title(title, fontsize=8)
            ax.set_xlabel("φ'")
            fig.colorbar(im, ax=ax)
        row[0].set_ylabel("cos θ'")
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(exp >= 5.0, obs / exp, np.nan)
        spread = float(np.nanmax(np.abs(ratio - 1.0))) if np.isfinite(ratio).any() else 0.1
        spread = min(max(spread, 0.05), 1.0)
        im = row[2].imshow(ratio, origin="lower", aspect="auto", extent=extent, cmap="RdBu_r", vmin=1.0 - spread,
                           vmax=1.0 + spread)
        row[2].set_title("pdf-ratio map: observed / expected", fontsize=9)
        row[2].set_xlabel("φ'")
        fig.colorbar(im, ax=row[2])
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.35 / fig.get_figheight()))  # room for the title
    return fig


def _bars(plt: Any, v: Verdict) -> Any:
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    f = v.figure
    ax.bar(f["labels"], f["values"], yerr=[3.0 * e for e in f["errors"]], capsize=6, color=["#4c72b0", "#dd8452"])
    lo = min(f["values"]) - 4 * max(max(f["errors"]), 1e-4 * abs(max(f["values"])))
    hi = max(f["values"]) + 4 * max(max(f["errors"]), 1e-4 * abs(max(f["values"])))
    ax.set_ylim(lo, hi)
    ax.set_title("error bars: 3 standard errors", fontsize=8)
    return fig


def _ratios(plt: Any, v: Verdict) -> Any:
    fig, ax = plt.subplots(figsize=(5, 3.2))
    values = np.asarray(v.figure["values"], dtype=np.float64)
    if values.size:
        ax.hist(values, bins=100, color="#4c72b0", log=True)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_xlabel(v.figure["xlabel"])
    ax.set_ylabel("samples")
    return fig


def _grid_coords(dirs: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from ..testing import orthonormal_frame

    b1, b2, n = orthonormal_frame(normal)
    phi = np.mod(np.arctan2(dirs @ b2, dirs @ b1), 2.0 * math.pi)
    return phi, np.clip(dirs @ n, -1.0, 1.0)


def _points(plt: Any, v: Verdict) -> Any:
    fig, ax = plt.subplots(figsize=(5, 3.2))
    f = v.figure
    for dirs, colour, label in ((f["all"], "#cccccc", "samples"), (f["dirs"], "#c44e52", "where the pdf is 0")):
        if len(dirs):
            phi, cos_t = _grid_coords(np.asarray(dirs), np.asarray(f["normal"]))
            ax.scatter(phi, cos_t, s=1, c=colour, label=label)
    ax.set_xlim(0, 2 * math.pi)
    ax.set_ylim(-1, 1)
    ax.set_xlabel("φ about the normal")
    ax.set_ylabel("cos θ")
    ax.legend(fontsize=7, loc="lower right")
    return fig


def _measure(plt: Any, v: Verdict) -> Any:
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    f = v.figure
    ax.errorbar(f["distances"], f["values"], yerr=[3 * e for e in f["errors"]], fmt="o-", capsize=5)
    d = np.linspace(1.0, max(f["distances"]), 50)
    ax.plot(d, f["values"][0] / d**2, "--", color="#c44e52", label="an area density: ∝ distance⁻²")
    ax.axhline(1.0, color="k", lw=0.8, label="a solid-angle density: 1")
    ax.set_xlabel("distance to the light (relative)")
    ax.set_ylabel("∫pdf / valid fraction")
    ax.legend(fontsize=7)
    return fig


def _channels(plt: Any, v: Verdict) -> Any:
    fig, ax = plt.subplots(figsize=(5, 3.2))
    series = v.figure["series"]
    width = 0.8 / len(series)
    for k, (label, (value, err)) in enumerate(series.items()):
        value, err = np.atleast_1d(value), np.atleast_1d(err)
        x = np.arange(len(value)) + k * width
        ax.bar(x, value, width, yerr=3 * err, capsize=4, label=label)
    if "reference" in v.figure:
        ax.axhline(v.figure["reference"], color="k", lw=0.8)
    names = ["r", "g", "b"] if len(np.atleast_1d(next(iter(series.values()))[0])) == 3 else None
    if names:
        ax.set_xticks(np.arange(3) + 0.4 - width / 2, names)
    ax.legend(fontsize=7)
    return fig


def _sphere(plt: Any, v: Verdict) -> Any:
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    f = v.figure
    dirs = np.asarray(f["dirs"])
    if len(dirs):
        phi, cos_t = _grid_coords(dirs, np.asarray(f["normal"]))
        sc = ax.scatter(phi[:50000], cos_t[:50000], s=1, c=np.asarray(f["values"])[:50000], cmap="RdBu_r")
        fig.colorbar(sc, ax=ax, label=f["title"])
    ax.set_xlim(0, 2 * math.pi)
    ax.set_ylim(-1, 1)
    ax.set_xlabel("φ about the normal")
    ax.set_ylabel("cos θ")
    return fig


_DRAW = {"histograms": _histograms, "bars": _bars, "ratios": _ratios, "points": _points, "measure": _measure,
         "channels": _channels, "sphere": _sphere}
