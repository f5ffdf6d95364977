"""matplotlib figures: calibration of each prediction and variance against N per receiver."""

from __future__ import annotations

import hashlib
import multiprocessing
import signal
import threading
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .runs import outdir  # noqa: E402

FORMATS = ("png", "pdf")
DPI = 120


def _save(fig, out: Path, stem: str) -> list[Path]:
    """Each format written atomically (a report never links a half-written figure); a one-line
    WarpisError when it cannot be written."""
    paths = []
    try:
        outdir.make_dir(out)
        box = _tight_box(fig)
        for ext in FORMATS:
            path = out / f"{stem}.{ext}"
            with outdir.replacing(path) as fh:
                fig.savefig(fh, format=ext, dpi=DPI, bbox_inches=box)
            paths.append(path)
    finally:
        plt.close(fig)
    return paths


def _tight_box(fig) -> matplotlib.transforms.Bbox:
    """The box ``bbox_inches="tight"`` gives the PNG, found once for every format.

    "tight" lays the whole figure out again in each ``savefig`` before drawing it: one
    layout here serves both formats (the demo's figures: 20–22 s → 19.5–20 s on a loaded
    two-core machine), and the PNG is byte for byte what "tight" writes (the same Agg
    renderer at the same dpi).
    """
    fig.set_dpi(DPI)
    fig.draw_without_rendering()
    return fig.get_tightbbox(fig.canvas.get_renderer()).padded(matplotlib.rcParams["savefig.pad_inches"])


# A second process pays from this many figures on: it takes about 3 s of a core to
# start (Python, Warp, matplotlib), and a figure takes 1–2 s to lay out and write twice.
HELPER_FROM = 5


def draw_all(jobs: Sequence[Callable[[], list[Path]]], processes: int = 1) -> list[list[Path]]:
    """The files of each job (a picklable call of a plot function of this module), in job order.

    matplotlib holds the GIL while it lays out and draws, so a second thread would not
    help: with ``processes`` ≥ 2 and at least HELPER_FROM jobs, a second process (spawned,
    since this one may run Warp's threads) draws jobs from the front of the list while
    this one draws from the back, and each takes the next as it finishes.  The files are
    the same bytes either way (the same Agg renderer).  A helper that cannot start, or
    dies, leaves its jobs to this process; an error a job raises (a file that cannot be
    written) is raised here.
    """
    made: list[list[Path]] = [[] for _ in jobs]
    todo = deque(range(len(jobs)))
    pool = _helper() if processes >= 2 and len(jobs) >= HELPER_FROM else None
    helper = pool
    running: tuple[int, Future] | None = None
    try:
        while todo or running is not None:
            if running is not None and (running[1].done() or not todo):
                i, future = running
                running = None
                try:
                    made[i] = future.result()
                except BrokenProcessPool:
                    helper = None
                    todo.appendleft(i)
            elif helper is not None and running is None:
                i = todo.popleft()
                try:
                    running = (i, helper.submit(jobs[i]))
                except (BrokenProcessPool, RuntimeError, OSError):  # it has died
                    helper = None
                    todo.appendleft(i)
            else:
                i = todo.pop() if helper is not None else todo.popleft()
                made[i] = jobs[i]()
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    return made


