"""`layerbvh sweep`: a grid of scenes × configurations run as Dask tasks, each point in a fresh process, resumable by
a content key, gathered into one table."""
from __future__ import annotations

import glob
import os
import shlex
import sys
from pathlib import Path
from types import SimpleNamespace

import mitsuba as mi

import layerbvh
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import UserError, check_seed, check_spp
from layerbvh_mitsuba.runtime import record
from layerbvh_mitsuba.runtime.settings import EMBREE, Traversal, check_traversal_settings
from layerbvh_mitsuba.tools.bench.locality import (
    DEFAULT_CAP,
    DEFAULT_KINDS,
    DEFAULT_PRESETS,
    DEFAULT_SPP,
    request_from_args,
)
from layerbvh_mitsuba.tools.converge import ConvergeError, parse_configs
from layerbvh_mitsuba.tools.sweep.slurm import JOB_SCRIPT, SlurmSettings, check
from layerbvh_mitsuba.tools.sweep.store import CLI_JOBS, GENERATED_RAYS, JOBS, RUNS_FILE, make_points
from layerbvh_mitsuba.tools.sweep.runner import DEFAULT_TIMEOUT_S, Limits, MEMORY_SHARE, run_sweep

# -- the command ------------------------------------------------------------------------------------


def _int_list(text: str, option: str) -> list[int]:
    try:
        vals = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"{option} must be a comma list of integers, got {text!r}") from None
    if not vals:
        raise UserError(f"{option} is empty")
    return vals


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def add_parser(sub) -> None:
    """The `sweep` sub-command of `layerbvh` (cli.py)."""
    s = sub.add_parser("sweep", help="a grid of scenes x configurations on Dask (local processes or a cluster), "
                                     "resumable, one results table")
    s.add_argument("scenes", nargs="+", metavar="SCENE_OR_GLOB", help="Mitsuba 3 XML scenes (globs are expanded)")
    s.add_argument("--job", required=True, choices=CLI_JOBS,
                   help="compare: stock vs layerbvh A/B per traversal and treelet height; converge: error against "
                        "time per configuration (timed); bench: traversal throughput on the scene's triangles (timed); "
                        "locality: memory transactions and cache hits of the scene's recorded rays per mode (a model, "
                        "untimed)")
    s.add_argument("--out", required=True, help="sweep folder: results.csv/.json, summary.md, index.html, points/")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="worker processes of a local Dask cluster (default: cores)")
    where.add_argument("--scheduler",
                       help="an existing Dask scheduler: ADDRESS (tcp://host:port) or its scheduler file")
    where.add_argument("--cluster", choices=("slurm",), help="slurm: the workers as SLURM jobs (dask-jobqueue; the "
                                                            "--slurm-* options), started and ended by the sweep")
    s.add_argument("--slurm-partition", help="slurm: partition (sbatch -p; default: the cluster's default)")
    s.add_argument("--slurm-account", help="slurm: account to charge (sbatch -A)")
    s.add_argument("--slurm-cores", type=int, default=1, help="slurm: cores per job; untimed points run one per core "
                                                              "(default %(default)s)")
    s.add_argument("--slurm-memory", type=float, default=4.0, metavar="GIB", help="slurm: memory per job in GiB "
                                                                                  "(default %(default)g)")
    s.add_argument("--slurm-walltime", default="01:00:00", help="slurm: time limit per job, [D-]HH:MM:SS (default "
                                                                "%(default)s); a point that would outlast its job "
                                                                "fails with a line naming it")
    s.add_argument("--slurm-jobs", type=int, default=1, help="slurm: jobs (workers) to run at once (default "
                                                            "%(default)s; with --slurm-adapt-min, the most)")
    s.add_argument("--slurm-adapt-min", type=int, help="slurm: scale adaptively between this many jobs and "
                                                       "--slurm-jobs (jobs end when idle)")
    s.add_argument("--slurm-extra", action="append", default=[], metavar="DIRECTIVE",
                   help="slurm: one more #SBATCH directive, e.g. --slurm-extra=--constraint=avx512 (repeatable)")
    s.add_argument("--spp", help="compare: spp, comma list (default: the scene's); bench: spp of the ray recording "
                                 "(default 4)")
    s.add_argument("--res", type=int, nargs=2, metavar=("W", "H"),
                   help="film resolution (default: the scene's; bench recordings 512 512)")
    s.add_argument("--seed", type=int, default=None, help="compare, bench: seed (default 0)")
    s.add_argument("--traversal", help="compare: comma list of auto, per_ray, layer_sorted, layer_unsorted, embree "
                                       "(default auto)")
    s.add_argument("--treelet-heights", help=f"compare, bench: comma list (default "
                                             f"{layerbvh.DEFAULT_TREELET_HEIGHT}; bench 4,8,12)")
    s.add_argument("--branchings", help="compare, bench, locality: children per BVH node, comma list of 2, 4, 8 "
                                        f"(default {layerbvh.DEFAULT_BRANCHING})")
    s.add_argument("--configs", help="converge: comma list, one point each: stock, embree, auto, per_ray, "
                                     "layer_sorted:H, layer_unsorted:H (default stock,per_ray,layer_sorted)")
    s.add_argument("--budget", type=float, help="converge: seconds of rendering per configuration (required)")
    s.add_argument("--ref-spp", type=int, help="converge: spp of the stock reference (default 4096)")
    s.add_argument("--max-spp", type=int, help="converge: stop doubling here (default ref spp / 16)")
    s.add_argument("--rays", help=f"bench: comma list of ray sets, one point each: {', '.join(GENERATED_RAYS)} "
                                  f"(generated over the scene's triangles) or recorded kinds (camera, "
                                  f"first_bounce_diffuse, diffuse, glossy, specular, shadow) (default "
                                  f"{','.join(GENERATED_RAYS)})")
    s.add_argument("--ray-count", type=int, help="bench: rays per set (default 1,000,000); locality: rays recorded "
                                                 "per kind at most (default 1,000,000)")
    s.add_argument("--preset", help="locality: comma list of hardware presets (default gtx965m,h200,cpu)")
    s.add_argument("--warp", help="locality: comma list of warp widths (default: each preset's own)")
    s.add_argument("--sample", type=int, help="locality: replay at most N rays per kind (default: all)")
    s.add_argument("--segment", help="locality: comma list of transaction sizes in bytes (default: each preset's own)")
    s.add_argument("--runs", type=int, help="bench: timed runs per configuration (default 5)")
    s.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb, cuda_ad_rgb)")
    s.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S,
                   help="seconds per point; a point past it is killed and recorded (default %(default)g)")
    s.add_argument("--memory-limit", type=float, metavar="GIB",
                   help=f"resident memory per point in GiB; a point above it is killed and recorded (default "
                        f"{MEMORY_SHARE:g} x the host's RAM, divided among the local workers for untimed jobs)")
    s.add_argument("--rerun", action="store_true", help="run every point again, ignoring stored results")
    s.add_argument("--no-progress", action="store_true")


