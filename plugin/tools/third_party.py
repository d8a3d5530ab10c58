"""A/B check on third-party scenes: stock against ours in the scene's own integrator (path, direct,
volpath, volpathmis, aov/moment around them; any other as path), same seed, each scene a point of a
`layerbvh sweep` (its own process).

For every scene found under --root (default ../shared/assets relative to the repository root) it
loads the scene with the project's loader (film resized to --res) and runs the one A/B comparison
(`ab.compare.compare`: stock `path` and `layerbvh` with the scene's own sensor, the same spp and
seed, then the two-step verdict and the image metrics). Scenes whose integrator ours does not
mirror are compared with `path` using the inner integrator's settings when they can be read, else
path's defaults, and the table says so. A SCENE@INTEGRATOR entry renders the scene with that
integrator instead (ptracer, prb, prb_basic, prbvolpath: no scene here asks for them), carrying
over the scene's own max_depth, rr_depth and hide_emitters. Scenes with participating media (volpath, volpathmis) run
with --media-traversal (default auto: its rule runs them per_ray in one megakernel, since the
wavefront loop is 8-126x slower there, PERFORMANCE.md entry 30); the notes say so.

    .venv/bin/python scripts/third_party.py [--root DIR] [--res W H] [--spp N] [--seed S]
        [--traversal per_ray|layer_sorted|layer_unsorted|auto] [--media-traversal MODE]
        [--check-rays N] [--timeout SECONDS]
        [--scenes GLOB ...] [--md OUT.md] [--json OUT.json] [--readme]
        [--out SWEEP_DIR] [--workers N | --scheduler ADDRESS] [--rerun]

The scenes run as points of `layerbvh sweep` (sweep.py: Dask, a fresh process per scene, resumable:
a scene whose content, settings and code are unchanged is not run again unless --rerun).

Result column: the two-step verdict (ab/verdict.py): `same paths` (same seed: >= 99.9% of
pixels within 1e-3 x max(1, |stock|) in every channel and mean |diff| <= 1e-4 x mean pixel value), else an
independent-seed per-pixel Welch t-test on a downsampled film: `agrees within Monte Carlo noise`
or `differs beyond noise` (with the numbers); `refused: ...` (our backend refuses a plugin),
`fails in stock Mitsuba: ...`, or `error in layerbvh: ...` / `killed: time limit ...` /
`crashed ...` when something else goes wrong.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import shlex
import sys
import time
from pathlib import Path

import numpy as np

import layerbvh
from layerbvh import MISS, meshes
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab import embree
from layerbvh_mitsuba.ab.compare import STOCK, CompareSettings, ComparisonFailed, compare
from layerbvh_mitsuba.ab.metrics import SAME_PATHS
from layerbvh_mitsuba.ab.render import UserError, load_scene, use_variant
from layerbvh_mitsuba.ab.scene_integrator import path_settings
from layerbvh_mitsuba.repo import ROOT
from layerbvh_mitsuba.runtime.scene_geometry import UnsupportedShapeError
from layerbvh_mitsuba.runtime.features import scene_media
from layerbvh_mitsuba.runtime.registry import handles_media
from layerbvh_mitsuba.runtime.settings import Traversal
from layerbvh_mitsuba.tools.sweep.runner import Limits, run_sweep
from layerbvh_mitsuba.tools.sweep.store import make_points

# The scenes of the task (PROVENANCE.md of shared/assets), as globs relative to --root.
DEFAULT_SCENES = (
    "bitterli/cornell-box/scene.xml",
    "bitterli/veach-mis/scene.xml",
    "bitterli/staircase2/scene.xml",
    "mitsuba/matpreview/matpreview.xml",
    "mitsuba/cbox/cbox.xml",
    "mitsuba/cbox/cbox-rgb.xml",
    "mitsuba/cbox/cbox-spectral.xml",
    "mitsuba/tests/bsdf_spheres/*.xml",
    "mitsuba/tests/infinite_mirrors/scene_path.xml",
    "mitsuba/tests/instancing/test_instancing_path.xml",
    "mitsuba/tests/floating_sphere/*.xml",
    "mitsuba/tests/orthographic_sensor/*.xml",
    "mitsuba/tests/participating_media/*.xml",
    # The integrators no scene here asks for, on scenes that suit them (SCENE@INTEGRATOR: rendered
    # with that integrator at the scene's own depths): light tracing and the differentiable ones.
    "bitterli/cornell-box/scene.xml@ptracer",
    "bitterli/veach-mis/scene.xml@ptracer",
    "mitsuba/matpreview/matpreview.xml@ptracer",
    "bitterli/cornell-box/scene.xml@prb",
    "bitterli/veach-mis/scene.xml@prb",
    "mitsuba/matpreview/matpreview.xml@prb_basic",
    "mitsuba/tests/participating_media/test_homo_area_light_volpath.xml@prbvolpath",
    "mitsuba/tests/participating_media/test_homo_obj_inside_medium_volpath.xml@prbvolpath",
)
# The settings of the scene's own integrator that a SCENE@INTEGRATOR row carries over, by integrator.
CARRIED = {"direct": ("hide_emitters",), "depth": ()}
DEPTHS = ("max_depth", "rr_depth", "hide_emitters")

# ------------------------------------------------------------------------------------------------
# One scene, in its own process (a sweep point: sweep.point.run_third_party).
# ------------------------------------------------------------------------------------------------

def _xml_text(path: Path, seen=None) -> str:
    """The scene file's text plus that of the files it <include>s (for notes only)."""
    seen = set() if seen is None else seen
    path = path.resolve()
    if path in seen or not path.is_file():
        return ""
    seen.add(path)
    text = path.read_text(errors="replace")
    for inc in re.findall(r'<include\s+filename\s*=\s*["\']([^"\']+)["\']', text):
        text += "\n" + _xml_text(path.parent / inc, seen)
    return text