def _helper() -> ProcessPoolExecutor | None:
    """One spawned process for :func:`draw_all`, started now, or None where it cannot start.

    It starts with Ctrl-C ignored (a disposition a new Python keeps), so that an interrupt
    reaches only this process, which stops the helper after its current figure and says so
    in one line, instead of each process printing its own traceback.  Only the main
    thread may change signal handlers: elsewhere there is no helper.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is None:  # None: set outside Python
        return None
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    pool = None
    try:
        pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        pool.submit(int)  # spawns the process now, while interrupts are ignored
        return pool
    except (OSError, ImportError, NotImplementedError, RuntimeError):
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
        return None
    finally:
        signal.signal(signal.SIGINT, previous)


def calibration_plot(rows: Sequence[dict], out: Path, stem: str = "calibration") -> list[Path]:
    """Per form, the histogram of z = (s² − V)/se against the N(0, 1) density.

    A correct formula gives z ~ N(0, 1); a wrong one a shifted or spread histogram.
    """
    forms: dict[str, list[float]] = {}
    for row in rows:
        for form, z in row.get("z", {}).items():
            if z is not None and form != "exact":
                forms.setdefault(form, []).append(z)
    names = sorted(forms)
    if not names:
        return []
    cols = min(3, len(names))
    nrows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(4 * cols, 3 * nrows), squeeze=False)
    grid = np.linspace(-5, 5, 201)
    for ax, form in zip(axes.flat, names):
        z = np.clip(np.array(forms[form]), -8, 8)
        ax.hist(z, bins=np.linspace(-8, 8, 33), density=True, alpha=0.6, color="C0", label=f"{len(z)} cells")
        ax.plot(grid, np.exp(-grid**2 / 2) / np.sqrt(2 * np.pi), "k--", label="N(0, 1)")
        ax.set_title(f"{form}: mean z {np.mean(z):.2f}, sd {np.std(z):.2f}", fontsize=9)
        ax.set_xlabel("z = (measured − predicted) / se")
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    return _save(fig, out, stem)


def convergence_plot(rows: Sequence[dict], receiver: int, out: Path, stem: str | None = None) -> list[Path]:
    """verify's rows for one receiver → :func:`slope_convergence_plot` (exact predictions dashed)."""
    mine = [r for r in rows if r["receiver"] == receiver]
    series = []
    for est in dict.fromkeys(r["estimator"] for r in mine):
        cells = sorted((r for r in mine if r["estimator"] == est), key=lambda r: r["n"])
        series.append({
            "label": est, "n": [c["n"] for c in cells], "variance": [c["variance"] for c in cells],
            "lo": [c["variance_ci"][0] for c in cells], "hi": [c["variance_ci"][1] for c in cells],
            "prediction": [c["predictions"].get("exact") for c in cells],
        })
    title = f"receiver {receiver}: measured (markers, 95% intervals) and exact prediction (dashed)"
    return slope_convergence_plot(series, title, out, stem or f"variance-vs-n-receiver-{receiver}")


SLUG_LENGTH = 64


def _slug(text: str) -> str:
    """A file-name-safe version of a scene or estimator name, distinct for distinct names.

    Characters a file name cannot hold become '-'; when that (or shortening a long name)
    changed the name, a short digest of the real name follows, so ``a/b`` and ``a:b`` do
    not overwrite each other's figures.
    """
    out = "".join(ch if ch.isalnum() or ch in "._-" else "-" for ch in text).strip("-")
    if out and out == text and len(out) <= SLUG_LENGTH:
        return out
    digest = hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:8]
    return f"{out[:SLUG_LENGTH]}-{digest}" if out else digest


def slope_convergence_plot(series: Sequence[dict], title: str, out: Path, stem: str) -> list[Path]:
    """Variance against N (log-log) with a line per estimator, interval bars, fitted slopes.

    Each entry of ``series``: ``label``, ``n``, ``variance``, ``lo``, ``hi`` (lists over N),
    optionally ``prediction`` (a list, drawn dashed; None entries are skipped) and
    ``slope`` (``(slope, lo, hi)`` or None), shown in the legend.  Points with zero
    variance are left out; with nothing left the figure is not made.
    """
    fig, ax = plt.subplots(figsize=(8.5, 5.8))
    drawn = 0
    for i, s in enumerate(series):
        n = np.asarray(s["n"], float)
        v = np.asarray(s["variance"], float)
        keep = v > 0
        if not keep.any():
            continue
        lo = np.maximum(np.asarray(s["lo"], float), v * 1e-3)
        hi = np.asarray(s["hi"], float)
        color = f"C{i % 10}"
        style = "o-" if i < 10 else "s-"
        label = s["label"]
        if s.get("slope") is not None:
            k, k_lo, k_hi = s["slope"]
            label = f"{label}: slope {k:.2f} [{k_lo:.2f}, {k_hi:.2f}]"
        ax.errorbar(n[keep], v[keep], yerr=[(v - lo)[keep], (hi - v)[keep]], fmt=style, ms=3, lw=1, color=color,
                    capsize=2, label=label)
        pred = s.get("prediction")
        if pred is not None:
            p = np.array([np.nan if x is None else x for x in pred], float)
            ok = np.isfinite(p) & (p > 0)
            if ok.sum() >= 1:
                ax.plot(n[ok], p[ok], "--", color=color, lw=0.8)
        drawn += 1
    if not drawn:
        plt.close(fig)
        return []
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("N (samples per estimate)")
    ax.set_ylabel("variance of one estimate")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6.5, ncol=1 if drawn <= 4 else 2, loc="upper center", bbox_to_anchor=(0.5, -0.12),
              title="markers: measured with 95% intervals; slope of the weighted log-log fit [95% interval]",
              title_fontsize=6.5, frameon=False)
    return _save(fig, out, stem)


