"""The picture on the README's first screen: docs/images/veach-plates-efficiency.png.

    python scripts/make_readme_image.py [--from OUT/image.npz] [--out docs/images/veach-plates-efficiency.png]

Without ``--from`` it runs ``warpis image`` on the bundled ``veach-plates-camera`` (128 × 96,
light sampling, BSDF sampling and balance MIS, all jittered, N = 16, 256 trials; about a
minute on two cores) into a temporary folder.  The picture shows the reference image
and, per pixel, the efficiency (1/(variance × time)) of BSDF sampling and of balance MIS
relative to light sampling, cropped to the plates: Veach's figure, measured.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ESTIMATORS = ("jittered:single:light-solid-angle", "jittered:single:bsdf", "jittered:balance:light-solid-angle+bsdf")
OUT = Path(__file__).resolve().parents[1] / "docs" / "images" / "veach-plates-efficiency.png"


def _run(folder: Path) -> Path:
    from warpis.cli import main

    argv = ["image", "veach-plates-camera", "--n", "16", "--trials", "256", "--out", str(folder)]
    for spec in ESTIMATORS:
        argv += ["--estimator", spec]
    if main(argv) != 0:
        raise SystemExit("warpis image failed")
    return folder / "image.npz"


def _crop(mask: np.ndarray) -> tuple[slice, slice]:
    rows, cols = np.nonzero(mask == 0)
    pad = 2
    return (slice(max(rows.min() - pad, 0), rows.max() + pad + 1),
            slice(max(cols.min() - pad, 0), cols.max() + pad + 1))


def draw(arrays: dict[str, np.ndarray], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm, Normalize

    mask = arrays["mask"]
    crop = _crop(mask)
    panels = [("reference (reflected direct radiance)", arrays["reference"], "inferno",
               Normalize(0, float(np.nanpercentile(arrays["reference"], 99.5)))),
              ("BSDF sampling ÷ light sampling", arrays["relative_efficiency_1"], "RdBu_r", LogNorm(1e-2, 1e2)),
              ("balance MIS ÷ light sampling", arrays["relative_efficiency_2"], "RdBu_r", LogNorm(1e-2, 1e2))]
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 2.3), constrained_layout=True)
    for ax, (title, image, cmap, norm) in zip(axes, panels):
        shown = np.ma.masked_invalid(image[crop])
        im = ax.imshow(shown, cmap=plt.get_cmap(cmap).with_extremes(bad="0.85"), norm=norm,
                       interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        bar = fig.colorbar(im, ax=ax, shrink=0.9)
        bar.ax.tick_params(labelsize=6)
    fig.suptitle("veach-plates-camera, N = 16: per-pixel efficiency 1/(variance × time), red where the estimator "
                 "beats light sampling", fontsize=8)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--from", dest="source", type=Path, default=None, help="an image.npz of the run above")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        source = args.source or _run(Path(tmp) / "image")
        with np.load(source) as data:
            arrays = {k: data[k] for k in data.files}
    draw(arrays, args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
