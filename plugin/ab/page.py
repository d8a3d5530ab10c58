"""index.html of a compare report: the verdict, an A/B viewer (flip, split, exposure, pixel values, loupe), error
maps with colour bars, plain metrics and timings. Self-contained: no network, no framework."""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np

from layerbvh_mitsuba.ab.metrics import STOKES_PANELS

# Images up to this many pixels travel inside the page as half floats (hover values, exposure);
# larger ones are shown from their PNGs (flip and split only), so the page stays a few MB.
EMBED_MAX_PIXELS = 1 << 20

# Each metric: a plain name, its unit, and what it means.
METRICS = {
    "frac_pixels_over_1e-3": ("pixels differing by more than 1e-3", "share", "pixels where some channel of ours "
                              "differs from stock by more than 1e-3 (linear radiance)"),
    "max_abs": ("largest difference", "radiance", "the largest |ours − stock| over every pixel and channel"),
    "mean_abs": ("mean difference", "radiance", "mean |ours − stock| over pixels and channels"),
    "rmse": ("RMSE", "radiance", "root of the mean squared difference"),
    "rel_mse": ("relative MSE", "", "mean of (ours − stock)² / (stock² + 0.01): error relative to brightness"),
    "flip_mean": ("mean ꟻLIP", "0–1",
                  "perceptual difference of the tone-mapped images (NVIDIA ꟻLIP, LDR); 0 = identical"),
    "delta_e2000_mean": ("mean ΔE2000", "ΔE",
                         "mean CIEDE2000 colour difference of the tone-mapped images; below 1 is invisible"),
    "delta_e2000_p95": ("95th-percentile ΔE2000", "ΔE", "95% of pixels differ by less than this colour difference"),
    "mean_ref": ("mean stock pixel", "radiance", "the mean pixel value of stock's image, for scale"),
    "pixels": ("pixels", "", "width × height"),
}

# Timing rows: key, plain name, what it is.
TIMINGS = (
    ("render_s", "render", "the timed render, without kernel compilation and auto's calibration"),
    ("compile_s", "kernel compilation", "Dr.Jit compiling kernels it had not cached (first runs only)"),
    ("calibration_s", "auto calibration", "auto timing per_ray against layer_sorted (first runs on a scene only)"),
    ("build_s", "BVH build", "binned-SAH build and Layer BVH layout, once per scene"),
    ("kernel_load_s", "builder kernel load", "numba compiling or loading the builder's kernels, once per process"),
    ("trace_s", "traversal (wavefront loop)", "time in our traversal; in the megakernel it is inside the one kernel"),
)
SIDES = (("stock", "stock path (Embree)"), ("embree_control", "our loop + Embree"), ("ours", "ours (layerbvh)"))


def split_share(seconds: float) -> str:
    """One share of the time split (compare.Comparison.split), for people: a difference of two timings,
    so one below zero says "no measurable cost", not a time."""
    return f"{seconds:.2f} s" if seconds >= 0 else f"~0 s ({seconds:.2f} s: within timing noise)"


def _g(x, unit: str = "") -> str:
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if unit == "share":
        return f"{100 * x:.3g}%"
    text = f"{x:.3g}"
    return f"{text} s" if unit == "s" else text


def _half_b64(img: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(img[:, :, :3], np.float16).tobytes()).decode()


def colour_bar(cmap: str, lo: str, hi: str, label: str) -> str:
    """A colour bar as a CSS gradient of the matplotlib colour map, with its scale written on it."""
    from matplotlib import colormaps  # local: matplotlib loads only when a plot is drawn
    stops = ", ".join(f"rgb({', '.join(str(int(255 * c)) for c in colormaps[cmap](i / 15)[:3])}) {100 * i / 15:.0f}%"
                      for i in range(16))
    return (f'<div class="bar"><span>{html.escape(lo)}</span><div class="grad" style="background:linear-gradient('
            f'to right, {stops})"></div><span>{html.escape(hi)}</span>'
            f'<div class="barlabel">{html.escape(label)}</div></div>')


def legend(text: str) -> str:
    """A caption in the colour bars' place, for a map without a scale."""
    return f'<div class="bar"><div class="barlabel">{html.escape(text)}</div></div>'


