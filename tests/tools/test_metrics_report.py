"""Image metrics, the Šidák Z-test and the crash-safe A/B report folder."""
from __future__ import annotations

import json

import matplotlib.image as mpimg
import mitsuba as mi
import numpy as np
import pytest

from layerbvh_mitsuba.ab import metrics, report

KEYS = {"rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs",
        "frac_pixels_over_1e-3", "mean_abs", "mean_ref", "pixels"}
H, W = 24, 32  # not square, so a transposed output is caught


def _img(seed=0, lo=0.1, hi=0.8, shape=(H, W, 3)):
    return np.random.default_rng(seed).uniform(lo, hi, shape).astype(np.float32)


# --- metrics -------------------------------------------------------------------------------------

def test_tonemap_srgb_known_values():
    x = np.array([-1.0, 0.0, 0.002, 0.5, 1.0, 4.0], np.float32)
    expect = [0.0, 0.0, 12.92 * 0.002, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0, 1.0]
    np.testing.assert_allclose(metrics.tonemap_srgb(x), expect, atol=1e-6)


def test_identical_images_give_zero_errors():
    a = _img()
    m = metrics.compare_images(a, a.copy())
    assert set(m) == KEYS
    for k in KEYS - {"mean_ref", "pixels"}:
        assert m[k] == 0.0, k
    assert m["pixels"] == H * W
    assert m["mean_ref"] == pytest.approx(float(a.mean()), rel=1e-6)


def test_constant_offset():
    a = _img()
    m = metrics.compare_images(a, a + np.float32(0.01))
    assert m["rmse"] == pytest.approx(0.01, rel=1e-4)
    assert m["max_abs"] == pytest.approx(0.01, rel=1e-4)
    assert m["mean_abs"] == pytest.approx(0.01, rel=1e-4)
    assert m["frac_pixels_over_1e-3"] == 1.0
    assert m["flip_mean"] > 0.0


def test_rel_mse_by_hand():
    ref = np.array([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], np.float32)
    test = np.array([[[0.1, 0.0, 0.0], [1.0, 1.0, 0.5]]], np.float32)
    # terms: 0.1^2/(0 + 0.01) = 1 and 0.5^2/(1 + 0.01); the other four are 0
    expect = (1.0 + 0.25 / 1.01) / 6.0
    m = metrics.compare_images(ref, test)
    assert m["rel_mse"] == pytest.approx(expect, rel=1e-5)
    assert m["frac_pixels_over_1e-3"] == 1.0
    assert m["max_abs"] == pytest.approx(0.5)


def test_frac_over_threshold_counts_pixels_not_channels():
    a = np.zeros((2, 2, 3), np.float32)
    b = a.copy()
    b[0, 0, 2] = 0.01  # one channel of one pixel
    b[1, 1, :] = 0.0005  # below the threshold
    assert metrics.compare_images(a, b)["frac_pixels_over_1e-3"] == 0.25


def test_channel_normalisation():
    g = _img(shape=(H, W))
    rgb = np.repeat(g[:, :, None], 3, axis=2)
    rgba = np.concatenate([rgb, np.full((H, W, 1), 7.0, np.float32)], axis=2)
    assert metrics.as_rgb(g).shape == (H, W, 3)
    np.testing.assert_array_equal(metrics.as_rgb(g[:, :, None]), rgb)
    np.testing.assert_array_equal(metrics.as_rgb(rgba), rgb)  # alpha dropped, not compared
    assert metrics.compare_images(g, rgba)["max_abs"] == 0.0


def test_delta_e2000():
    red = np.zeros((4, 4, 3), np.float32)
    red[..., 0] = 1.0
    green = np.zeros((4, 4, 3), np.float32)
    green[..., 1] = 1.0
    same = metrics.compare_images(red, red)
    assert same["delta_e2000_mean"] == 0.0 and same["delta_e2000_p95"] == 0.0
    m = metrics.compare_images(red, green)
    assert m["delta_e2000_mean"] > 50.0
    assert m["delta_e2000_p95"] > 50.0