def _shape_counts(scene) -> tuple[int, str]:
    tris, placed, other = 0, 0, {}
    for s in scene.shapes():
        if s.is_mesh():
            tris += int(s.face_count())
        elif s.class_name() == "Instance":
            other["instance"] = other.get("instance", 0) + 1
            placed += int(s.effective_primitive_count())
        else:
            name = s.class_name().lower()
            other[name] = other.get(name, 0) + 1
    shown = ", ".join(f"{n} {k}" for k, n in sorted(other.items())) or "-"
    return tris, shown + (f" ({placed:,} primitives placed)" if placed else "")


def one_line(e: BaseException) -> str:
    """The last line of the innermost exception (Dr.Jit wraps the real error as "see above")."""
    chain = [e]
    while (c := chain[-1].__cause__ or chain[-1].__context__) is not None and c not in chain:
        chain.append(c)
    inner = chain[-1]
    lines = [ln.strip() for ln in str(inner).strip().splitlines() if ln.strip()]
    msg = lines[-1] if lines else ""
    if inner is not e and not isinstance(inner, ValueError):
        msg = f"{type(inner).__name__}: {msg}"
    return (msg or type(inner).__name__)[:300]


def ray_check(tracer, n: int, seed: int) -> dict | None:
    """Closest hits of `n` random rays through the scene's triangles, ours against Embree: how
    many rays get another triangle, and how many of those are ties (`embree.disagreements`):
    shared edges and (near-)coplanar overlapping triangles, where either answer is right (we take
    the one whose float t is smaller, then the lower primitive id)."""
    g = tracer.geometry
    if n <= 0 or g.triangle_count == 0:
        return None
    # An instanced scene is compared on its placed triangles, flattened into world space for
    # Embree; our hit (instance, prim) is that placement's first flat face + prim.
    v, f, first = g.world_triangles()
    o, d = meshes.incoherent_rays(v, n, seed)
    _, p_e = embree.intersect(embree.scene_from_mesh(v, f), o, d)
    h = tracer.bvh.trace(o, d, mode="per_ray", stats=False)
    prim = h.prim
    if h.instance is not None:
        hit = h.prim != MISS
        prim = np.where(hit, first[np.where(hit, h.instance, 0)] + h.prim, MISS).astype(np.uint32)
    dis = embree.disagreements(v, f, o, d, prim, p_e)
    tie = dis["tie_idx"]
    shape_of = _flat_shapes(g)
    return {"rays": n, "other_prim": dis["ties"] + dis["other"] + dis["hit_miss"], "ties": dis["ties"],
            "tie_other_shape": int((shape_of[p_e[tie]] != shape_of[prim[tie]]).sum())}


