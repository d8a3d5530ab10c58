"""A/B report folder for stock vs ours (EXRs, PNGs, error and heat maps, derivative images, report.json with the
verdict, index.html), written whole."""
from __future__ import annotations

import io
import json
import math
from numbers import Integral, Real
from pathlib import Path

import numpy as np

from layerbvh_mitsuba.ab import metrics, page
from layerbvh_mitsuba.ab.compare import Comparison
from layerbvh_mitsuba.ab.gradient import GradientComparison
from layerbvh_mitsuba.ab.render import write_exr
from layerbvh_mitsuba.ab.verdict import Verdict, same_seed_only
from layerbvh_mitsuba.atomic import atomic_folder

# diff.png shows the largest channel of |ours - stock| per pixel, scaled so that its 99th
# percentile is the top of the colour map (viridis): the scale adapts to how close the images are,
# and is written on the page's colour bar.
DIFF_PERCENTILE = 99.0


def to_png_bytes(rgb01: np.ndarray) -> bytes:
    """Encode an (H, W, 3) image with values in [0, 1] (already display-encoded) as 8-bit RGB PNG."""
    from PIL import Image  # Pillow ships with matplotlib

    u8 = np.round(np.clip(rgb01, 0.0, 1.0) * 255.0).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(u8), "RGB").save(buf, format="PNG")
    return buf.getvalue()


def _colour_map(values: np.ndarray, cmap: str) -> np.ndarray:
    """(H, W) values in [0, 1] -> (H, W, 3) colours of a matplotlib colour map."""
    from matplotlib import colormaps  # local: matplotlib loads only when a plot is drawn

    return colormaps[cmap](np.clip(values, 0.0, 1.0))[..., :3]


def diff_map(stock: np.ndarray, ours: np.ndarray) -> tuple[np.ndarray, float]:
    """The per-pixel largest channel of |ours - stock| divided by its DIFF_PERCENTILE-th
    percentile (the scale), and that scale (0 when the images are equal)."""
    d = np.abs(ours.astype(np.float64) - stock).max(-1)
    scale = float(np.percentile(d, DIFF_PERCENTILE))
    if scale <= 0:
        scale = float(d.max())
    return (d / scale if scale > 0 else d), scale


def json_safe(x):
    """Plain JSON types only: numpy scalars/arrays unwrapped, NaN/Inf become null."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, set, frozenset)):
        items = sorted(x, key=repr) if isinstance(x, (set, frozenset)) else x
        return [json_safe(v) for v in items]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, Integral):
        return int(x)
    if isinstance(x, Real):
        f = float(x)
        return f if math.isfinite(f) else None
    if x is None or isinstance(x, str):
        return x
    return str(x)  # paths, enums, ...: a report should not die over an exotic info value


def render_html(rep: dict, stock: np.ndarray, ours: np.ndarray, maps: dict, heatmaps: list,
                gradient: list | None = None) -> str:
    """The self-contained index.html (page.render_page)."""
    return page.render_page(rep, stock, ours, maps, heatmaps, gradient)


def _write_bytes(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)


def gradient_pngs(stock: np.ndarray, ours: np.ndarray) -> tuple[bytes, bytes, float]:
    """Two signed derivative images (the largest-magnitude channel of each pixel, sign kept) in
    one diverging colour map (RdBu: red positive, blue negative, white 0), both scaled by the
    DIFF_PERCENTILE-th percentile of stock's |values|; and that scale."""
    def signed(img):
        idx = np.abs(img).argmax(-1)[..., None]
        return np.take_along_axis(img, idx, -1)[..., 0]
    s, o = signed(stock), signed(ours)
    scale = float(np.percentile(np.abs(s), DIFF_PERCENTILE)) or float(np.abs(s).max()) or 1.0
    png = (lambda v: to_png_bytes(_colour_map(0.5 - 0.5 * np.clip(v / scale, -1, 1), "RdBu")))
    return png(s), png(o), scale


def _write_gradient(tmp: Path, g: GradientComparison | None) -> list:
    """The derivative images of a gradient comparison (EXR and PNG), as the page's figures."""
    if g is None or g.stock.forward is None:
        return []
    write_exr(tmp / "stock_grad.exr", g.stock.forward.astype(np.float32))
    write_exr(tmp / "ours_grad.exr", g.ours.forward.astype(np.float32))
    s_png, o_png, scale = gradient_pngs(g.stock.forward, g.ours.forward)
    _write_bytes(tmp / "stock_grad.png", s_png)
    _write_bytes(tmp / "ours_grad.png", o_png)
    bar = page.colour_bar("RdBu_r", f"−{scale:.3g}", f"{scale:.3g}", f"d image / d {g.key} (the largest channel, "
                          f"signed); the ends are the {DIFF_PERCENTILE:g}th percentile of |stock|")
    return [("stock", "stock_grad.png", bar), ("ours", "ours_grad.png", bar)]