def variance_map_plot(panels: Sequence[tuple[str, np.ndarray]], title: str, out: Path, stem: str,
                      origin: str = "lower") -> list[Path]:
    """A panel per estimator of the variance over a receiver grid, on one shared log colour scale.

    ``panels``: (label, (rows, cols) array) with NaN where a receiver was not measured;
    zero variance (an umbra) is drawn grey.
    """
    from matplotlib.colors import LogNorm

    positive = np.concatenate([a[np.isfinite(a) & (a > 0)] for _, a in panels]) if panels else np.array([])
    if positive.size == 0:
        return []
    norm = LogNorm(vmin=float(positive.min()), vmax=float(max(positive.max(), positive.min() * 1.0001)))
    return _map_panels(panels, title, "viridis", norm, "variance (grey: zero or not measured)", out, stem, origin)


def ratio_map_plot(panels: Sequence[tuple[str, np.ndarray]], title: str, out: Path, stem: str,
                   origin: str = "lower") -> list[Path]:
    """Panels of a variance ratio over a receiver grid, log colour scale centred on 1.

    ``panels``: (label, (rows, cols) array of ratios); NaN or non-positive entries are grey.
    """
    from matplotlib.colors import LogNorm

    finite = np.concatenate([a[np.isfinite(a) & (a > 0)] for _, a in panels]) if panels else np.array([])
    if finite.size == 0:
        return []
    span = float(np.exp(np.max(np.abs(np.log(finite)))))
    span = max(span, 1.01)
    norm = LogNorm(vmin=1 / span, vmax=span)
    return _map_panels(panels, title, "RdBu_r", norm, "variance ratio (grey: undefined)", out, stem, origin)


def slope_map_plot(panels: Sequence[tuple[str, np.ndarray]], title: str, out: Path, stem: str,
                   origin: str = "upper") -> list[Path]:
    """Panels of the fitted convergence slope per receiver (a camera's pixels), on one
    linear scale from −2.5 to 0 (−1: independent sampling's rate; −2: jittered on a
    smooth integrand); grey where there is no slope (zero variance, or not measured)."""
    from matplotlib.colors import Normalize

    if not any(np.isfinite(a).any() for _, a in panels):
        return []
    return _map_panels(panels, title, "viridis_r", Normalize(-2.5, 0.0), "slope of log variance against log N "
                       "(grey: none)", out, stem, origin, positive_only=False)


def _map_panels(panels: Sequence[tuple[str, np.ndarray]], title: str, cmap_name: str, norm, label: str, out: Path,
                stem: str, origin: str = "lower", positive_only: bool = True) -> list[Path]:
    """One image per panel on a shared colour scale; masked (grey) where not finite (or,
    with ``positive_only``, not positive).  ``origin``: "lower" for receiver grids (row 0
    at the bottom), "upper" for camera images (row 0 at the top)."""
    cols = min(4, len(panels))
    nrows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(3.4 * cols, 3.0 * nrows), squeeze=False)
    cmap = plt.get_cmap(cmap_name).with_extremes(bad="0.75")
    image = None
    for ax, (name, grid) in zip(axes.flat, panels):
        bad = ~(np.isfinite(grid) & (grid > 0)) if positive_only else ~np.isfinite(grid)
        shown = np.ma.masked_where(bad, grid)
        image = ax.imshow(shown, origin=origin, cmap=cmap, norm=norm, interpolation="nearest",
                          aspect="equal" if origin == "upper" else "auto")
        ax.set_title(name, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.colorbar(image, ax=axes.ravel().tolist(), shrink=0.8, label=label)
    return _save(fig, out, stem)
