"""The `layerbvh` command line: render a Mitsuba XML scene with our traversal, or A/B-compare it against stock
Mitsuba."""
from __future__ import annotations

import argparse
import contextlib
import errno
import os
import shlex
import signal
import sys
import tempfile
import traceback
from pathlib import Path

import numpy as np

import layerbvh
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.compare import (
    STATS_SPP,
    CompareSettings,
    ComparisonFailed,
    check_memory_for,
    compare,
    ours_props,
    wrapped,
)
from layerbvh_mitsuba.ab.render import (UserError, check_seed, check_spp, load_integrator, load_scene,
    render_channels, render_passes, scene_spp, use_variant, write_exr)
from layerbvh_mitsuba.ab.scene_integrator import SUPPORTED, path_settings
from layerbvh_mitsuba.ab.report import REPORT_MARKER, heatmap_png, write_comparison
from layerbvh_mitsuba.runtime.scene_geometry import UnsupportedShapeError
from layerbvh_mitsuba.runtime.settings import CHOICES, Traversal, check_traversal_settings
from layerbvh_mitsuba.tools import converge
from layerbvh_mitsuba.tools.bench import locality
from layerbvh_mitsuba.tools.sweep import grid as sweep

AS_PATH_HELP = (f"the scene's integrator is none of {SUPPORTED} (the projective integrators, volprim_rf_basic, ...): "
                "render both sides with path anyway, with the settings read from it where it has them (without this, "
                "such a scene is refused)")


# Options that several commands take, declared once (issue 42).
def _scene_and_film(sp) -> None:
    sp.add_argument("scene", help="Mitsuba 3 XML scene")
    sp.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), help="film resolution (default: the scene's)")


def _tree(sp) -> None:
    sp.add_argument("--leaf-size", type=int, help="triangles per BVH leaf at most (default: 4 binary, 2 wide)")
    sp.add_argument("--branching", type=int, default=layerbvh.DEFAULT_BRANCHING,
                    help="children per BVH node: 2 (the paper's binary BVH), 4 or 8 (default %(default)s)")


def _session(sp) -> None:
    sp.add_argument("--variant", default="llvm_ad_rgb",
                    help="Mitsuba variant: any llvm_* or cuda_* (default %(default)s)")
    sp.add_argument("--as-path", action="store_true", help=AS_PATH_HELP)
    sp.add_argument("--no-progress", action="store_true")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="layerbvh", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        _scene_and_film(sp)
        sp.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
        sp.add_argument("--seed", type=int, default=0)
        sp.add_argument("--traversal", default=layerbvh.AUTO,
                        help=f"{' | '.join(CHOICES)} (embree: our loop, Mitsuba's queries: the control) "
                             f"(default %(default)s)")
        sp.add_argument("--treelet-height", type=int, default=layerbvh.DEFAULT_TREELET_HEIGHT,
                        help="levels of the BVH per treelet (default %(default)s)")
        _tree(sp)
        _session(sp)

    r = sub.add_parser("render", help="render with the layerbvh integrator to an EXR")
    common(r)
    r.add_argument("-o", "--output", required=True, help="output .exr")
    r.add_argument("--heatmap", action="store_true",
                   help="also write traversal-cost heat maps (OUT_heat_NAME.exr/.png: inner nodes, triangles and, in "
                        "the layer modes, wavefront steps per pixel sample; from a counted pass at up to 4 spp)")
    c = sub.add_parser("compare", help="A/B: stock path (Embree) vs layerbvh, with metrics and an HTML report")
    common(c)
    c.add_argument("--out", required=True, help="output folder")
    c.add_argument("--grad", metavar="KEY", help="also compare the derivatives with respect to the scene parameter "
                   "KEY (a mi.traverse key, e.g. red.reflectance.value), forward (an image) and backward (the "
                   "gradient of the image's sum), with the same two-step verdict; needs prb, prb_basic or prbvolpath")
    v = sub.add_parser("converge", help="error against run time: stock and layerbvh configurations at 1, 2, 4, ... spp "
                                        "within a time budget, scored against a cached stock reference")
    _scene_and_film(v)
    v.add_argument("--budget", type=float, required=True, help="seconds of rendering per configuration "
                   "(BVH build, compile and the reference are timed separately)")
    v.add_argument("--out", required=True, help="output folder (convergence.csv/.json/.png/.md)")
    v.add_argument("--configs", default="stock,embree,per_ray,layer_sorted",
                   help="comma list: stock, embree (our loop, Mitsuba's queries), auto, per_ray, layer_sorted[:H], "
                        "layer_unsorted[:H] (default %(default)s)")
    v.add_argument("--ref-spp", type=int, default=4096, help="spp of the stock reference (default %(default)s)")
    v.add_argument("--max-spp", type=int, help="stop doubling here even within budget (default ref spp / 16)")
    _tree(v)
    v.add_argument("--cache", help="reference cache folder (default $XDG_CACHE_HOME/layerbvh/references)")
    _session(v)
    sweep.add_parser(sub)
    locality.add_parser(sub)
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
        marker = {"compare": REPORT_MARKER, "locality": locality.OUTPUT_MARKER}.get(args.command,
                                                                                    converge.OUTPUT_MARKER)
        problem = atomic.check_output_folder(args.out, marker)
    if problem:
        raise UserError(problem)
    if args.command == "locality":
        try:
            locality.request_from_args(args)
        except ValueError as e:
            raise UserError(str(e)) from None
        return
    if args.command == "converge":
        try:
            layerbvh.check_param("branching", args.branching)
        except ValueError as e:
            raise UserError(f"--{e}") from None
        return
    check_spp(args.spp)
    check_seed(args.seed)
    try:  # the integrator's own rules, named as the option: "--treelet-height must ..."
        args.traversal = Traversal.parse(args.traversal)
        check_traversal_settings(treelet_height=args.treelet_height, leaf_size=args.leaf_size, batch_rays=1,
                                 branching=args.branching)
    except ValueError as e:
        name, _, rule = str(e).partition(" ")
        raise UserError(f"--{name.replace('_', '-')} {rule}") from None