def _write_all(tmp: Path, stock: np.ndarray, ours: np.ndarray, rep: dict, flip_map: np.ndarray,
               heatmaps: dict, judged: Verdict | None, gradient: GradientComparison | None = None) -> None:
    write_exr(tmp / "stock.exr", stock)
    write_exr(tmp / "ours.exr", ours)
    _write_bytes(tmp / "stock.png", to_png_bytes(metrics.tonemap_srgb(stock)))
    _write_bytes(tmp / "ours.png", to_png_bytes(metrics.tonemap_srgb(ours)))
    _write_bytes(tmp / "flip.png", to_png_bytes(_colour_map(flip_map, "magma")))
    diff, scale = diff_map(stock, ours)
    _write_bytes(tmp / "diff.png", to_png_bytes(_colour_map(diff, "viridis")))
    maps = {"|ours − stock|": ("diff.png", page.colour_bar("viridis", "0", f"{scale:.3g}",
                                                           f"largest channel of |ours − stock| (linear radiance); the "
                                                           f"top is its {DIFF_PERCENTILE:g}th percentile")),
            "ꟻLIP": ("flip.png", page.colour_bar("magma", "0", "1", "ꟻLIP error per pixel (0 = identical)"))}
    family = None if judged is None else judged.family
    if family is not None:
        # Where the verdict's tests reject equal means (hypotheses.Family.rejection_map), over the stock image.
        h, w = stock.shape[:2]
        where = family.rejection_map(h, w)
        colours = 0.25 + 0.5 * metrics.tonemap_srgb(stock)
        colours = np.where((where == 1)[..., None], np.array([0.95, 0.55, 0.1]), colours)
        colours = np.where((where == 2)[..., None], np.array([0.85, 0.1, 0.1]), colours)
        _write_bytes(tmp / "z_fail.png", to_png_bytes(colours))
        n = len(family.rejections)
        maps["where the tests reject equal means"] = (
            "z_fail.png", page.legend(f"{n} of {sum(family.counts.values())} tests reject; orange: a rejected "
                                      f"tile (or, everywhere, the image mean), red: a rejected pixel of the "
                                      f"independent-seed film; grey: the stock image"))
    heat = []
    for name, img in sorted(heatmaps.items(), key=lambda kv: list(HEATMAP_TITLES).index(kv[0])
                            if kv[0] in HEATMAP_TITLES else len(HEATMAP_TITLES)):
        png, top = heatmap_png(img)
        _write_bytes(tmp / f"heat_{name}.png", png)
        write_exr(tmp / f"heat_{name}.exr", np.repeat(img[:, :, None], 3, 2))
        heat.append((HEATMAP_TITLES.get(name, name), f"heat_{name}.png",
                     page.colour_bar("inferno", "0", f"{top:.3g}", "per pixel sample (mean)")))
    grad = _write_gradient(tmp, gradient)
    _write_bytes(tmp / "report.json", (json.dumps(rep, indent=2, allow_nan=False) + "\n").encode())
    _write_bytes(tmp / "index.html", render_html(rep, stock, ours, maps, heat, grad).encode())


REPORT_MARKER = "report.json"  # the file that makes a folder a compare report


def write_report(out_dir, stock_img, ours_img, info: dict, heatmaps: dict | None = None,
                 judged: Verdict | None = None, measured: tuple[dict, np.ndarray] | None = None,
                 gradient: GradientComparison | None = None) -> dict:
    """Write the stock-vs-ours report folder `out_dir` and return the report dict (= report.json).

    `judged` is the two-step verdict (verdict.judge); without it only the same-seed step is
    taken from the images. `measured`: the images' metrics and ꟻLIP map where the caller has them
    (Comparison.measured), else measured here. `gradient`: its derivative images are written too
    (info["gradient"] holds its verdict). Written into a temporary sibling folder that then replaces `out_dir`
    whole (atomic.atomic_folder): a crash leaves nothing half-written, and the folder's files
    always come from one run."""
    stock, ours = metrics.as_rgb(stock_img, "stock"), metrics.as_rgb(ours_img, "ours")
    m, flip_map = measured or metrics.compare_images_with_flip_map(stock, ours)
    judged = judged or same_seed_only(stock, ours)
    rep = json_safe({**dict(info), "metrics": m, "verdict": judged.as_dict()})
    with atomic_folder(out_dir, REPORT_MARKER) as tmp:
        _write_all(tmp, stock, ours, rep, flip_map, heatmaps or {}, judged, gradient)
    return rep


# -- traversal-cost heat maps -------------------------------------------------------------------------

HEATMAP_TITLES = {"camera_inner": "inner nodes, camera rays", "camera_triangles": "triangles tested, camera rays",
                  "path_inner": "inner nodes, whole paths", "path_triangles": "triangles tested, whole paths",
                  "path_steps": "wavefront steps, whole paths"}


def heatmap_png(values: np.ndarray) -> tuple[bytes, float]:
    """A per-pixel count as a PNG in the inferno colour map scaled to its 99th percentile, and
    that scale."""
    top = float(np.percentile(values, 99)) or float(values.max()) or 1.0
    return to_png_bytes(_colour_map(values / top, "inferno")), top


def write_comparison(out_dir, c: Comparison) -> dict:
    """The report folder of one comparison (ab.compare.compare); returns report.json's dict."""
    return write_report(out_dir, c.stock, c.ours, c.info(), c.heatmaps, c.verdict, c.measured, c.gradient)