JOB_OPTIONS = {  # which options each job takes (an option given to another job is an error)
    "compare": {"spp", "res", "seed", "traversal", "treelet_heights", "branchings"},
    "converge": {"res", "configs", "budget", "ref_spp", "max_spp"},
    "bench": {"spp", "res", "seed", "treelet_heights", "branchings", "rays", "ray_count", "runs"},
    "locality": {"spp", "res", "seed", "treelet_heights", "branchings", "rays", "ray_count", "preset", "warp", "sample",
                 "segment"},
}
ALL_JOB_OPTIONS = set().union(*JOB_OPTIONS.values())


def expand_scenes(patterns: list[str]) -> list[tuple[str, str]]:
    """(path, name) of every scene: a path is taken as given, a glob is expanded (sorted)."""
    out = []
    for pat in patterns:
        if any(c in pat for c in "*?["):
            hits = sorted(h for h in glob.glob(pat, recursive=True) if Path(h).is_file())
            if not hits:
                raise UserError(f"no scene file matches {pat}")
        elif Path(pat).is_file():
            hits = [pat]
        else:
            raise UserError(f"scene file not found: {pat}")
        out += [(h, h) for h in hits if (h, h) not in out]
    return out


def grid(args) -> list[dict]:
    """The settings of every configuration the options ask for (one point per scene each)."""

    for opt in sorted(ALL_JOB_OPTIONS - JOB_OPTIONS[args.job]):
        if getattr(args, opt) is not None:
            raise UserError(f"--{opt.replace('_', '-')} does not apply to --job {args.job}")
    if args.variant not in mi.variants():
        raise UserError(f"--variant: Mitsuba variant {args.variant!r} is not available (choose one of "
                        f"{', '.join(mi.variants())})")
    if args.res is not None and min(args.res) < 1:
        raise UserError(f"--res must be positive, got {args.res[0]} {args.res[1]}")
    res = list(args.res) if args.res else None
    seed = 0 if args.seed is None else args.seed
    check_seed(seed)
    branchings = _int_list(args.branchings, "--branchings") if args.branchings else [layerbvh.DEFAULT_BRANCHING]
    for k in branchings:
        try:
            layerbvh.check_param("branching", k)
        except ValueError as e:
            raise UserError(f"--branchings: {e}") from None
    if args.job == "compare":
        spps = _int_list(args.spp, "--spp") if args.spp else [None]
        for s in spps:
            check_spp(s)
        traversals = _names(args.traversal or layerbvh.AUTO)
        heights = _int_list(args.treelet_heights, "--treelet-heights") if args.treelet_heights else \
            [layerbvh.DEFAULT_TREELET_HEIGHT]
        for t in traversals:
            for h in heights:
                try:
                    Traversal.parse(t)
                    check_traversal_settings(treelet_height=h, leaf_size=layerbvh.DEFAULT_LEAF_SIZE, batch_rays=1)
                except ValueError as e:
                    name, _, rule = str(e).partition(" ")
                    opt = "--treelet-heights" if name == "treelet_height" else f"--{name.replace('_', '-')}"
                    raise UserError(f"{opt} {rule}") from None
        return [{"traversal": t, "treelet_height": layerbvh.DEFAULT_TREELET_HEIGHT if t == EMBREE else h,
                 "branching": layerbvh.DEFAULT_BRANCHING if t == EMBREE else k,
                 "spp": spp, "res": res, "seed": seed, "variant": args.variant}
                for spp in spps for t in traversals for k in ([None] if t == EMBREE else branchings)
                for h in ([None] if t == EMBREE else heights)]
    if args.job == "converge":
        if args.budget is None:
            raise UserError("--job converge needs --budget SECONDS")
        if args.budget <= 0:
            raise UserError(f"--budget must be > 0 seconds, got {args.budget}")
        try:
            configs = parse_configs(args.configs or "stock,per_ray,layer_sorted")
        except ConvergeError as e:
            raise UserError(str(e)) from None
        return [{"config": c.name, "budget": args.budget, "ref_spp": args.ref_spp or 4096, "max_spp": args.max_spp,
                 "res": res, "variant": args.variant} for c in configs]
    if args.job == "locality":
        return _locality_grid(args, res, seed, branchings)
    kinds = _names(args.rays or ",".join(GENERATED_RAYS))
    for k in kinds:
        if k not in GENERATED_RAYS + record.KINDS:
            raise UserError(f"--rays: unknown ray set {k!r}; use {', '.join(GENERATED_RAYS + record.KINDS)}")
    heights = _int_list(args.treelet_heights or "4,8,12", "--treelet-heights")
    for h in heights:
        try:
            layerbvh.check_param("treelet_height", h)
        except ValueError as e:
            raise UserError(f"--treelet-heights: {e}") from None
    spp = _int_list(args.spp, "--spp") if args.spp else [4]
    if len(spp) != 1 or spp[0] < 1:
        raise UserError(f"--spp for --job bench is one value >= 1 (the recording's), got {args.spp}")
    for opt, val in (("--ray-count", args.ray_count), ("--runs", args.runs)):
        if val is not None and val < 1:
            raise UserError(f"{opt} must be >= 1, got {val}")
    # res and spp make the recording; generated ray sets do not depend on them (nor does their key)
    return [{"rays": k, "heights": heights, "branchings": branchings, "ray_count": args.ray_count or 1_000_000,
             "runs": args.runs or 5,
             "res": None if k in GENERATED_RAYS else res or [512, 512], "spp": None if k in GENERATED_RAYS else spp[0],
             "seed": seed, "variant": args.variant} for k in kinds]


