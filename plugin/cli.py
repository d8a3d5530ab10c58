"""The `layerbvh` command line: render a Mitsuba XML scene with our traversal, or A/B-compare it against stock Mitsuba."""
from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

import numpy as np

import layerbvh

from . import atomic
from .render import (UserError, check_memory, load_integrator, load_scene, path_settings, render_passes, scene_spp, timed_render,
                     use_variant, write_exr)



AS_PATH_HELP = ("the scene's integrator is not path (volpath, direct, a moment/aov wrapper, ...): render both sides "
                "with path anyway, with the settings read from it where it has them (without this, such a scene "
                "is refused)")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="layerbvh", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("scene", help="Mitsuba 3 XML scene")
        sp.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
        sp.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), help="film resolution (default: the scene's)")
        sp.add_argument("--seed", type=int, default=0)
        sp.add_argument("--traversal", default="auto",
                        help="auto | per_ray | layer_sorted | layer_unsorted | embree (our loop, Mitsuba's queries: "
                             "the control) (default auto)")
        sp.add_argument("--treelet-height", type=int, default=layerbvh.DEFAULT_TREELET_HEIGHT,
                        help="levels of the BVH per treelet (default %(default)s)")
        sp.add_argument("--leaf-size", type=int, help="triangles per BVH leaf at most (default: 4 binary, 2 wide)")
        sp.add_argument("--branching", type=int, default=layerbvh.DEFAULT_BRANCHING,
                        help="children per BVH node: 2 (the paper's binary BVH), 4 or 8 (default %(default)s)")
        sp.add_argument("--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant: any llvm_* or cuda_* (default %(default)s)")
        sp.add_argument("--as-path", action="store_true", help=AS_PATH_HELP)
        sp.add_argument("--no-progress", action="store_true")

    r = sub.add_parser("render", help="render with the layerbvh integrator to an EXR")
    common(r)
    r.add_argument("-o", "--output", required=True, help="output .exr")
    r.add_argument("--heatmap", action="store_true",
                   help="also write traversal-cost heat maps (OUT_heat_NAME.exr/.png: inner nodes, triangles and, in "
                        "the layer modes, wavefront steps per pixel sample; from a counted pass at up to 4 spp)")
    c = sub.add_parser("compare", help="A/B: stock path (Embree) vs layerbvh, with metrics and an HTML report")
    common(c)
    c.add_argument("--out", required=True, help="output folder")
    v = sub.add_parser("converge", help="error against run time: stock and layerbvh configurations at 1, 2, 4, ... spp "
                                        "within a time budget, scored against a cached stock reference")
    v.add_argument("scene", help="Mitsuba 3 XML scene")
    v.add_argument("--budget", type=float, required=True, help="seconds of rendering per configuration "
                   "(BVH build, compile and the reference are timed separately)")
    v.add_argument("--out", required=True, help="output folder (convergence.csv/.json/.png/.md)")
    v.add_argument("--configs", default="stock,embree,per_ray,layer_sorted",
                   help="comma list: stock, embree (our loop, Mitsuba's queries), auto, per_ray, layer_sorted[:H], "
                        "layer_unsorted[:H] (default %(default)s)")
    v.add_argument("--ref-spp", type=int, default=4096, help="spp of the stock reference (default %(default)s)")
    v.add_argument("--max-spp", type=int, help="stop doubling here even within budget (default ref spp / 16)")
    v.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), help="film resolution (default: the scene's)")
    v.add_argument("--leaf-size", type=int, help="triangles per BVH leaf at most (default: 4 binary, 2 wide)")
    v.add_argument("--branching", type=int, default=layerbvh.DEFAULT_BRANCHING,
                   help="children per BVH node of the layerbvh configurations: 2, 4 or 8 (default %(default)s)")
    v.add_argument("--cache", help="reference cache folder (default $XDG_CACHE_HOME/layerbvh/references)")
    v.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant: any llvm_* or cuda_* (default %(default)s)")
    v.add_argument("--as-path", action="store_true", help=AS_PATH_HELP)
    v.add_argument("--no-progress", action="store_true")
    from .bench.locality import add_parser as add_locality
    from .sweep import add_parser as add_sweep
    add_sweep(sub)
    add_locality(sub)
    return p


