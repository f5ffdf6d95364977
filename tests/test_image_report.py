"""The pictures and the page of ``warpis image``, from synthetic per-pixel arrays (no kernels)."""

from __future__ import annotations

import html
import json

import matplotlib.pyplot as plt
import numpy as np
import pytest

from warpis.runs import image_report as ir
from warpis.runs import outdir

H, W = 24, 32
SCENE = "<script>alert('x')</script> & co $\\frac{"  # unbalanced mathtext too: titles must show it as text
SPECS = ["jittered:balance:light-solid-angle+bsdf", "independent:bsdf", "custom:<a&b>"]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
STEMS = ["mean", "single", "variance", "predicted", "ratio", "rel_error", "efficiency", "winner"]


def synthetic() -> tuple[dict[str, np.ndarray], dict]:
    """A 24×32 image: a masked corner of each kind, 3 estimators, partial and missing
    predictions, zero variance in an umbra of estimator 1, one hot pixel in mean_1."""
    rng = np.random.default_rng(1)
    mask = np.zeros((H, W), np.int8)
    mask[:4, :8] = 1  # sees nothing
    mask[:4, -8:] = 2  # sees an emitter
    mask[-4:, :8] = 3  # sees a back face
    off = mask != 0
    y, x = np.mgrid[0:H, 0:W]
    reference = 1.0 + x / W + y / H
    arrays: dict[str, np.ndarray] = {"mask": mask, "reference": reference, "reference_stderr": reference * 1e-3}
    efficiencies = []
    for i in range(3):
        variance = (0.01 * (i + 1)) * reference**2 * rng.uniform(0.5, 2.0, (H, W))
        if i == 1:
            variance[10:14, 10:20] = 0.0  # an umbra: no variance at all
        predicted = variance * rng.uniform(0.8, 1.25, (H, W))
        if i == 1:
            predicted[:, W // 2:] = np.nan  # predicted on a subset of pixels only
        if i == 2:
            predicted[:] = np.nan  # no exact form
        cost = np.full((H, W), 1e-6 * (i + 1))
        with np.errstate(divide="ignore", invalid="ignore"):
            efficiency = 1.0 / (variance * cost)
            ratio = variance / predicted
        mean = reference + rng.normal(0, 0.01, (H, W))
        if i == 1:
            mean[12, 5] = 1e6  # one hot pixel must not wash out the shared scale
        arrays |= {f"mean_{i}": mean, f"single_{i}": reference + rng.normal(0, 0.3, (H, W)),
                   f"variance_{i}": variance, f"variance_lo_{i}": variance * 0.8, f"variance_hi_{i}": variance * 1.2,
                   f"predicted_{i}": predicted, f"predicted_stderr_{i}": predicted * 0.01, f"ratio_{i}": ratio,
                   f"rel_error_{i}": np.sqrt(variance) / reference, f"cost_{i}": cost, f"efficiency_{i}": efficiency}
        efficiencies.append(efficiency)
    with np.errstate(invalid="ignore"):
        for i in range(3):
            arrays[f"relative_efficiency_{i}"] = efficiencies[i] / efficiencies[0]
    winner = np.argmax(np.stack(efficiencies), axis=0).astype(np.int16)
    winner[20:22, 20:22] = -1  # undefined at a receiver
    for key, a in arrays.items():
        if key != "mask":
            arrays[key] = np.where(off, np.nan, a)
    winner[off] = -1
    arrays["winner"] = winner
    summary = [
        {"estimator": SPECS[0], "median_relative_efficiency": 1.0, "wins_share": 0.125, "median_variance": 0.0123,
         "median_ratio": 1.02},
        {"estimator": SPECS[1], "median_relative_efficiency": 2.5, "wins_share": 0.75, "median_variance": 0.0456,
         "median_ratio": 0.97},
        {"estimator": SPECS[2], "median_relative_efficiency": 0.333, "wins_share": 0.125, "median_variance": 0.0789,
         "median_ratio": None},
    ]
    meta = {
        "scene": SCENE, "estimators": SPECS, "baseline": 0, "n": 16, "trials": 64, "seed": 7, "width": W, "height": H,
        "command": "warpis image scene.toml --estimators 'custom:<a&b>'", "seconds": 12.34,
        "prediction": "exact variance from 4096 dense points per pixel and technique; median relative error 3%",
        "summary": summary, "masked": {"nothing": 32, "emitter": 32, "back": 32},
    }
    return arrays, meta


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """The pictures and the page of the synthetic run, written once for the module."""
    out = tmp_path_factory.mktemp("image")
    arrays, meta = synthetic()
    pictures = ir.write_pictures(out, arrays, meta)
    index = ir.write_index(out, meta, pictures)
    return out, pictures, index, arrays, meta


def read_png(path) -> np.ndarray:
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    return plt.imread(path)


# --------------------------------------------------------------------------- pictures


def test_every_picture_is_a_png_of_a_plausible_shape(report):
    out, pictures, _, _, _ = report
    assert [p.stem for p in pictures] == STEMS
    for path in pictures:
        assert path.parent == out and path.suffix == ".png"
        image = read_png(path)
        h, w = image.shape[:2]
        assert 100 < h < 1500 and 100 < w < 2000, (path.name, image.shape)
        assert path.stat().st_size < 400_000
    # four wide panels in a row: a wide picture, wider than the one-panel winner map
    mean, winner = read_png(out / "mean.png"), read_png(out / "winner.png")
    assert mean.shape[1] > 2 * mean.shape[0]
    assert mean.shape[1] / mean.shape[0] > winner.shape[1] / winner.shape[0]


def test_writes_leave_no_temporary_files(report):
    out = report[0]
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"{s}.png" for s in STEMS] + ["index.html"])
    assert not any(n.endswith(outdir.TMP_SUFFIX) or n.startswith(".") for n in names)