def _settings(args) -> CompareSettings:
    """`render`'s and `compare`'s options, parsed once (`_check_args`)."""
    return CompareSettings(scene=args.scene, spp=args.spp, res=tuple(args.res) if args.res else None, seed=args.seed,
                           traversal=args.traversal, treelet_height=args.treelet_height, branching=args.branching,
                           leaf_size=args.leaf_size, as_path=args.as_path, control=True, statistics_pass=True,
                           progress=not args.no_progress, grad=getattr(args, "grad", None))


def cmd_render(mi, args) -> int:
    s = _settings(args)
    scene = load_scene(mi, args.scene, s.res)
    spp = s.spp or scene_spp(scene)
    path = path_settings(mi, scene, args.as_path, args.scene)
    integ = load_integrator(mi, ours_props(s, path))
    check_memory_for(scene, spp, integ)  # builds the BVH (and refuses unsupported shapes) first
    # In the scene's aov/moment wrapper where it has one: the EXR holds the wrapper's channels too.
    rendered = wrapped(mi, path, integ)
    img, secs = render_passes(mi, scene, rendered, spp, args.seed, "layerbvh", not args.no_progress)
    if not np.isfinite(img).all():
        raise UserError(f"render produced {int((~np.isfinite(img)).any(-1).sum())} NaN/Inf pixels; nothing written")
    write_exr(args.output, img, render_channels(rendered, img.shape[-1] if img.ndim == 3 else 1))
    st = integ.last_stats
    if args.heatmap:
        counted = load_integrator(mi, ours_props(s, path, stats=True))
        render_passes(mi, scene, wrapped(mi, path, counted), min(spp, STATS_SPP), args.seed, "heat maps",
                      not args.no_progress)
        stem = str(Path(args.output).with_suffix(""))
        for name, values in counted.heatmaps(scene).items():
            write_exr(f"{stem}_heat_{name}.exr", np.repeat(values[:, :, None].astype(np.float32), 3, 2))
            atomic.write_bytes(f"{stem}_heat_{name}.png", heatmap_png(values)[0])
    trace = f", trace {st.trace_s:.2f} s" if st.trace_s is not None else " (one kernel per pass)"
    print(f"wrote {args.output} ({img.shape[1]}x{img.shape[0]}, {spp} spp) in {secs:.2f} s; "
          f"BVH build {st.build_s:.2f} s{trace}")
    return 0