def _check_args(args):
    scene = Path(args.scene)
    if scene.is_dir():
        raise UserError(f"scene {args.scene} is a directory, not an XML file")
    if not scene.is_file():
        raise UserError(f"scene file not found: {args.scene}")
    if args.res is not None and min(args.res) < 1:
        raise UserError(f"--res must be positive, got {args.res[0]} {args.res[1]}")
    # Outputs are checked before any work: a run never renders for minutes to fail on its output.
    if args.command == "render":
        if not args.output.endswith(".exr"):
            raise UserError(f"-o must name an .exr file, got {args.output}")
        problem = atomic.check_output_file(args.output)
    else:
        from .bench.locality import OUTPUT_MARKER as LOCALITY_MARKER
        from .converge import OUTPUT_MARKER
        from .report import REPORT_MARKER
        marker = {"compare": REPORT_MARKER, "locality": LOCALITY_MARKER}.get(args.command, OUTPUT_MARKER)
        problem = atomic.check_output_folder(args.out, marker)
    if problem:
        raise UserError(problem)
    if args.command == "locality":
        from .bench.locality import request_from_args
        try:
            request_from_args(args)
        except ValueError as e:
            raise UserError(str(e)) from None
        return
    if args.command == "converge":
        try:
            layerbvh.check_param("branching", args.branching)
        except ValueError as e:
            raise UserError(f"--{e}") from None
        return
    if args.spp is not None and args.spp < 1:
        raise UserError(f"--spp must be >= 1, got {args.spp}")
    from .integrator import check_settings
    try:
        check_settings(max_depth=-1, rr_depth=5, traversal=args.traversal, treelet_height=args.treelet_height,
                       leaf_size=args.leaf_size, batch_rays=1, branching=args.branching)
    except ValueError as e:  # the integrator's own rule, named as the option: "--treelet-height must ..."
        name, _, rule = str(e).partition(" ")
        raise UserError(f"--{name.replace('_', '-')} {rule}") from None


def _check_memory(scene, spp: int, integ) -> None:
    """Refuse (one line) a render that would not fit in memory, before it starts."""
    size = scene.sensors()[0].film().crop_size()
    tracer = integ.tracer(scene)
    work = 0
    if tracer is not None:
        st = tracer.bvh.stats
        rays = min(int(size[0]) * int(size[1]) * spp, tracer.bvh.batch_rays)
        work = st.total_bytes + rays * ((st.branching - 1) * st.depth * 8 + 150)  # entry stacks + ray state
    check_memory(int(size[0]), int(size[1]), spp, "megakernel" if integ.megakernel(tracer) else "wavefront", work)


def _ours_props(args, props, stats=False, traversal=None) -> dict:
    """The layerbvh integrator's properties for these options and path settings."""
    return {"traversal": traversal or args.traversal, "treelet_height": args.treelet_height,
            "branching": args.branching, "stats": stats, **props,
            **({} if args.leaf_size is None else {"leaf_size": args.leaf_size})}


def _ours(mi, args, props, stats=False, traversal=None):
    return load_integrator(mi, {"type": "layerbvh", **_ours_props(args, props, stats, traversal)})


STATS_SPP = 4  # spp of the separate counted pass (statistics, heat maps: work per ray needs few samples)