STYLE = """
body{font-family:system-ui,sans-serif;margin:1.2em 2em;color:#222;max-width:1400px}
h1{font-size:1.4em;margin-bottom:.2em} h2{font-size:1.1em;margin-top:1.6em;border-bottom:1px solid #ddd}
.verdict{font-size:1.2em;padding:.6em 1em;border-radius:6px;margin:.8em 0}
.pass{background:#e3f6e3;border:2px solid #2a2} .fail{background:#fbe3e3;border:2px solid #c22}
.warn{border:2px solid #c60;padding:.5em;font-weight:bold;border-radius:6px}
.small{color:#666;font-size:.85em}
.viewer{display:flex;gap:1.5em;align-items:flex-start;flex-wrap:wrap}
#view,#viewimgs{image-rendering:pixelated;image-rendering:crisp-edges;cursor:crosshair;border:1px solid #999}
#loupe{image-rendering:pixelated;border:1px solid #999;width:176px;height:176px}
.controls button{margin:0 .3em .3em 0;padding:.3em .8em} .controls button.on{background:#246;color:#fff}
.readout{font-family:ui-monospace,monospace;font-size:.85em;white-space:pre;min-height:4.5em}
table{border-collapse:collapse;margin:.4em 0 1em}
td,th{border:1px solid #ccc;padding:3px 9px;text-align:left;vertical-align:top}
td.num{text-align:right;font-variant-numeric:tabular-nums} th{background:#f3f3f3}
.maps{display:flex;gap:2em;flex-wrap:wrap} .maps figure{margin:0}
.maps img{image-rendering:pixelated;border:1px solid #999}
.bar{display:flex;align-items:center;gap:.4em;font-size:.8em;flex-wrap:wrap;max-width:420px}
.grad{height:12px;flex:1;min-width:160px;border:1px solid #999} .barlabel{width:100%;color:#555}
"""

SCRIPT = r"""
(function(){
const D = JSON.parse(document.getElementById('data').textContent);
const W = D.width, H = D.height, scale = D.scale;
let mode = 'stock', ev = 0, split = 0.5, last = null;
const view = document.getElementById('view');
const status = document.getElementById('showing');
function half(b64){  // IEEE half floats -> Float32Array
  const bin = atob(b64), n = bin.length / 2, out = new Float32Array(n);
  for (let i = 0; i < n; i++){
    const h = bin.charCodeAt(2*i) | (bin.charCodeAt(2*i+1) << 8);
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 31, f = h & 1023;
    out[i] = e === 0 ? s * Math.pow(2, -14) * f / 1024
           : e === 31 ? (f ? NaN : s * Infinity) : s * Math.pow(2, e - 15) * (1 + f / 1024);
  }
  return out;
}
const img = D.stock ? {stock: half(D.stock), ours: half(D.ours)} : null;
function srgb(x){
  x = Math.min(Math.max(x, 0), 1);
  return x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1/2.4) - 0.055;
}
const modeButtons = document.querySelectorAll('.controls button[data-mode]');
function draw(){
  status.textContent = mode === 'split' ? 'split: stock | ours' : mode;
  view.dataset.showing = mode;
  modeButtons.forEach(b => b.classList.toggle('on', b.dataset.mode === mode));
  if (!img){  // large image: PNGs, flip and split by clipping
    const s = document.getElementById('img_stock'), o = document.getElementById('img_ours');
    o.style.clipPath = mode === 'ours' ? 'none' : mode === 'stock' ? 'inset(0 0 0 100%)' : `inset(0 0 0 ${100*split}%)`;
    s.style.visibility = mode === 'ours' ? 'hidden' : 'visible';
    return;
  }
  const ctx = view.getContext('2d'), out = ctx.createImageData(W, H), k = Math.pow(2, ev), cut = Math.round(split * W);
  for (let y = 0; y < H; y++) for (let x = 0; x < W; x++){
    const which = mode === 'split' ? (x < cut ? 'stock' : 'ours') : mode, src = img[which];
    const i = 3 * (y * W + x), o = 4 * (y * W + x);
    for (let c = 0; c < 3; c++) out.data[o + c] = Math.round(255 * srgb(src[i + c] * k));
    out.data[o + 3] = 255;
  }
  ctx.putImageData(out, 0, 0);
  if (mode === 'split'){ ctx.fillStyle = '#ff0'; ctx.fillRect(cut, 0, 1, H); }
  if (last) loupe(last.x, last.y);
}
function setMode(m){ mode = m; draw(); }
window.layerbvhSetMode = setMode;
function flip(){ setMode(mode === 'stock' ? 'ours' : 'stock'); }
modeButtons.forEach(b => b.addEventListener('click', () => setMode(b.dataset.mode)));
const target = img ? view : document.getElementById('viewimgs');
target.addEventListener('click', flip);
document.addEventListener('keydown', e => { if (e.key === 'f' || e.key === ' '){ e.preventDefault(); flip(); } });
const sl = document.getElementById('split');
if (sl) sl.addEventListener('input', () => { split = sl.value / 100; if (mode !== 'split') mode = 'split'; draw(); });
const ex = document.getElementById('ev');
if (ex) ex.addEventListener('input', () => {
  ev = +ex.value;
  document.getElementById('evval').textContent = (ev >= 0 ? '+' : '') + ev.toFixed(1) + ' EV';
  draw();
});
function fmt(v){ return v.toPrecision(4).padStart(10); }
function loupe(x, y){
  const lc = document.getElementById('loupe'); if (!lc || !img) return;
  const r = 5, c = lc.getContext('2d'), n = 2 * r + 1;
  const tmp = document.createElement('canvas'); tmp.width = n; tmp.height = n;
  tmp.getContext('2d').drawImage(view, x - r, y - r, n, n, 0, 0, n, n);
  c.imageSmoothingEnabled = false; c.clearRect(0, 0, lc.width, lc.height); c.drawImage(tmp, 0, 0, lc.width, lc.height);
  c.strokeStyle = '#f0f'; c.strokeRect(r * lc.width / n, r * lc.height / n, lc.width / n, lc.height / n);
}
if (img) view.addEventListener('mousemove', e => {
  const b = view.getBoundingClientRect();
  const x = Math.floor((e.clientX - b.left) / b.width * W), y = Math.floor((e.clientY - b.top) / b.height * H);
  if (x < 0 || y < 0 || x >= W || y >= H) return;
  last = {x, y}; const i = 3 * (y * W + x), s = img.stock, o = img.ours;
  document.getElementById('readout').textContent =
    `pixel (${x}, ${y})      R          G          B\n`
    + `stock   ${fmt(s[i])} ${fmt(s[i+1])} ${fmt(s[i+2])}\n`
    + `ours    ${fmt(o[i])} ${fmt(o[i+1])} ${fmt(o[i+2])}\n`
    + `|diff|  ${fmt(Math.abs(o[i]-s[i]))} ${fmt(Math.abs(o[i+1]-s[i+1]))} ${fmt(Math.abs(o[i+2]-s[i+2]))}`;
  loupe(x, y);
});
draw();
})();
"""