def _flat_shapes(g):
    """Per flat face of SceneGeometry.world_triangles: (placement, shape) as one integer."""
    if not g.instanced:
        return g.tri_shape.astype(np.int64)
    return np.concatenate([k * (1 << 32) + g.groups[p.group].tri_shape.astype(np.int64)
                           for k, p in enumerate(g.placements)])


def run_worker(args) -> dict:
    """The record of one scene: `compare` (same seed, then the two-step verdict) with every
    failure named by the side and stage where it happened, the ray check, notes."""
    rec = {"notes": []}
    scene_path = Path(args.worker)
    text = _xml_text(scene_path)
    mi = use_variant(args.variant)
    if "spectral" not in args.variant and (re.search(r'<spectrum[^>]*value\s*=\s*"[^"]*\d\s*:', text)
                                           or "spectral" in scene_path.name):
        rec["notes"].append(f"spectral data rendered in RGB mode ({args.variant})")

    # Stock Mitsuba loads it first: a scene failing there is not ours to judge.
    try:
        t0 = time.perf_counter()
        scene = load_scene(mi, str(scene_path), tuple(args.res))
        rec["load_s"] = time.perf_counter() - t0
    except UserError as e:
        rec["result"] = f"fails in stock Mitsuba: {str(e).split(': ', 1)[-1] if ': ' in str(e) else e}"
        return rec
    except Exception as e:
        rec["result"] = f"fails in stock Mitsuba: {one_line(e)}"
        return rec
    rec["triangles"], rec["other_shapes"] = _shape_counts(scene)
    # The table compares every scene as path and says so where its integrator is another one.
    path = path_settings(mi, scene, as_path=True, scene_path=scene_path)
    integrator = None
    if getattr(args, "integrator", None):  # SCENE@INTEGRATOR: that integrator at the scene's own depths
        carried = {k: v for k, v in path.props.items() if k in CARRIED.get(args.integrator, DEPTHS)}
        integrator, asked = {"type": args.integrator, **carried}, path.compared_as
        try:
            path = path_settings(mi, scene, integrator=mi.load_dict(integrator))
        except (UserError, RuntimeError) as e:
            rec["result"] = f"refused: {one_line(e)}"
            return rec
        shown = ", ".join(f"{k}={v}" for k, v in carried.items()) or "no settings"
        rec["notes"].append(f"rendered with {args.integrator} instead of the scene's {asked} ({shown} carried over)")
    overrides, note = {}, path.note
    if "hide_emitters" in text and "hide_emitters" not in path.props:
        m = re.search(r'name\s*=\s*"hide_emitters"\s+value\s*=\s*"(\w+)"', text)
        if m:
            overrides["hide_emitters"] = m.group(1).lower() == "true"
            note = (note + "; " if note else "") + f"hide_emitters={m.group(1)} read from the XML"
    if note:
        rec["notes"].append(note)
    rec["integrator"] = {**path.props, **overrides}
    rec["compared_as"] = path.compared_as
    traversal = args.traversal
    media = handles_media(path.estimator) and bool(scene_media(scene))
    if media:
        traversal = args.media_traversal
    rec["traversal"] = traversal
    sensor = scene.sensors()[0]
    rec["sensor"] = sensor.class_name()
    rec["resolution"] = [int(x) for x in sensor.film().crop_size()]

    settings = CompareSettings(scene=scene_path, spp=args.spp, res=tuple(args.res), seed=args.seed,
                               traversal=Traversal.parse(traversal), as_path=True, path_overrides=overrides,
                               integrator=integrator)
    try:
        c = compare(mi, settings, scene=scene)
    except ComparisonFailed as e:
        if e.side == STOCK:
            rec["result"] = f"fails in stock Mitsuba: {one_line(e.error)}"
        elif isinstance(e.error, UnsupportedShapeError):
            rec["result"] = f"refused: {one_line(e.error)}"
        else:
            where = "render" if e.stage == "render" else "setup/BVH build"
            rec["result"] = f"error in layerbvh ({where}): {one_line(e.error)}"
        return rec
    rec["compared_as"] = c.path.compared_as  # (what the comparison rendered)
    rec["stock_s"], rec["ours_s"] = c.stock_time.render_s, c.ours_time.render_s
    if media:
        ran = ", ".join(sorted({m.split(":")[-1] for m in c.stats.modes_used})) or "per_ray"
        rec["notes"].append(f"media: traversal {traversal} (--media-traversal), ran {ran}")
    rec["ray_check"] = ray_check(c.integrator.tracer(scene), args.check_rays, args.seed)
    rec["ours_build_s"] = float(c.stats.build_s)
    rec["ours_trace_s"] = float(c.stats.trace_s or 0.0)
    if any(c.nonfinite):
        rec["notes"].append(f"NaN/Inf pixels set to 0: stock {c.nonfinite[0]}, ours {c.nonfinite[1]}")
    v = c.verdict.same_seed["values"]
    rec["same_seed"] = {"frac_within_1e-3": v["frac_within"], "mean_abs": v["mean_abs"], "mean_ref": v["mean_ref"],
                        "max_abs": v["max_abs"], "channels": int(c.stock.shape[-1])}
    rec["metrics"] = c.metrics
    rec["verdict"] = c.verdict.as_dict()
    rec["result"] = c.verdict.label if c.verdict.label == SAME_PATHS else f"{c.verdict.label}: {c.verdict.summary()}"
    return rec