def cmd_render(mi, args) -> int:
    scene = load_scene(mi, args.scene, args.res)
    spp = args.spp or scene_spp(scene)
    props = path_settings(mi, scene, args.as_path).props
    integ = _ours(mi, args, props)
    _check_memory(scene, spp, integ)  # builds the BVH (and refuses unsupported shapes) first
    img, secs = render_passes(mi, scene, integ, spp, args.seed, "layerbvh", not args.no_progress)
    if not np.isfinite(img).all():
        raise UserError(f"render produced {int((~np.isfinite(img)).any(-1).sum())} NaN/Inf pixels; nothing written")
    write_exr(args.output, img)
    st = integ.last_stats
    if args.heatmap:
        from .report import heatmap_png
        counted = _ours(mi, args, props, stats=True)
        render_passes(mi, scene, counted, min(spp, STATS_SPP), args.seed, "heat maps", not args.no_progress)
        stem = str(Path(args.output).with_suffix(""))
        for name, values in counted.heatmaps(scene).items():
            write_exr(f"{stem}_heat_{name}.exr", np.repeat(values[:, :, None].astype(np.float32), 3, 2))
            atomic.write_bytes(f"{stem}_heat_{name}.png", heatmap_png(values)[0])
    trace = f", trace {st['trace_s']:.2f} s" if st.get("trace_s") is not None else " (one kernel per pass)"
    print(f"wrote {args.output} ({img.shape[1]}x{img.shape[0]}, {spp} spp) in {secs:.2f} s; "
          f"BVH build {st.get('build_s', 0):.2f} s{trace}")
    return 0


def cmd_compare(mi, args) -> int:
    from .integrator import EMBREE
    from .report import write_report
    from .verdict import judge
    scene = load_scene(mi, args.scene, args.res)
    spp = args.spp or scene_spp(scene)
    path = path_settings(mi, scene, args.as_path)
    props = path.props
    stock = load_integrator(mi, {"type": "path", **props})
    ours = _ours(mi, args, props)
    _check_memory(scene, spp, ours)  # builds the BVH (and refuses unsupported shapes) first
    progress = not args.no_progress
    # Timed renders without work counters: what a user's render costs. Our loop with Embree's
    # queries (the control) splits our time into the loop's share and the traversal's.
    st = timed_render(mi, scene, stock, spp, args.seed, "stock path", progress)
    control = None
    if args.traversal != EMBREE:
        control = timed_render(mi, scene, _ours(mi, args, props, traversal=EMBREE), spp, args.seed,
                               "layerbvh loop + Embree", progress)
    ou = timed_render(mi, scene, ours, spp, args.seed, "layerbvh", progress)
    run = dict(ours.last_stats)
    features = run.pop("features")
    # Traversal statistics from a separate counted pass (counters cost time; reported apart).
    counted = _ours(mi, args, props, stats=True)
    stats_spp = min(spp, STATS_SPP)
    cs = timed_render(mi, scene, counted, stats_spp, args.seed, "statistics pass", progress)
    heatmaps = counted.heatmaps(scene)
    traversal = {k: v for k, v in counted.last_stats.items() if k != "features"}
    bvh = run.get("bvh", {})

    def side(r):
        return {"render_s": r.seconds, "compile_s": r.compile_s, "wall_s": r.wall_s}
    info = {
        "scene": str(args.scene), "spp": spp, "resolution": [int(ou.image.shape[1]), int(ou.image.shape[0])],
        "seed": args.seed, "variant": mi.variant(), "integrator": props,
        "scene_integrator": path.scene_integrator, "compared_as": "path" + (" (--as-path)" if path.as_path else ""),
        **({"compared_as_note": path.note} if path.note else {}),
        "stock": side(st),
        "ours": {**side(ou), "calibration_s": ou.calibration_s, "build_s": run.get("build_s", 0.0),
                 "kernel_load_s": bvh.get("kernel_load_s", 0.0), "loop": run.get("loop"),
                 "trace_s": run.get("trace_s"), "shading_s": run.get("shading_s"), "traversal": args.traversal,
                 "treelet_height": args.treelet_height, "branching": args.branching},
        "auto_choices": run.get("auto_choices", {}),
        "traversal": traversal,
        "statistics_pass": {"spp": stats_spp, "render_s": cs.seconds, "compile_s": cs.compile_s},
        "features": features,
    }
    if control is not None:
        info["embree_control"] = side(control)
        info["split"] = {"loop_s": control.seconds - st.seconds, "traversal_s": ou.seconds - control.seconds,
                         "ours_over_stock": ou.seconds / st.seconds if st.seconds else None}
    # The verdict: same seed, and where same-seed paths diverged, independent seeds.
    judged = judge(mi, args.scene, st.image, ou.image, spp, props, _ours_props(args, props))
    rep = write_report(args.out, st.image, ou.image, info, heatmaps, judged)
    m = rep["metrics"]
    ratio = f" ({ou.seconds / st.seconds:.1f}x)" if st.seconds else ""
    split = (f"; our loop with Embree {control.seconds:.2f} s: traversal {ou.seconds - control.seconds:.2f} s, "
             f"loop {control.seconds - st.seconds:.2f} s") if control is not None else ""
    print(f"stock {st.seconds:.2f} s, layerbvh {ou.seconds:.2f} s{ratio}{split} (not counted: build "
          f"{info['ours']['build_s']:.2f} s, compile {ou.compile_s:.2f} s, calibration {ou.calibration_s:.2f} s); "
          f"rmse {m['rmse']:.3g}, FLIP {m['flip_mean']:.3g}, pixels > 1e-3: {100 * m['frac_pixels_over_1e-3']:.3f}%")
    print(f"verdict: {judged.label} ({judged.summary()})")
    print(str(Path(args.out).resolve() / "index.html"))
    return 0