def _rows(items) -> str:
    return "".join("<tr>" + "".join(c for c in r) + "</tr>\n" for r in items)


def _td(x, unit: str = "", cls: str = "num") -> str:
    return f'<td class="{cls}">{html.escape(_g(x, unit))}</td>'


def _metrics_table(m: dict) -> str:
    rows = []
    for key, (name, unit, meaning) in METRICS.items():
        if key in m:
            rows.append((f"<td>{html.escape(name)}</td>", _td(m[key], unit),
                         f'<td class="small">{html.escape(meaning)}</td>'))
    return "<table><tr><th>metric</th><th>value</th><th>meaning</th></tr>\n" + _rows(rows) + "</table>\n"


def _timing_table(rep: dict) -> str:
    present = [(k, label) for k, label in SIDES if isinstance(rep.get(k), dict)]
    head = "".join(f"<th>{html.escape(label)}</th>" for _, label in present)
    rows = []
    for key, name, meaning in TIMINGS:
        vals = [rep[k].get(key) for k, _ in present]
        if all(v is None for v in vals):
            continue
        ratio = ""
        if key == "render_s" and rep.get("stock", {}).get("render_s"):
            ratio = f"{rep['ours']['render_s'] / rep['stock']['render_s']:.2f}×"
        rows.append((f'<td title="{html.escape(meaning)}">{html.escape(name)}</td>',
                     *(_td(v, "s") for v in vals), f'<td class="num">{ratio}</td>',
                     f'<td class="small">{html.escape(meaning)}</td>'))
    split = rep.get("split")
    note = ""
    if isinstance(split, dict) and split.get("traversal_s") is not None:
        loop, traversal = (html.escape(split_share(split[k])) for k in ("loop_s", "traversal_s"))
        note = (f'<p>Of our render time over stock\'s, <b>{loop}</b> is the loop (our loop with '
                f'Embree\'s queries against stock) and <b>{traversal}</b> is the traversal (ours '
                f'against our loop with Embree\'s queries).</p>')
    return (f"<table><tr><th>time</th>{head}<th>ours ÷ stock</th><th>meaning</th></tr>\n" + _rows(rows)
            + "</table>\n" + note)