# ------------------------------------------------------------------------------------------------
# Driver
# ------------------------------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", default=str(ROOT.parent / "shared" / "assets"),
                   help="folder holding the third-party scenes (default: ../shared/assets from the repo root)")
    p.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES), metavar="GLOB[@INTEGRATOR]",
                   help="scene files or globs relative to --root (default: the task's list); GLOB@INTEGRATOR "
                        "renders them with that integrator (ptracer, prb, ...) at the scene's own depths")
    p.add_argument("--res", type=int, nargs=2, default=[64, 48], metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--traversal", default="layer_sorted",
                   help="per_ray | layer_sorted | layer_unsorted | auto (default layer_sorted)")
    p.add_argument("--media-traversal", default=layerbvh.AUTO,
                   help="the traversal of scenes with participating media (volpath, volpathmis; default auto, "
                        "which runs them per_ray in one megakernel: the wavefront loop is 8-126x slower there)")
    p.add_argument("--check-rays", type=int, default=200_000,
                   help="random rays traced by ours and Embree over each scene's triangles (0: skip)")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per scene (default 300)")
    p.add_argument("--md", help="also write the markdown table here (atomically)")
    p.add_argument("--json", help="write the raw figures here as JSON (atomically)")
    p.add_argument("--readme", action="store_true",
                   help="also splice the table into docs/scenes.md (section third_party)")
    p.add_argument("--out", default=str(ROOT / "out" / "third_party"),
                   help="the sweep folder (points, results.csv, summary.md, index.html; default out/third_party)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="processes of a local Dask cluster (default: cores)")
    where.add_argument("--scheduler", help="an existing Dask scheduler (address or scheduler file)")
    p.add_argument("--rerun", action="store_true", help="run every scene again, ignoring stored results")
    return p


def _find_scenes(root: Path, patterns) -> tuple[list[tuple[Path, str | None]], list[str]]:
    """(scene file, integrator or None) for each file a GLOB or GLOB@INTEGRATOR names, in order."""
    found, missing = [], []
    for pat in patterns:
        glob_, _, integrator = pat.partition("@")
        hits = sorted(Path(h) for h in glob.glob(str(root / glob_)) if Path(h).is_file())
        if not hits:
            missing.append(pat)
        for h in hits:
            if (h, integrator or None) not in found:
                found.append((h, integrator or None))
    return found, missing


def _record(stored: dict | None) -> dict:
    """A scene's row from its sweep result: run_worker's record, or the reason there is none."""
    if stored is None:
        return {"result": "not run (sweep interrupted)", "notes": []}
    if stored["status"] == "ok":
        return {**stored["figures"], "wall_s": stored["wall_s"], "host": stored["host"]}
    error = stored["error"]  # killed/crashed say so; an exception inside run_worker is a crash too
    return {"result": error if stored["status"] != "error" else f"crashed: {error}", "notes": [],
            "wall_s": stored["wall_s"], "host": stored["host"]}


def _shown(path: str) -> str:
    """A path relative to the repository when it lies near it (README tables stay machine-independent)."""
    return os.path.relpath(path, ROOT) if Path(path).is_relative_to(ROOT.parent) else path


def _fmt(x, spec):
    return "-" if x is None else format(x, spec)


def _markdown(cmdline: str, args, rows, missing, total: str) -> str:
    lines = [f"`{cmdline}`", "",
             f"Stock vs ours (traversal `{args.traversal}`; scenes with media `{args.media_traversal}`) in the "
             f"scene's own integrator where ours mirrors it (`path`, `direct`, `volpath`, `volpathmis`, an "
             f"`aov`/`moment` wrapper around them: ours inside), any other compared as path "
             f"(the notes say so); a scene@integrator row renders the scene with that integrator (ptracer, prb, "
             f"...) at the scene's own depths; same seed {args.seed}, "
             f"{args.spp} spp, {args.res[0]}x{args.res[1]}, variant `{args.variant}`, root `{_shown(args.root)}`. "
             f"within 1e-3 = share of pixels whose every channel differs by <= 1e-3; FLIP/rel_mse from "
             f"`metrics.compare_images`; rays: of --check-rays random rays through the scene's triangles, how many "
             f"get another triangle from ours than from Embree, and in brackets how many of those are ties: both "
             f"triangles at the same distance (float64) up to float32 resolution of the coordinates (shared edges, "
             f"coplanar overlapping triangles), where either answer is right; seconds are each side's render without "
             f"kernel compilation (`ab.compare`) and, with several sweep workers on one machine, scenes rendering "
             f"side by side on its cores.", "",
             "| scene | triangles | other shapes | compared as | result | within 1e-3 | mean abs | max abs | FLIP mean "
             "| rel_mse | rays: other prim (ties) | stock s | ours s | notes |",
             "|---|---:|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        ss, m = r.get("same_seed") or {}, r.get("metrics") or {}
        frac = ss.get("frac_within_1e-3")
        notes = "; ".join(r.get("notes") or []) or ""
        rc = r.get("ray_check")
        rays = "-" if not rc else f"{rc['other_prim']} ({rc['ties']}) of {rc['rays'] // 1000}k"
        result = r["result"]
        if result.startswith("refused") and " is not supported" in result:
            result = result[:result.index(" is not supported")] + " is not supported"
        cells = [f"`{r['scene']}`", _fmt(r.get("triangles"), ","), r.get("other_shapes", "-"),
                 r.get("compared_as") or "-", result.replace("|", "\\|"),
                 "-" if frac is None else f"{100 * frac:.2f}%",
                 _fmt(ss.get("mean_abs"), ".2e"), _fmt(ss.get("max_abs"), ".2e"),
                 _fmt(m.get("flip_mean"), ".2e"), _fmt(m.get("rel_mse"), ".2e"), rays,
                 _fmt(r.get("stock_s"), ".2f"), _fmt(r.get("ours_s"), ".2f"), notes.replace("|", "\\|")]
        lines.append("| " + " | ".join(cells) + " |")
    for pat in missing:
        lines.append(f"\nNot found under root (skipped): `{pat}`")
    lines.append(f"\nTotal: {len(rows)} scenes in {total}.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    cmdline = shlex.join(getattr(sys, "orig_argv", [sys.executable, *sys.argv]))
    args.root = str(Path(args.root).resolve())
    for flag, value in (("--traversal", args.traversal), ("--media-traversal", args.media_traversal)):
        if value not in layerbvh.TRACE_MODES:
            print(f"third_party: {flag} must be one of {', '.join(layerbvh.TRACE_MODES)}, got {value}",
                  file=sys.stderr)
            return 2
    if args.workers is not None and args.workers < 1:
        print(f"third_party: --workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 2
    root = Path(args.root)
    if not root.is_dir():
        print(f"third_party: root folder not found: {root}", file=sys.stderr)
        return 2
    scenes, missing = _find_scenes(root, args.scenes)
    for pat in missing:
        print(f"note: {pat} not found under {root}; skipped", file=sys.stderr)
    settings = {"traversal": args.traversal, "media_traversal": args.media_traversal, "res": list(args.res),
                "spp": args.spp, "seed": args.seed, "variant": args.variant, "check_rays": args.check_rays}
    points = [p for s, integ in scenes for p in make_points(
        "third_party", [(str(s), s.relative_to(root).as_posix() + (f"@{integ}" if integ else ""))],
        [settings if integ is None else {**settings, "integrator": integ}])]
    workers = None if args.scheduler else (args.workers or os.cpu_count() or 1)
    try:
        sweep = run_sweep(points, args.out, workers=workers, scheduler=args.scheduler, rerun=args.rerun,
                          limits=Limits(timeout_s=args.timeout, slots=workers or 1), command=cmdline)
    except UserError as e:
        print(f"third_party: {e}", file=sys.stderr)
        return 2
    rows = [{"scene": p.name, **_record(r)} for p, r in zip(points, sweep.results)]
    for r in rows:
        print(f"{r['scene']}: {r['result']}", file=sys.stderr)
    reused = len(points) - len(sweep.ran)
    where = f"scheduler {args.scheduler}" if args.scheduler else f"{workers} local worker{'s' * (workers > 1)}"
    total = (f"{sweep.wall_s:.1f} s (sweep wall time, {where}"
             + (f"; {reused} scenes reused from {_shown(str(sweep.out))}" if reused else "") + ")")
    md = _markdown(cmdline, args, rows, missing, total)
    sys.stdout.write(md)
    if args.md:
        atomic.write_text(args.md, md)
    if args.readme:
        from update_readme import readme_body  # local: a script module, on sys.path only when run from scripts/
        atomic.splice_section(ROOT / "docs" / "scenes.md", "third_party", readme_body(md))
    if args.json:
        raw = {"command": cmdline, "root": args.root, "res": args.res, "spp": args.spp, "seed": args.seed,
               "traversal": args.traversal, "media_traversal": args.media_traversal, "variant": args.variant,
               "timeout_s": args.timeout,
               "total_s": sweep.wall_s, "sweep": str(sweep.out), "cluster": sweep.cluster, "reused": reused,
               "missing": missing, "scenes": rows}
        atomic.write_text(args.json, json.dumps(raw, indent=2) + "\n")
    return 130 if sweep.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