def disk_full(e: BaseException) -> bool:
    """Whether `e` (or what caused it) is a write that found no space on the device: Python
    says ENOSPC, Mitsuba's streams "No space left on device" in a RuntimeError."""
    import errno
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if (isinstance(e, OSError) and e.errno == errno.ENOSPC) or "no space left on device" in str(e).lower():
            return True
        e = e.__cause__ or e.__context__
    return False


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    args.command_line = "layerbvh " + shlex.join(sys.argv[1:] if argv is None else argv)  # what outputs quote
    try:
        return _run(args)
    except KeyboardInterrupt:  # Ctrl-C: outputs are written whole at the end, so nothing is left
        if not getattr(args, "no_progress", True):
            # A bar interrupted while it draws is never cleared: end its line (on a terminal, erase it).
            sys.stderr.write("\r\033[K" if sys.stderr.isatty() else "\n")
        print("layerbvh: interrupted; nothing written", file=sys.stderr)
        return 130
    except Exception as e:  # a bug, not bad input: one line, the traceback kept in a file
        if disk_full(e):  # the user's disk, not our bug (the file was a temporary sibling: name the output)
            where = getattr(args, "out", None) or getattr(args, "output", None) or "the output"
            print(f"layerbvh: error: no space left on device writing {where}; nothing written", file=sys.stderr)
            return 2
        import tempfile
        import traceback
        fd, log = tempfile.mkstemp(prefix="layerbvh-error-", suffix=".txt")
        with os.fdopen(fd, "w") as fh:
            traceback.print_exc(file=fh)
        first = (str(e).strip().splitlines() or [""])[0]
        print(f"layerbvh: internal error (please report it): {type(e).__name__}: {first}; traceback in {log}",
              file=sys.stderr)
        return 1


def _run(args) -> int:
    try:
        if args.command == "sweep":  # checks its own options; Mitsuba runs in the points' processes only
            from .sweep import run_command as sweep
            return sweep(args)
        _check_args(args)
        mi = use_variant(args.variant)
        from .adapter import UnsupportedShapeError
        try:
            if args.command == "converge":
                from .converge import run as converge
                converge(mi, args)
                return 0
            if args.command == "locality":
                from .bench.locality import run as locality
                return locality(mi, args, args.command_line)
            return cmd_render(mi, args) if args.command == "render" else cmd_compare(mi, args)
        except UnsupportedShapeError as e:
            raise UserError(str(e)) from None
        except ValueError as e:
            raise UserError(str(e)) from None
    except UserError as e:
        print(f"layerbvh: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