def _locality_grid(args, res, seed: int, branchings: list[int]) -> list[dict]:
    """One point per recorded kind, treelet height and branching; each replays every mode x preset x warp."""


    opts = SimpleNamespace(scene="", res=res, spp=int(args.spp) if args.spp and args.spp.isdigit() else None,
                           seed=seed, rays=args.rays or ",".join(DEFAULT_KINDS), warp=args.warp,
                           preset=args.preset or ",".join(DEFAULT_PRESETS),
                           treelet_heights=args.treelet_heights or str(layerbvh.DEFAULT_TREELET_HEIGHT),
                           modes=",".join(layerbvh.MODES), leaf_size=None, sample=args.sample,
                           cap=args.ray_count or DEFAULT_CAP, no_check=False, segment=args.segment)
    if args.spp and not args.spp.isdigit():
        raise UserError(f"--spp for --job locality is one value >= 1 (the recording's), got {args.spp}")
    try:
        req = request_from_args(opts)
    except ValueError as e:
        raise UserError(str(e)) from None
    return [{"rays": k, "treelet_height": h, "presets": list(req.presets), "warps": list(req.warps or []) or None,
             "res": res, "spp": req.spp or DEFAULT_SPP, "seed": seed, "sample": req.sample, "ray_count": req.cap,
             "segments": list(req.segments) if req.segments else None, "variant": args.variant, "branching": b}
            for k in req.kinds for h in req.treelet_heights for b in branchings]