def _features_table(features: dict) -> str:
    def row(f, state):
        return f"<td>{html.escape(f['feature'])}</td>", state, f'<td class="small">{html.escape(f["reason"])}</td>'
    rows = [row(f, "<td>on</td>") for f in features.get("active_detail", [])]
    rows += [row(f, "<td>left out</td>") for f in features.get("left_out", [])]
    return "<table><tr><th>feature</th><th>state</th><th>why</th></tr>\n" + _rows(rows) + "</table>\n" if rows else ""


STATS = (("rays", "rays traced", "all queries of the counted pass"),
         ("inner_nodes", "inner nodes visited", "node tests (each tests both children)"),
         ("triangles", "triangles tested", ""),
         ("wavefront_steps", "wavefront steps", "sorted/unsorted steps (layer modes)"),
         ("queries", "queries", "closest-hit and any-hit calls"), ("loop", "bounce loop", "megakernel or wavefront"),
         ("peak_work_bytes", "peak work memory (bytes)", "entry stacks, ray state, outputs of one batch"))


def _stats_table(tr: dict, stats_pass: dict | None) -> str:
    rows = []
    for key, name, meaning in STATS:
        if key in tr:
            rows.append((f"<td>{html.escape(name)}</td>", _td(tr[key]) if not isinstance(tr[key], str)
                         else f"<td>{html.escape(tr[key])}</td>", f'<td class="small">{html.escape(meaning)}</td>'))
    rays = tr.get("rays") or 0
    for key, name in (("inner_nodes", "inner nodes per ray"), ("triangles", "triangles per ray")):
        if rays and key in tr:
            rows.append((f"<td>{name}</td>", _td(tr[key] / rays), "<td></td>"))
    note = (f'<p class="small">From a separate counted pass at {stats_pass["spp"]} spp (work counters slow a render, '
            f'so the timed renders run without them).</p>' if stats_pass else "")
    return "<table><tr><th>statistic</th><th>value</th><th>meaning</th></tr>\n" + _rows(rows) + "</table>\n" + note


def _verdict_html(v: dict) -> str:
    """The verdict (verdict.Verdict.as_dict): its label with what it rules out (the MDE), what was
    tested, how long."""
    esc = html.escape
    passed = bool(v.get("passed"))
    label = str(v.get("label", ""))
    fam = v.get("hypotheses") or {}
    headline = {"same paths": "matches stock: same paths",
                "agrees within Monte Carlo noise": "matches stock within Monte Carlo noise"}.get(
        label, f"differs from stock: {label}")
    if passed and fam and not fam.get("rejected"):
        headline += f": {fam.get('mde_text', '')}"
    step1 = f"Step 1, same seed: {_g(v.get('values', {}).get('frac_within'), 'share')} of pixels within tolerance"
    z = v.get("statistical")
    parts = [step1 + (", so same-seed paths diverged." if not v.get("same_seed", {}).get("passed") else ".")]
    tests = fam.get("tests", {})
    if tests:
        kinds = sorted({k for lv in tests.values() for k in lv.get("kinds", [])})
        parts.append(f"Tests of equal means ({esc(', '.join(kinds))}): "
                     + "; ".join(f"{lv} level {t['count']} tests at alpha {_g(t['alpha_each'])} each"
                                 for lv, t in tests.items() if t.get("count"))
                     + f"; equivalence margin {_g(fam.get('margin'))} of |stock|.")
    if z:
        w, h = z.get("resolution", ["?", "?"])
        parts.append(f"Independent seeds: stock and ours rendered once each at {z.get('spp')} spp on a {w}×{h} "
                     f"film ({esc(str(z.get('test', '')))}); took {_g(z.get('seconds'))} s.")
    if fam:
        parts.append(f"Result: {esc(str(fam.get('summary', '')))}.")
    elif label != "same paths":
        parts.append("No test of equal means was run.")
    return (f'<div class="verdict {"pass" if passed else "fail"}" id="verdict" data-passed="{str(passed).lower()}" '
            f'data-label="{esc(label)}"><b>{esc(headline)}</b><div class="small">{" ".join(parts)}</div>'
            f'<div class="small">criterion: {esc(str(v.get("criterion", "")))}</div></div>')