def test_pictures_without_any_prediction_leave_out_predicted_and_ratio(tmp_path):
    arrays, meta = synthetic()
    for i in range(3):
        arrays[f"predicted_{i}"] = np.full((H, W), np.nan)
        arrays[f"ratio_{i}"] = np.full((H, W), np.nan)
    stems = [p.stem for p in ir.write_pictures(tmp_path, arrays, dict(meta, baseline=1))]
    assert stems == ["mean", "single", "variance", "rel_error", "efficiency", "winner"]


def test_one_estimator_has_no_efficiency_picture(tmp_path):
    arrays, meta = synthetic()
    arrays["winner"] = np.where(arrays["mask"] != 0, -1, 0).astype(np.int16)
    stems = [p.stem for p in ir.write_pictures(tmp_path, arrays, dict(meta, estimators=SPECS[:1]))]
    assert "efficiency" not in stems and "winner" in stems


def test_a_missing_array_is_named(tmp_path):
    arrays, meta = synthetic()
    del arrays["rel_error_2"]
    with pytest.raises(KeyError, match="rel_error_2"):
        ir.write_pictures(tmp_path, arrays, meta)


def grey_pixels(image: np.ndarray, rgb) -> np.ndarray:
    """Where a read-back PNG has the colour ``rgb`` (up to one step of 8-bit rounding)."""
    return np.all(np.abs(image[..., :3] * 255 - np.array(rgb) * 255) <= 1.0, axis=-1)


