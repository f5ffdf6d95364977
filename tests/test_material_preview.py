"""The bundled ``mitsuba-material-preview`` scene against Mitsuba's own ``direct`` integrator.

The scene (scripts/make_material_preview.py over warpis.scenes.builders.material_preview):
a procedural HDR sky with a sun (an ``envmap``, rotated), a checkerboard-textured diffuse
floor, and two glossy spheres on one smooth-normal mesh, a gold roughconductor (alpha
0.08) and a blue roughplastic (alpha 0.3).  Its 36 receivers, 12 per surface, are camera hits.

At every receiver, in each of r, g, b and in the luminance y of the RGB result:

* warpis: ``reference`` in each of the channels r, g and b, in fixed mode (the power MIS of ``envmap`` and the receiver's
  BSDF sampling, ``SAMPLES`` jittered samples × 32 replicas), on warpis's own reading of
  the XML (the PFM through Mitsuba's Bitmap, the floor's texture evaluated at each
  receiver, the spheres shaded with their interpolated vertex normals);
* Mitsuba: its ``direct`` integrator (one emitter and one BSDF sample per pass, MIS)
  rendering a ``radiancemeter`` at the camera's position aimed at the receiver, so its
  one ray meets the receiver's point: ``BATCHES`` independent renders of ``SPP`` samples
  each, their mean and standard error (RGB at once; y = Mitsuba's luminance weights).

Tolerance: |F_warpis − F_Mitsuba| ≤ z* · sqrt(se_w² + se_m²), z* = the two-sided normal
quantile at 1e-3 / (2 · 144) (Bonferroni over 36 receivers × 4 channels: family-wise
false failure ≤ 1e-3).  Both sides are means of bounded samples (MIS weights and a
bounded BSDF; the sun is sampled by both sides' emitter sampling), 32 and 64 replicas;
the Student-t tails at z* ≈ 4.5 with 31 degrees of freedom add ≤ 2× to the normal's, so
the family-wise rate stays below 2e-3.  The fixed seeds make every run the same.  The
table (``pytest -s``) prints the worst |z|.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

mi = pytest.importorskip("mitsuba")

from warpis.analysis.reference import reference  # noqa: E402
from warpis.scenes import load_scene, resolve_scene_path  # noqa: E402
from warpis.scenes.mitsuba import CHANNELS  # noqa: E402

NAME = "mitsuba-material-preview"
SAMPLES = 4096
SPP, BATCHES = 4096, 64
COMPARISONS = 36 * 4
Z_STAR = float(norm.ppf(1 - 1e-3 / (2 * COMPARISONS)))


@pytest.fixture(scope="module")
def mitsuba_values():
    """(R, 3) mean and stderr of Mitsuba's direct RGB radiance at each receiver."""
    scene = load_scene(NAME, channel="y")
    mi.set_variant("scalar_rgb")
    ms = mi.load_file(str(resolve_scene_path(NAME)), parallel=False)
    origin = np.array(ms.sensors()[0].world_transform().matrix, dtype=np.float64)[:3, 3]
    means, ses = [], []
    for p in scene.receivers.positions:
        d = (p - origin) / np.linalg.norm(p - origin)
        meter = mi.load_dict({"type": "radiancemeter", "origin": origin.tolist(), "direction": d.tolist(),
                              "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"},
                                       "pixel_format": "rgb"},
                              "sampler": {"type": "independent"}})
        runs = np.array([np.array(mi.render(ms, sensor=meter, spp=SPP, seed=1 + k)).reshape(-1)[:3]
                         for k in range(BATCHES)])
        means.append(runs.mean(axis=0))
        ses.append(runs.std(axis=0, ddof=1) / math.sqrt(BATCHES))
    return scene, np.array(means), np.array(ses)


def test_the_scene_is_what_it_says(mitsuba_values):
    """36 receivers, 12 per surface; an envmap; the spheres shade with vertex normals."""
    scene = mitsuba_values[0]
    rx = scene.receivers
    assert len(rx) == 36 and sorted(rx.group_names) == ["floor", "gold", "plastic"]
    assert scene.environment is not None and scene.emitter_count == 0
    on_spheres = np.isin(rx.group, [rx.group_names.index("gold"), rx.group_names.index("plastic")])
    tilt = np.einsum("ij,ij->i", rx.normals[on_spheres], rx.geometric_normals[on_spheres])
    assert np.all(tilt < 1 - 1e-7)  # interpolated, not the facets'
    floor = rx.group == rx.group_names.index("floor")
    assert len(np.unique(np.round(rx.albedo[floor], 6))) == 2  # both colours of the checker