def _gradient_html(g: dict | None, figures: list, width: int) -> str:
    """The gradient comparison (gradient.GradientComparison.as_dict): its verdict, the backward
    gradients side by side, and the forward derivative images [(title, png, bar)]."""
    if not g:
        return ""
    esc = html.escape
    passed = bool(g.get("passed"))
    z = g.get("statistical")
    how = "same seed: every derivative within the image criterion" if g.get("label") == "same paths" else (
        "same-seed derivatives diverged" + ("" if not z else
                                            f"; independent seeds, {z.get('renders')} renders a side at {z.get('spp')} "
                                            f"spp on a {z['resolution'][0]}×{z['resolution'][1]} film: "
                                            f"{esc(str(z.get('test', '')))}, {_g(z.get('seconds'))} s"))
    b = g.get("backward", {})
    rows = _rows((f"<td>{i}</td>", _td(s), _td(o)) for i, (s, o) in enumerate(zip(b.get("stock", []),
                                                                                   b.get("ours", []))))
    figs = "".join(f'<figure><img src="{esc(png)}" alt="{esc(t)}" width="{width}"><figcaption><b>{esc(t)}</b>{bar}'
                   f'</figcaption></figure>' for t, png, bar in figures)
    if not g.get("forward"):
        figs = '<p class="small">The integrator has no forward mode (prbvolpath): the backward gradient only.</p>'
    return (f"<h2>Derivatives with respect to {esc(str(g.get('key')))}</h2>\n"
            f'<div class="verdict {"pass" if passed else "fail"}" id="gradient-verdict" '
            f'data-passed="{str(passed).lower()}"><b>{esc(str(g.get("label")))}</b><div class="small">{how}</div></div>'
            f'<div class="maps">{figs}</div><p class="small">Backward: the gradient of the image\'s sum with respect '
            f'to each of the parameter\'s {b.get("components")} components (the first 64 shown).</p>'
            f"<table><tr><th>component</th><th>stock</th><th>ours</th></tr>{rows}</table>\n")


def _referee_html(r: dict | None) -> str:
    """The unit-scale referee of a scene far from unit size (referee.Referee.as_dict), or why not."""
    if not r:
        return ""
    if "refused" in r:
        return f'<p class="warn" id="referee">{html.escape(str(r["refused"]))}</p>\n'
    return (f'<p class="warn" id="referee" data-matches="{html.escape(str(r.get("matches")))}">This scene is far from '
            f'unit size (extent {r.get("extent", 0):.3g}), where float32 and Mitsuba\'s epsilons lose precision: '
            f'{html.escape(str(r.get("line", "")))}.</p>\n')