def cmd_compare(mi, args) -> int:
    """Stock and ours timed, our loop with Embree's queries (the control: splits our time into
    the loop's share and the traversal's), a counted pass for statistics, the verdict; the
    report folder."""
    c = compare(mi, _settings(args))
    write_comparison(args.out, c)
    print(c.summary())
    print(f"verdict: {c.verdict.label} ({c.verdict.summary()})")
    if c.gradient is not None:
        print(f"gradient verdict: {c.gradient.label} ({c.gradient.summary()})")
    if c.referee is not None:
        print(c.referee if isinstance(c.referee, str) else c.referee.line())
    print(str(Path(args.out).resolve() / "index.html"))
    return 0


def disk_full(e: BaseException) -> bool:
    """Whether `e` (or what caused it) is a write that found no space on the device: Python
    says ENOSPC, Mitsuba's streams "No space left on device" in a RuntimeError."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if (isinstance(e, OSError) and e.errno == errno.ENOSPC) or "no space left on device" in str(e).lower():
            return True
        e = e.__cause__ or e.__context__
    return False


class Terminated(KeyboardInterrupt):
    """SIGTERM (a job scheduler's stop, `kill`), handled as Ctrl-C: what is stored is kept, the
    rest stops in order (issue 56). Exit 143 (128 + SIGTERM), as a shell reports it."""


_sigterms = 0  # SIGTERMs received (a sweep catches the interrupt itself: main reads this)


def _on_sigterm(signum, frame):
    global _sigterms
    _sigterms += 1
    raise Terminated


@contextlib.contextmanager
def _sigterm_as_ctrl_c():
    """While a command runs, SIGTERM raises Terminated in the main thread (between Python steps:
    a render pass ends first); the earlier handler comes back after it (main() also runs inside
    tests)."""
    try:
        old = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    args.command_line = "layerbvh " + shlex.join(sys.argv[1:] if argv is None else argv)  # what outputs quote
    sigterms = _sigterms
    try:
        with _sigterm_as_ctrl_c():
            rc = _run(args)
        # (a sweep stops its points on the interrupt itself and returns 130)
        return 143 if rc == 130 and _sigterms > sigterms else rc
    except BrokenPipeError:  # `layerbvh compare ... | head`: the reader left; outputs were written before
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (Python's flush at exit would fail again)
        return 141  # 128 + SIGPIPE, as a shell reports a command killed by a closed pipe
    except KeyboardInterrupt:  # Ctrl-C: outputs are written whole at the end, so nothing is left
        if not getattr(args, "no_progress", True):
            # A bar interrupted while it draws is never cleared: end its line (on a terminal, erase it).
            sys.stderr.write("\r\033[K" if sys.stderr.isatty() else "\n")
        print("layerbvh: interrupted; nothing written", file=sys.stderr)
        return 143 if _sigterms > sigterms else 130
    except Exception as e:  # a bug, not bad input: one line, the traceback kept in a file
        if disk_full(e):  # the user's disk, not our bug (the file was a temporary sibling: name the output)
            where = getattr(args, "out", None) or getattr(args, "output", None) or "the output"
            print(f"layerbvh: error: no space left on device writing {where}; nothing written", file=sys.stderr)
            return 2
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
            return sweep.run_command(args)
        _check_args(args)
        mi = use_variant(args.variant)
        try:
            try:
                if args.command == "converge":
                    converge.run(mi, converge.settings_from_args(args))
                    return 0
                if args.command == "locality":
                    return locality.run(mi, args, args.command_line)
                return cmd_render(mi, args) if args.command == "render" else cmd_compare(mi, args)
            except ComparisonFailed as e:
                raise e.error  # the user's error or our bug, as if no comparison wrapped it
        except UnsupportedShapeError as e:
            raise UserError(str(e)) from None
        except ValueError as e:
            raise UserError(str(e)) from None
    except UserError as e:
        print(f"layerbvh: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