def test_flip():
    a = _img(1)
    fmap, mean = metrics.flip_error_map(a, a)
    assert fmap.shape == (H, W) and mean == 0.0 and float(fmap.max()) == 0.0
    b = _img(2, 0.0, 1.0)
    fmap, mean = metrics.flip_error_map(np.zeros_like(b), b)
    assert mean > 0.1
    assert fmap.shape == (H, W) and 0.0 <= fmap.min() and fmap.max() <= 1.0
    assert float(fmap.mean()) == pytest.approx(mean, rel=1e-4)
    assert metrics.compare_images(np.zeros_like(b), b)["flip_mean"] == pytest.approx(mean)


def test_shape_mismatch_names_both_shapes():
    with pytest.raises(ValueError) as e:
        metrics.compare_images(np.zeros((4, 5, 3), np.float32), np.zeros((5, 4, 3), np.float32))
    assert "(4, 5, 3)" in str(e.value) and "(5, 4, 3)" in str(e.value)


def test_nonfinite_inputs_rejected():
    a = _img()
    b = a.copy()
    b[0, 0, 1] = np.nan
    b[3, 4, :] = np.nan  # one pixel, three channels
    with pytest.raises(ValueError, match=r"test image has 2 pixel"):
        metrics.compare_images(a, b)
    c = a.copy()
    c[5, 5, 0] = np.inf
    with pytest.raises(ValueError, match=r"ref image has 1 pixel"):
        metrics.compare_images(c, a)


# --- Z-test --------------------------------------------------------------------------------------

N_SPP, RES = 64, 32


def _estimate(seed: int, truth: np.ndarray, sigma: float):
    """Per-pixel mean and per-sample variance from N_SPP noisy samples."""
    s = np.random.default_rng(seed).normal(truth, sigma, (N_SPP, *truth.shape))
    return s.mean(axis=0), s.var(axis=0, ddof=1)


@pytest.fixture(scope="module")
def truth():
    return np.random.default_rng(7).uniform(0.4, 0.9, (RES, RES, 3))


# sigma 0.01 per sample: a 5% scale of values >= 0.4 is >= 11 standard errors, far past the
# Šidák-corrected critical z of ~4.4, while unbiased estimates essentially never cross it.
SIGMA = 0.01


def test_zscore_same_distribution_passes(truth):
    a, va = _estimate(1, truth, SIGMA)
    b, vb = _estimate(2, truth, SIGMA)
    r = metrics.pixel_test(a, va, b, vb, N_SPP, N_SPP)[0]
    assert r["pixels"] == RES * RES
    assert r["threshold"] == pytest.approx(1 - 0.99 ** (1 / (RES * RES)), rel=1e-9)
    assert r["pass_fraction"] >= 0.975
    assert 0.0 < r["min_p"] <= 1.0


def test_zscore_scaled_albedo_fails(truth):
    a, va = _estimate(1, truth, SIGMA)
    b, vb = _estimate(2, truth * 1.05, SIGMA * 1.05)
    r = metrics.pixel_test(a, va, b, vb, N_SPP, N_SPP)[0]
    assert r["pass_fraction"] < 0.9
    assert r["min_p"] < r["threshold"]


def test_zscore_zero_variance_guard():
    m = np.full((2, 2, 3), 0.5)
    z = np.zeros_like(m)
    assert metrics.pixel_test(m, z, m + 1e-8, z, 4, 4)[0]["pass_fraction"] == 1.0
    off = m.copy()
    off[0, 0, 0] += 0.1
    r = metrics.pixel_test(m, z, off, z, 4, 4)[0]
    assert r["pass_fraction"] == 0.75 and r["min_p"] == 0.0


# --- report --------------------------------------------------------------------------------------

FILES = {"stock.exr", "ours.exr", "stock.png", "ours.png", "flip.png", "diff.png", "report.json", "index.html"}


def _info():
    return {
        "scene": "cbox <test> & co",
        "spp": np.int64(16),
        "resolution": (W, H),
        "seed": 3,
        "stock": {"render_s": np.float32(1.5), "variant": "llvm_ad_rgb"},
        "ours": {"render_s": 2.25, "build_s": 0.5, "nan_field": float("nan")},
        "traversal": {"rays": 1000, "per_level": {"nodes": list(range(40)), "mean": np.float64(3.5)}},
        "features": {"emitters": True},
    }


def _pair():
    stock = _img(11, 0.0, 1.5)  # above 1 on purpose: EXR must keep it, PNG clips it
    ours = stock * np.float32(1.02)
    return stock, ours