def render_page(rep: dict, stock: np.ndarray, ours: np.ndarray, maps: dict, heatmaps: list,
                gradient: list | None = None) -> str:
    """The page for a report dict (as in report.json), its two images (linear RGB), the error
    maps {"diff": (png name, colour bar html), "flip": ...}, heat maps [(title, png, bar)] and the
    derivative images of a gradient comparison [(title, png, bar)]."""
    esc = html.escape
    h, w = stock.shape[:2]
    title = Path(str(rep.get("scene", "scene"))).name
    v = rep.get("verdict", {})
    verdict = _verdict_html(v)
    as_path = ""
    if "--as-path" in str(rep.get("compared_as", "")):
        as_path = f'<p class="warn">Compared as path (--as-path): {esc(str(rep.get("compared_as_note", "")))}</p>'
    elif str(rep.get("compared_as", "")).startswith("stokes("):
        as_path = ('<p class="warn">A stokes render: each image below is its five RGB images side by side '
                   f'({", ".join(STOKES_PANELS)}; S1-S3 are signed), and every one of them is judged.</p>')
    scale = max(1, min(16, 640 // max(w, h)))
    embed = w * h <= EMBED_MAX_PIXELS
    data = {"width": w, "height": h, "scale": scale}
    if embed:
        data.update(stock=_half_b64(stock), ours=_half_b64(ours))
    if embed:
        canvas = (f'<canvas id="view" width="{w}" height="{h}" style="width:{w * scale}px;height:{h * scale}px" '
                  f'data-showing="stock"></canvas>')
        side = ('<div><canvas id="loupe" width="176" height="176"></canvas><div class="small">loupe: 11×11 pixels '
                'around the cursor</div><div class="readout" id="readout">hover the image to read stock and ours</div>'
                '</div>')
        exposure = ('<label>exposure <input type="range" id="ev" min="-6" max="6" step="0.5" value="0"> '
                    '<span id="evval">+0.0 EV</span></label>')
    else:
        canvas = (f'<div id="viewimgs" style="position:relative;width:{w * scale}px;height:{h * scale}px" '
                  f'data-showing="stock"><img id="img_stock" src="stock.png" alt="stock" style="position:absolute;'
                  f'width:100%"><img id="img_ours" src="ours.png" alt="ours" style="position:absolute;width:100%">'
                  f'</div>')
        side = f'<p class="small">{w}×{h} is too large to embed for pixel values and exposure; flip and split work.</p>'
        exposure = ""
    controls = ('<div class="controls"><button data-mode="stock">stock</button><button data-mode="ours">ours</button>'
                '<button data-mode="split">split</button> <label>split <input type="range" id="split" min="0" '
                f'max="100" value="50"></label> {exposure}<div class="small">click the image or press F to flip; '
                'showing: <b id="showing">stock</b></div></div>')
    map_figs = "".join(f'<figure><img src="{esc(png)}" alt="{esc(name)}" width="{w * max(1, scale // 2)}"><figcaption>'
                       f'{bar}</figcaption></figure>' for name, (png, bar) in maps.items())
    heat = ""
    if heatmaps:
        heat = ("<h2>Traversal cost per pixel</h2><p class=\"small\">What our traversal did for each pixel's samples "
                "(counted pass): stock Mitsuba has no such view. Brighter = more work.</p><div class=\"maps\">"
                + "".join(f'<figure><img src="{esc(png)}" alt="{esc(t)}" width="{w * max(1, scale // 2)}"><figcaption>'
                          f'<b>{esc(t)}</b>{bar}</figcaption></figure>' for t, png, bar in heatmaps) + "</div>")
    ours = rep.get("ours", {})
    run = (f"{rep.get('resolution', [w, h])[0]}×{rep.get('resolution', [w, h])[1]}, {rep.get('spp')} spp, seed "
           f"{rep.get('seed')}, variant {rep.get('variant')}, traversal {ours.get('traversal')} "
           f"({ours.get('branching', 2)} children per node, treelet height {ours.get('treelet_height')}, "
           f"{ours.get('loop', '')} loop), path settings "
           f"{rep.get('integrator')}")
    links = " · ".join(f'<a href="{f}">{f}</a>' for f in ("stock.exr", "ours.exr", "report.json", "stock.png",
                                                           "ours.png", "diff.png", "flip.png"))
    auto = rep.get("auto_choices") or {}
    auto_html = ""
    if auto:
        auto_html = ("<h2>auto's decisions</h2><table><tr><th>kind of batch</th><th>mode</th><th>why</th></tr>"
                     + _rows((f"<td>{esc(k)}</td>", f"<td>{esc(str(c.get('mode')))}</td>",
                              f'<td class="small">{esc(str(c.get("reason", "")))}</td>') for k, c in auto.items())
                     + "</table>")
    return "".join([
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n',
        f"<title>{esc(title)}: stock vs layerbvh</title>\n<style>{STYLE}</style>\n</head>\n<body>\n",
        f"<h1>{esc(title)}: stock Mitsuba vs layerbvh</h1>\n<div class=\"small\">{esc(run)}</div>\n",
        verdict, _referee_html(rep.get("referee")), as_path,
        "<h2>Stock and ours</h2>\n", controls, f'<div class="viewer">{canvas}{side}</div>\n',
        "<h2>Where they differ</h2>\n", f'<div class="maps">{map_figs}</div>\n',
        _gradient_html(rep.get("gradient"), gradient or [], w * max(1, scale // 2)),
        "<h2>Metrics (ours against stock)</h2>\n", _metrics_table(rep.get("metrics", {})),
        "<h2>Timings</h2>\n", _timing_table(rep),
        heat,
        "<h2>Traversal statistics</h2>\n", _stats_table(rep.get("traversal", {}), rep.get("statistics_pass")),
        auto_html,
        "<h2>What the integrator ran for this scene</h2>\n", _features_table(rep.get("features", {})),
        f"<h2>Files</h2>\n<p>{links}</p>\n",
        f'<script type="application/json" id="data">{json.dumps(data)}</script>\n<script>{SCRIPT}</script>\n',
        "</body>\n</html>\n",
    ])
