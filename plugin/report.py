"""A/B report folder (EXR, PNG, ꟻLIP map, report.json, index.html) for stock vs ours, written crash-safely."""
from __future__ import annotations

import html
import io
import json
import math
from numbers import Integral, Real
from pathlib import Path

import numpy as np

from . import metrics
from .atomic import atomic_folder
from .render import write_exr

# diff.png shows |ours - stock| * DIFF_SCALE per channel, tone mapped like the renders:
# a linear difference of 0.1 or more is full white, and the hue tells which channel is off.
DIFF_SCALE = 10.0
_LIST_PREVIEW = 8

_IMAGES = (("stock.png", "stock (reference)"), ("ours.png", "ours"),
           ("flip.png", "ꟻLIP error (magma)"), ("diff.png", f"|ours − stock| × {DIFF_SCALE:g}"))


def to_png_bytes(rgb01: np.ndarray) -> bytes:
    """Encode an (H, W, 3) image with values in [0, 1] (already display-encoded) as 8-bit RGB PNG."""
    from PIL import Image  # Pillow ships with matplotlib

    u8 = np.round(np.clip(rgb01, 0.0, 1.0) * 255.0).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(u8), "RGB").save(buf, format="PNG")
    return buf.getvalue()


def _magma(err: np.ndarray) -> np.ndarray:
    from matplotlib import colormaps

    return colormaps["magma"](np.clip(err, 0.0, 1.0))[..., :3]


def _diff_image(stock: np.ndarray, ours: np.ndarray) -> np.ndarray:
    return metrics.tonemap_srgb(np.abs(ours - stock) * DIFF_SCALE)


def _json_safe(x):
    """Plain JSON types only: numpy scalars/arrays unwrapped, NaN/Inf become null."""
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, set, frozenset)):
        items = sorted(x, key=repr) if isinstance(x, (set, frozenset)) else x
        return [_json_safe(v) for v in items]
    if isinstance(x, np.ndarray):
        return _json_safe(x.tolist())
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


def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    rows = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            rows.extend(_flatten(v, key + "."))
        else:
            rows.append((key, v))
    return rows


def _fmt(v) -> str:
    if isinstance(v, list):
        head = ", ".join(_fmt(x) for x in v[:_LIST_PREVIEW])
        more = f", … ({len(v)} items)" if len(v) > _LIST_PREVIEW else ""
        return f"[{head}{more}]"
    if isinstance(v, float):
        return f"{v:.6g}"
    return "—" if v is None else str(v)


def _table(header: tuple[str, ...], rows) -> str:
    esc = html.escape
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(_fmt(c))}</td>" for c in r) + "</tr>\n" for r in rows)
    return f"<table>\n<tr>{head}</tr>\n{body}</table>\n"


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


TIMED_SIDES = ("stock", "embree_control", "ours")


def _timing_rows(rep: dict) -> list[tuple]:
    sides = [rep.get(s) if isinstance(rep.get(s), dict) else {} for s in TIMED_SIDES]
    keys = list(dict.fromkeys(k for side in sides for k, v in side.items() if _is_number(v)))
    return [(k, *(side.get(k) if _is_number(side.get(k)) else None for side in sides)) for k in keys]


def render_html(rep: dict) -> str:
    """The self-contained index.html for a report dict (as written to report.json)."""
    esc = html.escape
    scene = str(rep.get("scene", "scene"))
    figs = "".join(f'<figure><img src="{f}" alt="{esc(c)}"><figcaption>{esc(c)}</figcaption></figure>\n'
                   for f, c in _IMAGES)
    run = {k: v for k, v in rep.items() if k not in ("metrics", *TIMED_SIDES, "traversal")}
    traversal = rep.get("traversal") if isinstance(rep.get("traversal"), dict) else {}
    parts = [
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n",
        f"<title>{esc(scene)}: stock vs ours</title>\n",
        "<style>body{font-family:sans-serif;margin:1.5em}figure{display:inline-block;margin:0 1em 1em 0}"
        "img{image-rendering:pixelated;max-width:30vw}table{border-collapse:collapse;margin-bottom:1.5em}"
        "td,th{border:1px solid #bbb;padding:2px 8px;text-align:left}</style>\n</head>\n<body>\n",
        f"<h1>{esc(scene)}: stock Mitsuba vs ours</h1>\n",
        (f"<p style=\"border:2px solid #c60;padding:.5em;font-weight:bold\">Compared as path (--as-path): "
         f"{esc(str(rep.get('compared_as_note', '')))}</p>\n" if "--as-path" in str(rep.get("compared_as", "")) else ""),
        f"<div>{figs}</div>\n",
        "<h2>Metrics (ours against stock)</h2>\n", _table(("metric", "value"), rep.get("metrics", {}).items()),
        "<h2>Timings</h2>\n", _table(("key", "stock", "our loop + Embree", "ours"), _timing_rows(rep)),
        "<h2>Traversal statistics</h2>\n", _table(("statistic", "value"), _flatten(traversal)),
        "<h2>Run</h2>\n", _table(("key", "value"), _flatten(run)),
        "</body>\n</html>\n",
    ]
    return "".join(parts)


def _write_bytes(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)


def _write_all(tmp: Path, stock: np.ndarray, ours: np.ndarray, rep: dict, flip_map: np.ndarray) -> None:
    write_exr(tmp / "stock.exr", stock)
    write_exr(tmp / "ours.exr", ours)
    _write_bytes(tmp / "stock.png", to_png_bytes(metrics.tonemap_srgb(stock)))
    _write_bytes(tmp / "ours.png", to_png_bytes(metrics.tonemap_srgb(ours)))
    _write_bytes(tmp / "flip.png", to_png_bytes(_magma(flip_map)))
    _write_bytes(tmp / "diff.png", to_png_bytes(_diff_image(stock, ours)))
    _write_bytes(tmp / "report.json", (json.dumps(rep, indent=2, allow_nan=False) + "\n").encode())
    _write_bytes(tmp / "index.html", render_html(rep).encode())


REPORT_MARKER = "report.json"  # the file that makes a folder a compare report


def write_report(out_dir, stock_img, ours_img, info: dict) -> dict:
    """Write the stock-vs-ours report folder `out_dir` and return the report dict (= report.json).

    Written into a temporary sibling folder that then replaces `out_dir` whole
    (atomic.atomic_folder): a crash leaves nothing half-written, and the folder's files always
    come from one run."""
    stock, ours = metrics.as_rgb(stock_img, "stock"), metrics.as_rgb(ours_img, "ours")
    m, flip_map = metrics.compare_images_with_flip_map(stock, ours)
    rep = _json_safe({**dict(info), "metrics": m})
    with atomic_folder(out_dir, REPORT_MARKER) as tmp:
        _write_all(tmp, stock, ours, rep, flip_map)
    return rep