def run_command(args) -> int:
    """`layerbvh sweep ...` (cli.py dispatches here)."""
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.timeout <= 0:
        raise UserError(f"--timeout must be > 0 seconds, got {args.timeout:g}")
    if args.memory_limit is not None and args.memory_limit <= 0:
        raise UserError(f"--memory-limit must be > 0 GiB, got {args.memory_limit:g}")
    settings = grid(args)
    points = make_points(args.job, expand_scenes(args.scenes), settings)
    # A file, or a folder of the user's own files (no runs.json, nor the job script a SLURM sweep
    # writes before it: not a sweep's), is refused before any point runs: a sweep writes
    # index.html, results.csv and summary.md there (issue 56).
    problem = atomic.check_output_folder(args.out, (RUNS_FILE, JOB_SCRIPT))
    if problem:
        raise UserError(problem)
    slurm = None
    if args.cluster == "slurm":
        slurm = check(SlurmSettings(partition=args.slurm_partition, account=args.slurm_account, cores=args.slurm_cores,
                                    memory_gib=args.slurm_memory, walltime=args.slurm_walltime, jobs=args.slurm_jobs,
                                    adapt_min=args.slurm_adapt_min, extra=tuple(args.slurm_extra)))
    workers = None if args.scheduler or slurm else (args.workers or os.cpu_count() or 1)
    slots = 1 if JOBS[args.job].timed else (slurm.cores if slurm else (workers or 1))
    memory = args.memory_limit or (slurm.memory_gib * MEMORY_SHARE if slurm else None)  # a job's memory, shared
    limits = Limits(timeout_s=args.timeout, memory_bytes=int(memory * (1 << 30) / (slots if slurm and not
                    args.memory_limit else 1)) if memory else None, slots=slots)
    command = shlex.join(["layerbvh", *sys.argv[1:]]) if Path(sys.argv[0]).name == "layerbvh" else \
        shlex.join(getattr(sys, "orig_argv", sys.argv))
    res = run_sweep(points, args.out, workers=workers, scheduler=args.scheduler, limits=limits, rerun=args.rerun,
                    progress=not args.no_progress, command=command, slurm=slurm)
    done = sum(1 for r in res.results if r is not None)
    bad = len(res.failed)
    print(f"{len(points)} points: {len(points) - bad} ok, {bad} failed or not run; ran {len(res.ran)}, reused "
          f"{done - len(res.ran)}; {res.wall_s:.1f} s")
    print(str(res.out / "index.html"))
    if res.interrupted:
        print(f"layerbvh: interrupted; {done} of {len(points)} points stored, tables written", file=sys.stderr)
        return 130
    if bad:  # scripts and CI must notice; the table is written all the same
        print(f"layerbvh: {bad} of {len(points)} points failed (see {res.out / 'summary.md'})", file=sys.stderr)
        return 1
    return 0