@pytest.fixture(scope="module")
def warpis_values():
    """(R, 3) warpis's references and stderrs in r, g, b (fixed mode, fixed seed)."""
    values, ses = [], []
    for channel in "rgb":
        refs = reference(load_scene(NAME, channel=channel), samples=SAMPLES)
        values.append([r.value for r in refs])
        ses.append([r.stderr for r in refs])
    return np.array(values).T, np.array(ses).T


@pytest.mark.parametrize("channel", ["y", "r", "g", "b"])
def test_references_match_mitsuba_direct(mitsuba_values, warpis_values, channel):
    """Each of r, g, b, and the luminance y of the RGB result, within z* of Mitsuba's.

    warpis's channel y (luminance of the light times luminance of the BSDF) is not the
    luminance of an RGB result under coloured light on coloured surfaces: the luminance
    compared is that of warpis's r, g, b, its stderr bounded by Σ w_c se_c (the three
    references share seeds, so their errors may correlate)."""
    scene, means, ses = mitsuba_values
    mine, mine_se = warpis_values
    weights = np.array(CHANNELS[channel])
    theirs, their_se = means @ weights, np.sqrt(ses ** 2 @ weights ** 2)
    value, value_se = mine @ weights, mine_se @ weights
    rows, bad, zs = [], [], []
    for i in range(len(value)):
        sigma = math.hypot(value_se[i], their_se[i])
        z = (value[i] - theirs[i]) / sigma
        zs.append(z)
        group = scene.receivers.group_names[scene.receivers.group[i]]
        rows.append(f"  {i:>2} {group:<8} warpis {value[i]:.6f} ± {value_se[i]:.1e}  mitsuba {theirs[i]:.6f} ± "
                    f"{their_se[i]:.1e}  z {z:+.2f}")
        if not abs(z) <= Z_STAR:
            bad.append(i)
    table = "\n".join(rows) + f"\n  worst |z| = {max(abs(z) for z in zs):.2f} (z* = {Z_STAR:.2f})"
    print(f"\n{NAME}, channel {channel}, warpis vs Mitsuba's direct integrator:\n" + table)
    assert not bad, f"receivers {bad} disagree:\n{table}"


def test_channel_y_says_it_is_not_the_luminance_of_rgb():
    """Coloured sky on coloured spheres: warpis's channel y notes how it differs."""
    notes = load_scene(NAME, channel="y").notes
    assert any("channel y multiplies the luminance" in n for n in notes), notes


def test_the_committed_scene_is_its_generator_s():
    """scripts/make_material_preview.py --check: the bundled files are what it writes."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "make_material_preview.py"
    done = subprocess.run([sys.executable, str(script), "--check"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


ESTIMATORS = ("jittered:balance:envmap+bsdf", "independent:power:envmap+bsdf")
ESTIMATOR_TRIALS = 2000
ESTIMATOR_Z = float(norm.ppf(1 - 1e-3 / (2 * 36 * len(ESTIMATORS))))


@pytest.mark.parametrize("spec", ESTIMATORS)
def test_estimators_match_mitsuba_direct(mitsuba_values, spec):
    """Unbiased estimators themselves (not only the reference) on the XML scene — an
    envmap, a textured floor, smooth-normal spheres — agree with Mitsuba's direct
    integrator in channel g: the mean of ``ESTIMATOR_TRIALS`` trials of N = 16 within
    z* combined standard errors (MIS of bounded weights: normal means; Bonferroni over 36
    receivers × 2 estimators, family-wise ≤ 1e-3)."""
    from warpis.kernels.engine import run_trials

    _, means, ses = mitsuba_values
    scene = load_scene(NAME, channel="g")
    x = run_trials(scene, spec, 16, ESTIMATOR_TRIALS, seed=17)
    mine, mine_se = x.mean(axis=1), x.std(axis=1, ddof=1) / math.sqrt(x.shape[1])
    z = (mine - means[:, 1]) / np.hypot(mine_se, ses[:, 1])
    assert np.abs(z).max() <= ESTIMATOR_Z, (spec, np.round(z, 2))


def test_the_generator_check_tells_rounding_from_a_moved_point(tmp_path):
    """`--check` forgives two CPUs' float32 roundings of Mitsuba's hits (seen 1.01e-6
    apart) but not a receiver that moved to another point."""
    from pathlib import Path

    from warpis.scenes.builders.material_preview import _same_points

    committed = Path(__file__).resolve().parents[1] / "meshes" / NAME / "scene.receivers.toml"
    text = committed.read_text()
    first = text.index("    [") + len("    [")
    x = float(text[first:text.index(",", first)])

    def moved_by(dx: float) -> Path:
        path = tmp_path / f"moved-{dx}.toml"
        path.write_text(text[:first] + repr(x + dx) + text[text.index(",", first):])
        return path

    assert _same_points(committed, moved_by(2e-6))
    assert not _same_points(committed, moved_by(1e-3))