def test_save_image_draws_masked_pixels_light_grey_at_the_top(tmp_path):
    image = np.arange(24, dtype=float).reshape(4, 6) + 1.0
    mask = np.zeros((4, 6), np.int8)
    mask[0] = 2  # the top row sees an emitter
    image[0] = np.nan
    path = ir.save_image(tmp_path / "one.png", image, mask, log=False, label="radiance", title="a <tiny> image")
    back = read_png(path)
    grey = grey_pixels(back, ir.MASKED_RGB)
    assert grey.sum() > 500
    # the band: rows and columns full of grey (a few text edges elsewhere are grey-ish too)
    rows, cols = np.nonzero(grey.sum(axis=1) > 50)[0], np.nonzero(grey.sum(axis=0) > 20)[0]
    # one row of six pixels: a band six times as wide as it is tall...
    aspect = (cols.max() - cols.min() + 1) / (rows.max() - rows.min() + 1)
    assert aspect == pytest.approx(6.0, rel=0.1)
    # ...at the top of the picture (row 0 is the top), above the drawn values
    below = back[rows.max() + 2, (cols.min() + cols.max()) // 2, :3]
    assert not np.allclose(below, ir.MASKED_RGB, atol=0.01)
    top = back[rows.min() - 6, cols.min() + 3, :3]  # above the frame, beside the title
    assert np.allclose(top, 1.0)  # white figure background above the image
    unmasked = ir.save_image(tmp_path / "two.png", np.abs(image), np.zeros_like(mask), log=True, label="v", title="t")
    assert grey_pixels(read_png(unmasked), ir.MASKED_RGB).sum() < 20  # at most anti-aliased text edges


def test_save_image_rejects_mismatched_shapes(tmp_path):
    with pytest.raises(ValueError, match="same"):
        ir.save_image(tmp_path / "x.png", np.ones((2, 3)), np.zeros((3, 2)), log=False, label="", title="")


# --------------------------------------------------------------------------- scales and colours


def test_shared_log_range_ignores_nan_zero_negative_and_inf():
    a = np.array([[1e-3, np.nan], [0.0, -1.0]])
    b = np.array([[np.inf, 10.0], [0.5, np.nan]])
    assert ir.shared_log_range([a, b], clip=0) == pytest.approx((1e-3, 10.0))
    lo, hi = ir.shared_log_range([a, b])  # percentile clip: inside the exact range
    assert 1e-3 <= lo < hi <= 10.0
    assert ir.shared_log_range([np.full((2, 2), np.nan), np.zeros((2, 2))]) is None
    assert ir.shared_log_range([np.full((2, 2), 3.0)]) == pytest.approx((1.5, 6.0))


def test_percentile_clip_keeps_one_outlier_from_stretching_a_log_scale():
    values = np.full(1000, 1.0)
    values[0] = 1e-12
    values[1:500] = 2.0
    lo, hi = ir.shared_log_range([values])
    assert lo == pytest.approx(1.0) and hi == pytest.approx(2.0)


def test_linear_range_clips_a_hot_pixel_and_starts_at_zero():
    image = np.linspace(1.0, 2.0, 1000)
    image[3] = 1e6
    lo, hi = ir.linear_range([image, np.array([np.nan, np.inf])])
    assert lo == 0.0 and 1.9 < hi < 2.0
    assert ir.linear_range([np.array([np.nan])]) is None
    assert ir.linear_range([np.zeros(3)]) == (0.0, 1.0)


def test_diverging_span_is_symmetric_capped_and_floored():
    assert ir.diverging_span([np.array([0.5, 1.5, np.nan, 0.0, np.inf])], cap=10) == pytest.approx(2.0)
    assert ir.diverging_span([np.array([1e-4, 3.0])], cap=10) == 10.0
    assert ir.diverging_span([np.array([1.0, 1.01])], cap=10) == ir.MIN_SPAN
    assert ir.diverging_span([np.array([np.nan])], cap=10) == ir.MIN_SPAN


def test_picture_scales_are_shared_between_panels_and_pictures():
    arrays, meta = synthetic()
    scales = ir.picture_scales(arrays, meta)
    assert scales["predicted"] is scales["variance"]
    assert scales["single"] is scales["mean"]
    every = [arrays[f"{name}_{i}"] for name in ("variance", "predicted") for i in range(3)]
    assert (scales["variance"].vmin, scales["variance"].vmax) == pytest.approx(ir.shared_log_range(every))
    assert scales["mean"].vmax < 10  # the hot pixel in mean_1 is clipped, not the top of the scale
    ratio = scales["ratio"]
    assert ratio.kind == "diverging" and ratio.vmin * ratio.vmax == pytest.approx(1.0)
    assert ratio.vmax <= ir.RATIO_CAP
    # the baseline's own panel (all ones) is left out of the efficiency scale: the span is data's
    eff = scales["efficiency"]
    assert eff.vmin * eff.vmax == pytest.approx(1.0) and eff.vmax <= ir.EFFICIENCY_CAP


def test_colorize_gives_each_kind_of_pixel_its_colour():
    scale = ir.Scale("log", 1e-2, 1e2, "v")
    image = np.array([[np.nan, np.nan, 0.0, 1.0, 1e9]])
    mask = np.array([[3, 0, 0, 0, 0]])
    rgba = ir.colorize(image, mask, scale)
    assert np.allclose(rgba[0, 0, :3], ir.MASKED_RGB)
    assert np.allclose(rgba[0, 1, :3], ir.MISSING_RGB)
    assert np.allclose(rgba[0, 2, :3], ir.ZERO_RGB)
    assert np.allclose(rgba[0, 3], scale.cmap(0.5), atol=0.01)  # the middle of the scale
    assert np.allclose(rgba[0, 4], scale.cmap(1.0))  # above the scale: the top colour
    diverging = ir.Scale("diverging", 0.1, 10.0, "r")
    rgba = ir.colorize(np.array([[0.0, np.inf, 1.0]]), np.zeros((1, 3)), diverging)
    assert np.allclose(rgba[0, 0], diverging.cmap(0.0)) and np.allclose(rgba[0, 1], diverging.cmap(1.0))
    assert np.allclose(rgba[0, 2], diverging.cmap(0.5), atol=0.01)


def test_special_colours_are_not_in_the_colour_maps():
    for name in (ir.LINEAR_CMAP, ir.LOG_CMAP, ir.DIVERGING_CMAP):
        colours = plt.get_cmap(name)(np.linspace(0, 1, 256))[:, :3]
        for rgb in (ir.MASKED_RGB, ir.MISSING_RGB):
            assert np.min(np.abs(colours - rgb).sum(axis=1)) > 0.1, (name, rgb)


def test_titles_wrap_long_specs_and_show_dollars_as_text():
    text = "stratified:balance:light-solid-angle+light-area+bsdf+cosine"
    wrapped = ir._wrap(text, 20)
    assert wrapped.replace("\n", "") == text
    assert all(len(line) <= 20 for line in wrapped.splitlines())
    assert ir._tex_safe("a$b") == "a\\$b"


# --------------------------------------------------------------------------- the page


def test_index_escapes_every_string_from_meta(report):
    page = report[2].read_text(encoding="utf-8")
    assert "<script>" not in page and "<a&b>" not in page
    assert html.escape(SCENE, quote=True) in page
    for spec in SPECS:
        assert html.escape(spec, quote=True) in page
    assert "custom:&lt;a&amp;b&gt;" in page
    assert "<link" not in page and "<script" not in page and "http" not in page  # self-contained


def test_index_shows_the_summary_numbers(report):
    page = report[2].read_text(encoding="utf-8")
    for text in ("2.5", "0.333", "75.0%", "12.5%", "0.0123", "0.0456", "1.02", "0.97", "—", "(baseline)"):
        assert text in page, text
    assert page.count("<tr>") == 1 + len(SPECS)


def test_index_links_every_picture_and_the_numbers(report):
    out, pictures, index, _, meta = report
    page = index.read_text(encoding="utf-8")
    for path in pictures:
        assert f'src="{path.name}"' in page and f'href="{path.name}"' in page
        assert html.escape(ir.DESCRIPTIONS[path.stem]) in page
    assert 'href="image.npz"' in page
    assert 'href="image.exr"' not in page  # none written here


def test_index_shows_the_run(report):
    page = report[2].read_text(encoding="utf-8")
    meta = report[4]
    for text in (html.escape(meta["command"]), "12.3 s", ">16<", ">64<", ">7<", "32 × 24",
                 html.escape(meta["prediction"]), "sees nothing: 32", "sees an emitter: 32",
                 "sees the back of a one-sided surface: 32", "receivers (measured): 672 of 768", "light grey"):
        assert text in page, text


def test_index_links_pictures_in_a_subfolder(tmp_path):
    (tmp_path / "figures").mkdir()
    picture = tmp_path / "figures" / "a b.png"
    picture.write_bytes(PNG_SIGNATURE)
    page = ir.write_index(tmp_path, {"scene": "s", "estimators": ["x"], "baseline": 0}, [picture]).read_text()
    assert 'src="figures/a%20b.png"' in page
    assert [p.name for p in tmp_path.iterdir() if p.is_file()] == ["index.html"]


# --------------------------------------------------------------------------- OpenEXR


def test_exr_channel_names():
    assert ir.exr_channel("variance_lo_3") == "variance_lo.3"
    assert ir.exr_channel("mask") == "mask" and ir.exr_channel("reference_stderr") == "reference_stderr"


def test_write_exr_without_openexr_returns_none(tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def no_openexr(name, *args, **kwargs):
        if name in ("OpenEXR", "Imath"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_openexr)
    arrays, meta = synthetic()
    assert ir.write_exr(tmp_path, arrays, meta) is None
    assert list(tmp_path.iterdir()) == []


def test_write_exr_holds_every_array(tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR", reason="OpenEXR is optional: image.exr is written only with it")
    Imath = pytest.importorskip("Imath", reason="OpenEXR's Imath module is needed to read channels back")
    arrays, meta = synthetic()
    path = ir.write_exr(tmp_path, arrays, meta)
    assert path == tmp_path / "image.exr"
    assert [p.name for p in tmp_path.iterdir()] == ["image.exr"]
    exr = OpenEXR.InputFile(str(path))
    header = exr.header()
    assert set(header["channels"]) == {ir.exr_channel(k) for k in arrays}
    assert json.loads(header["warpis_estimators"]) == SPECS
    pixels = exr.channel("variance.1", Imath.PixelType(Imath.PixelType.FLOAT))
    back = np.frombuffer(pixels, np.float32).reshape(H, W)
    np.testing.assert_array_equal(back, arrays["variance_1"].astype(np.float32))
    exr.close()