def test_write_report_files(tmp_path):
    stock, ours = _pair()
    out = tmp_path / "run"
    rep = report.write_report(out, stock, ours, _info())

    assert {p.name for p in out.iterdir()} == FILES
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # temp folder gone

    loaded = json.loads((out / "report.json").read_text())
    assert loaded == rep
    assert set(loaded["metrics"]) == KEYS
    assert loaded["metrics"]["rmse"] == pytest.approx(metrics.compare_images(stock, ours)["rmse"])
    assert loaded["spp"] == 16 and loaded["stock"]["render_s"] == 1.5
    assert loaded["ours"]["nan_field"] is None  # NaN is not JSON

    for name in ("stock.png", "ours.png", "flip.png", "diff.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert mpimg.imread(out / name).shape[:2] == (H, W), name
    png = mpimg.imread(out / "stock.png")[..., :3]
    np.testing.assert_allclose(png, metrics.tonemap_srgb(stock), atol=1 / 255 + 1e-6)

    for name, img in (("stock.exr", stock), ("ours.exr", ours)):
        back = np.array(mi.Bitmap(str(out / name)))
        assert back.shape == (H, W, 3)
        np.testing.assert_allclose(back, img, atol=1e-6)

    page = (out / "index.html").read_text()
    assert "cbox &lt;test&gt; &amp; co" in page and "cbox <test>" not in page
    assert '<img src="diff.png"' in page and '<img src="flip.png"' in page and '<canvas id="view"' in page
    assert "BVH build" in page and "ours ÷ stock" in page and "1.50×" in page  # 2.25 s against 1.5 s
    # Ours is 2% brighter everywhere: the verdict says it differs, in the page and in report.json.
    assert loaded["verdict"]["passed"] is False and 'id="verdict" data-passed="false"' in page
    assert loaded["verdict"]["values"]["frac_within"] == pytest.approx(
        metrics.same_seed_verdict(stock, ours)["values"]["frac_within"])


def test_write_report_replaces_an_earlier_report_whole(tmp_path):
    """A report folder holds the files of one run: an earlier report is replaced as a whole
    (a file left from it would no longer belong to the report), and a folder that is not a
    report is never replaced."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("from the earlier run")
    (out / "report.json").write_text("stale")
    stock, ours = _pair()
    report.write_report(out, stock, ours, _info())
    assert {p.name for p in out.iterdir()} == FILES
    assert json.loads((out / "report.json").read_text())["scene"] == "cbox <test> & co"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not a layerbvh output"):
        report.write_report(theirs, stock, ours, _info())
    assert [p.name for p in theirs.iterdir()] == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "theirs"]


def _explode(*_a, **_k):
    raise RuntimeError("disk on fire")


def test_crash_leaves_nothing_behind(tmp_path, monkeypatch):
    written = []
    real = report._write_bytes

    def spy(path, data):
        written.append(path.name)
        real(path, data)

    monkeypatch.setattr(report, "_write_bytes", spy)
    monkeypatch.setattr(report, "render_html", _explode)  # last step, after everything else
    stock, ours = _pair()
    with pytest.raises(RuntimeError, match="disk on fire"):
        report.write_report(tmp_path / "run", stock, ours, _info())
    assert "report.json" in written and "stock.png" in written  # the crash really came late
    assert list(tmp_path.iterdir()) == []


def test_crash_keeps_existing_report_intact(tmp_path, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    (out / "report.json").write_text('{"old": true}')
    monkeypatch.setattr(report, "render_html", _explode)
    stock, ours = _pair()
    with pytest.raises(RuntimeError):
        report.write_report(out, stock, ours, _info())
    assert [p.name for p in out.iterdir()] == ["report.json"]
    assert json.loads((out / "report.json").read_text()) == {"old": True}
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_json_safe_converts_numpy_and_drops_nonfinite():
    rep = report.json_safe({"a": np.float32("inf"), "b": (np.nan, np.int8(1)), "c": {np.int32(1): np.bool_(True)},
                             "d": np.arange(3, dtype=np.uint16)})
    assert rep == {"a": None, "b": [None, 1], "c": {"1": True}, "d": [0, 1, 2]}
    assert type(rep["b"][1]) is int and type(rep["c"]["1"]) is bool
    json.dumps(rep, allow_nan=False)
